"""``preview-surface``: exactly what a USD viewer without texelbake's shader shows — each
LOD's UsdPreviewSurface fallback as authored in the baked USD (read back by
`texelbake.usd.read.read_baked`: its diffuseColor, normal, roughness and occlusion textures
after their colour space, scale and bias, and its constant inputs), evaluated with the
specification's BRDF (`brdf.analytic.preview_surface`).

The mesh is picked as ``cpm`` picks it (`cpm.choose_mesh`: the coarsest M_i whose geometric
error projects under a pixel), eye rays hit that M_i, and its interpolated ``st`` (no
closest-point correction: a viewer has none) look up every texture trilinearly in a box-filtered
mip chain at the pixel footprint (`cpm.footprint_level`, each of the spp samples at its 1/spp
share of the pixel, as a GPU's texture unit under supersampling). The normal texture is
decoded in M_i's own MikkTSpace frame from its uvs and authored normals
(`geometry.mikktspace`, what Blender and glTF viewers derive), falling back to the geometric normal where it points below the surface
(`brdf.shading_normal`'s rule). Shadows on M_i. The ``occlusion`` input is, by the
specification, for indirect light only; this renderer has direct light only, so it does not
change the image (it is authored for the viewers that do have indirect light).
"""

from __future__ import annotations

import math

import numpy as np

from texelbake import model
from texelbake.baselines.normal_maps import face_tangent_space
from texelbake.brdf.analytic import preview_surface
from texelbake.errors import SettingsError, StageError
from texelbake.geometry.mikktspace import decode, frames_at, mikk_tangents
from texelbake.geometry.texels import bilinear_texels
from texelbake.render.cpm import choose_mesh, footprint_level
from texelbake.render.scene import RenderScene
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.shade import direct_radiance
from texelbake.trace.tracer import accumulate


def mip_chain(img: np.ndarray) -> list[np.ndarray]:
    """Box-filtered mip chain of an (n, n, c) map (n a power of two), each level flattened to
    (n_l², c) float64, finest first."""
    level = np.asarray(img, dtype=np.float64)
    if level.ndim != 3 or level.shape[0] != level.shape[1]:
        raise StageError(f"fallback texture must be square (n, n, c), got {level.shape}")
    out = [level.reshape(-1, level.shape[2])]
    while level.shape[0] > 1 and level.shape[0] % 2 == 0:
        level = 0.25 * (level[0::2, 0::2] + level[1::2, 0::2] + level[0::2, 1::2]
                        + level[1::2, 1::2])
        out.append(level.reshape(-1, level.shape[2]))
    return out


