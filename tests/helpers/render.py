"""Small scenes for the renderer tests (tests/render/): AssetModels built in Python
(no USD, no bake) for the truth tests, and a flat plane USD authored with pxr for the bake."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade, Vt

from texelbake.model import AssetModel, Light, Material

RHO = np.array([0.6, 0.45, 0.3])


def lambert(rho=RHO, path: str = "/Looks/Lambert") -> Material:
    return Material(path=path, model="lambert", params={"diffuseColor": np.asarray(rho, float)})


def distant(direction, irradiance=3.0) -> Light:
    d = np.asarray(direction, dtype=np.float64)
    return Light(path="/Lights/Sun", kind="distant", direction=d / np.linalg.norm(d),
                 position=np.zeros(3), radius=0.0, radiance_scale=np.full(3, float(irradiance)))


def model(points, faces, normals=None, lights=(), materials=None) -> AssetModel:
    """A one-mesh AssetModel; normals (n, 3) per vertex (default: face normals)."""
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if normals is None:
        tri = p[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        cn = np.repeat(n[:, None, :], 3, axis=1)
    else:
        cn = np.asarray(normals, dtype=np.float64)[f]
    return AssetModel(
        source="test", points=p, faces=f, corner_normals=cn,
        corner_uvs=np.zeros((len(f), 3, 2)), has_uvs=np.zeros(len(f), bool),
        face_material=np.zeros(len(f), np.int32), face_mesh=np.zeros(len(f), np.int32),
        mesh_paths=("/Mesh",), materials=tuple(materials or (lambert(),)), lights=tuple(lights),
    )


def quad(x0, x1, y0, y1, z) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles in the plane z, facing +z."""
    p = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    return p, np.array([[0, 1, 2], [0, 2, 3]])


def icosphere(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere (vertices on the sphere, faces counter-clockwise from outside)."""
    t = (1.0 + 5 ** 0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t),
         (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    pts = np.array(v, dtype=np.float64)
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    faces = np.array(f, dtype=np.int64)
    for _ in range(levels):
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]),
                        axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = pts[uniq].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1) + len(pts)  # midpoints of edges 01, 12, 20
        a, b, c = faces.T
        faces = np.concatenate([np.stack([a, m[0], m[2]], 1), np.stack([b, m[1], m[0]], 1),
                                np.stack([c, m[2], m[1]], 1), np.stack([m[0], m[1], m[2]], 1)])
        pts = np.concatenate([pts, mid])
    return pts, faces


def _author_quad_grid(stage, path: str, rect, cells: int):
    """A cells x cells grid of quads over rect = (x0, x1, y0, y1, z), facing +z, with st."""
    x0, x1, y0, y1, z = rect
    xs, ys = np.meshgrid(np.linspace(x0, x1, cells + 1), np.linspace(y0, y1, cells + 1))
    pts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, float(z))], axis=1)
    idx, st = [], []
    for j in range(cells):
        for i in range(cells):
            v = j * (cells + 1) + i
            quad_ids = [v, v + 1, v + cells + 2, v + cells + 1]
            idx += quad_ids
            st += [((pts[q, 0] - x0) / (x1 - x0), (pts[q, 1] - y0) / (y1 - y0))
                   for q in quad_ids]
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr([4] * (cells * cells))
    mesh.CreateFaceVertexIndicesAttr(idx)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateNormalsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 1)] * len(pts)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    ).Set(Vt.Vec2fArray([Gf.Vec2f(*map(float, q)) for q in st]))
    return mesh


def write_plane_usd(path: Path, rho=RHO, light_dir=(0.3, 0.2, 0.9), intensity=3.0,
                    cells: int = 4, occluder=None, occluder_cutout: bool = False) -> Path:
    """A flat unit plane (cells x cells quads in z = 0, facing +z) with one Lambertian
    texelbake material, a distant light and a camera looking down at it; with occluder =
    (x0, x1, y0, y1, z) a second mesh, a quad floating above it that casts a shadow. With
    `occluder_cutout` the occluder is a UsdPreviewSurface cut-out: opacity from the alpha of
    an 8 x 8 RGBA PNG beside the layer (`cutout_alpha.png`: 0 on its left half, s < 0.5,
    1 on its right), opacityThreshold 0.5, so only the quad's half toward +x is there."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    meshes = [_author_quad_grid(stage, "/Root/Plane", (-0.5, 0.5, -0.5, 0.5, 0.0), cells)]
    if occluder is not None:
        meshes.append(_author_quad_grid(stage, "/Root/Occluder", occluder, 1))
    mat = UsdShade.Material.Define(stage, "/Root/Looks/Lambert")
    sh = UsdShade.Shader.Define(stage, "/Root/Looks/Lambert/Surface")
    sh.CreateIdAttr("texelbake:lambert")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, rho)))
    mat.CreateSurfaceOutput("texelbake").ConnectToSource(
        sh.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    for mesh in meshes:
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    if occluder_cutout:
        from tests.helpers.usd_stages import preview_material, write_png

        px = np.zeros((8, 8, 4), dtype=np.uint8)
        px[..., :3] = (np.asarray(rho) * 255).astype(np.uint8)
        px[:, 4:, 3] = 255
        write_png(Path(path).parent / "cutout_alpha.png", px)
        card = preview_material(stage, "/Root/Looks/Card", diffuse=rho,
                                texture="./cutout_alpha.png", output="a", connect_to="opacity")
        surface = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/Card/Surface"))
        surface.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
        UsdShade.MaterialBindingAPI.Apply(meshes[1].GetPrim()).Bind(card)
    light = UsdLux.DistantLight.Define(stage, "/Root/Sun")
    d = np.asarray(light_dir, dtype=np.float64)
    d /= np.linalg.norm(d)
    # the light shines down its local -Z: rotate +Z onto d
    z = d
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = x, y, z
    UsdGeom.Xformable(light).AddTransformOp().Set(Gf.Matrix4d(m.tolist()))
    light.CreateIntensityAttr(float(intensity))
    light.CreateNormalizeAttr(True)  # UsdLux: the intensity is the irradiance
    cam = UsdGeom.Camera.Define(stage, "/Root/Camera")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(24.0)
    cam.CreateVerticalApertureAttr(24.0)
    cm = np.eye(4)
    cm[3, :3] = (0.3, -0.4, 4.0)
    UsdGeom.Xformable(cam).AddTransformOp().Set(Gf.Matrix4d(cm.tolist()))
    stage.GetRootLayer().Save()
    return path


def psnr_object(res, ref) -> float:
    """PSNR of RenderResult `res` against `ref` over the object's pixels (the union of both
    coverages, dilated by a pixel: what the reports measure), the reference's peak."""
    from texelbake.render import metrics

    mask = metrics.object_mask(ref.coverage, res.coverage)
    return metrics.psnr_db(res.image[mask], ref.image[mask], float(ref.image[mask].max()))


def bake_small_cylinder(folder: Path) -> Path:
    """The small ridged cylinder baked at 32² with the smallest settings that keep every level,
    an atlas-sized LOD chain (issue 22: its M2 is coarse); the baked root USD."""
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    src = write_scene("cylinder", folder / "cylinder.usda", size="small")
    settings = BakeSettings(atlas_resolution=32, samples_per_texel=8, n_light_dirs=8,
                            n_view_dirs=8, n_heldout=4, c_max=8, avis_resolution=4,
                            lod_mode="atlas")
    return bake(src, folder / "baked", settings, progress=False)