def trilinear(chain: list[np.ndarray], uv: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Trilinear look-up of a mip chain at uv (k, 2), λ (k,) in the chain's own levels
    (clipped); returns (k, c) float64."""
    n0 = int(round(math.sqrt(chain[0].shape[0])))
    lam = np.clip(lam, 0.0, len(chain) - 1.0)
    j0 = np.floor(lam).astype(np.int64)
    fr = lam - j0
    out = np.zeros((uv.shape[0], chain[0].shape[1]))
    for j in range(len(chain)):  # a loop over the few levels
        for sel, up in ((np.flatnonzero(j0 == j), False),
                        (np.flatnonzero((j0 + 1 == j) & (fr > 0)), True)):
            if sel.size:
                tex, w = bilinear_texels(uv[sel], max(n0 >> j, 1))
                wl = fr[sel] if up else 1.0 - fr[sel]
                out[sel] += wl[:, None] * np.einsum("nk,nkc->nc", w, chain[j][tex])
    return out


_BRDF_CONSTANTS = tuple(k for k in model.PREVIEW_DEFAULTS
                        if k not in ("normal", "occlusion", "emissiveColor", "opacity",
                                     "opacityThreshold", "displacement"))


def _tables(scene: RenderScene, lod: int) -> dict:
    """LOD `lod`'s (0 = M1) fallback: mip chains of its textures, constants, tangent frames."""
    cache = scene.__dict__.setdefault("_preview_tables", {})
    if lod in cache:
        return cache[lod]
    mats = scene.baked.fallback.get("materials", [])
    mat = mats[lod] if lod < len(mats) else {}
    if not mat:
        raise StageError(f"baked asset {scene.root}: LOD{lod + 1} has no UsdPreviewSurface "
                         "fallback material")
    consts = {k: v for k, v in mat["constants"].items()
              if k in _BRDF_CONSTANTS and v is not None}
    chains = {k: mip_chain(v) for k, v in mat["textures"].items()}
    m = scene.baked.meshes[lod]
    cn = m.corner_normals
    if cn is None:  # none authored: the face normals, as a viewer derives them
        cn = np.repeat(face_tangent_space(m.vertices, m.faces, m.corner_uvs)[:, None, 2], 3,
                       axis=1)
    tangent, sign = mikk_tangents(m.vertices, m.faces, cn, m.corner_uvs)
    cache[lod] = {"constants": consts, "chains": chains, "mikk": (tangent, sign, cn),
                  "path": mat["path"]}
    return cache[lod]


def shade_preview_surface(scene: RenderScene, cam: PinholeCamera, lod: int, o: np.ndarray,
                          d: np.ndarray, spp: int) -> tuple[np.ndarray, int, np.ndarray]:
    """Radiance along eye rays traced against M_{lod+1} with its fallback material (module
    docstring); returns (radiance (n, 3), rays cast, hit (n,) bool)."""
    tb = _tables(scene, lod)
    mesh = scene.baked.meshes[lod]
    caster = scene.lods[lod]
    out = np.zeros((o.shape[0], 3))
    hits = caster.cast(o, d)
    idx = np.flatnonzero(hits.hit)
    if idx.size == 0:
        return out, o.shape[0], hits.hit
    prim = hits.prim[idx]
    b = hits.bary3()[idx]
    p = np.einsum("nk,nkj->nj", b, mesh.vertices[mesh.faces[prim]])
    uv = np.einsum("nk,nkj->nj", b, mesh.corner_uvs[prim])
    # the pixel footprint in texels of an n0² map, each sample at its 1/spp share
    lam0 = footprint_level(scene, cam, lod, prim, p, o[idx], d[idx]) \
        - 0.5 * math.log2(max(int(spp), 1))
    params: dict[str, np.ndarray] = dict(tb["constants"])
    n_local = np.tile([0.0, 0.0, 1.0], (idx.size, 1))
    for name, chain in tb["chains"].items():  # the material's few textures
        res = int(round(math.sqrt(chain[0].shape[0])))
        v = trilinear(chain, uv, lam0 + math.log2(res / scene.n0))
        if name == "normal":
            n_local = v
        elif name in _BRDF_CONSTANTS:
            params[name] = v if v.shape[1] == 3 else v[:, 0]
    length = np.linalg.norm(n_local, axis=1, keepdims=True)
    ok = (length[:, 0] > 0) & (n_local[:, 2] > 0)
    n_local = np.where(ok[:, None], n_local / np.where(ok, length[:, 0], 1.0)[:, None],
                       [0.0, 0.0, 1.0])
    tangent, sign, cn = tb["mikk"]
    ns = decode(frames_at(tangent, sign, cn, prim, b), n_local)

    def brdf(sel: np.ndarray, wi_l: np.ndarray, wo_l: np.ndarray) -> np.ndarray:
        rows = {k: (v[sel] if np.ndim(v) and np.shape(v)[0] == idx.size else v)
                for k, v in params.items()}
        return preview_surface(rows, wi_l, wo_l)

    rad, shadow = direct_radiance(p, scene.lod_face_normals[lod][prim], ns, -d[idx],
                                  scene.lights, brdf, caster, scene.ray_eps)
    out[idx] = rad
    return out, o.shape[0] + shadow, hits.hit


def render_preview_surface(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int, *,
                           max_error_px: float = 1.0, lod: int | None = None):
    """The LODs' UsdPreviewSurface fallback as authored: the mesh the camera's projected error
    selects (`choose_mesh`), or mesh `lod` (0 = M1) when given (a benchmark judging one LOD)."""
    if lod is None:
        lod = choose_mesh(scene, cam, max_error_px)
    elif not 0 <= lod < len(scene.lods):
        raise SettingsError(f"preview-surface: lod {lod} is not one of the scene's "
                            f"{len(scene.lods)} meshes (0 = M1)")
    return accumulate(cam, spp, seed,
                      lambda o, d: shade_preview_surface(scene, cam, lod, o, d, spp),
                      scene.eye_box)
