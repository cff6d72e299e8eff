"""Runs inside Blender (headless `bpy`, scripts/dcc-venv.sh), only through
`tests.dcc_util.run_blender`: import USD files with Blender's own importer at its defaults
(`bpy.ops.wm.usd_import`), report what it made, and render each file from one camera and sun.

    python import_render.py -- SPEC.json

SPEC: {"files": [{"name", "path", "options"?, "scene_frame"?, "keep"?, "seed"?}, ...], "out_dir",
"resolution", "samples",
"frame": null | [[xmin, ymin, zmin], [xmax, ymax, zmax]], "diag_px": null | pixels}. Each file
is imported into an empty scene (`options`: importer keywords, e.g. {"import_subdivision":
True}). The camera and the sun are placed from `frame` (Blender world space; when null, from
the first file's imported bounds), so every file is seen from the same view: at the distance
where the frame fits the image, or, with `diag_px`, where the frame box's diagonal covers that
many pixels (a LOD's switch distance; the small-angle size). Per file the last
stdout line's JSON holds: the mesh objects (name, triangles, world-space bounds), the materials
they use, the images those materials read (size, whether pixels loaded), each material's
Principled BSDF inputs ("bsdf": what the importer made of a UsdPreviewSurface), the world
bounds of all meshes, the render's PNG path and seconds.

The render is Cycles on the CPU (the only engine that runs in headless bpy without a GPU
context), a fixed seed (the file's `seed`, default 0), no denoiser, no adaptive sampling: the
same file and seed give the same pixels; one file under two seeds measures Cycles' noise.
Lights and cameras the file carries are removed (so the original and a LOD are lit alike): one
sun of 3 W/m² from over the camera's left shoulder plus a dim uniform world (0.05), the film
transparent (alpha = coverage), the Standard view transform (8-bit sRGB PNG, RGBA), exposure 0.

A file's `keep` (a list) overrides that: with "lights" its own lights stay and the scene gets a
world before the import, so the importer turns the file's first DomeLight into the world's
background (`create_world_material`: an Environment Texture, or the constant colour, times the
light's colour and intensity), no sun or dim world is added, and Cycles computes direct light
only (max bounces 0: what texelbake's `gt` computes); with "camera" the file's first camera is
the one rendered from.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector


def _reset() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _mesh_objects() -> list:
    return [o for o in bpy.context.scene.objects if o.type == "MESH"]


def _world_bounds(objs) -> tuple[list[float], list[float]] | None:
    pts = []
    for o in objs:
        m = np.array(o.matrix_world)
        corners = np.array([list(c) for c in o.bound_box], dtype=np.float64)
        pts.append(corners @ m[:3, :3].T + m[:3, 3])
    if not pts:
        return None
    allp = np.concatenate(pts)
    return allp.min(axis=0).tolist(), allp.max(axis=0).tolist()


def _exact_bounds(objs) -> tuple[list[float], list[float]] | None:
    """World bounds from the evaluated vertices (bound_box is the local box, rotated)."""
    deps = bpy.context.evaluated_depsgraph_get()
    pts = []
    for o in objs:
        ev = o.evaluated_get(deps)
        me = ev.to_mesh()
        co = np.empty(len(me.vertices) * 3, dtype=np.float64)
        me.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3)
        m = np.array(ev.matrix_world)
        pts.append(co @ m[:3, :3].T + m[:3, 3])
        ev.to_mesh_clear()
    if not pts or not sum(len(p) for p in pts):
        return None
    allp = np.concatenate(pts)
    return allp.min(axis=0).tolist(), allp.max(axis=0).tolist()


def _triangles(o) -> int:
    me = o.data
    me.calc_loop_triangles()
    return len(me.loop_triangles)


def _images_of(mat) -> list[dict]:
    out = []
    if not mat or not mat.use_nodes:
        return out
    for node in mat.node_tree.nodes:
        if node.type == "TEX_IMAGE" and node.image is not None:
            img = node.image
            w, h = img.size
            has = False
            if w and h:
                px = np.empty(w * h * img.channels, dtype=np.float32)
                img.pixels.foreach_get(px)
                has = bool(np.isfinite(px).all() and px.max() > px.min() or px.max() > 0)
            out.append({"image": img.name, "file": img.filepath, "size": [w, h],
                        "has_pixels": has, "packed": img.packed_file is not None})
    return out


#: the Principled BSDF inputs `_bsdf_of` reports
BSDF_INPUTS = ("Base Color", "Metallic", "Roughness", "IOR", "Specular IOR Level",
               "Specular Tint", "Coat Weight", "Alpha")


def _bsdf_of(mat) -> dict:
    """The first Principled BSDF's inputs (`BSDF_INPUTS`): a value (a list for colours) where
    the input is unlinked, "linked" where a node drives it."""
    if not mat or not mat.use_nodes:
        return {}
    for node in mat.node_tree.nodes:
        if node.type == "BSDF_PRINCIPLED":
            out = {}
            for name in BSDF_INPUTS:
                inp = node.inputs[name]
                v = inp.default_value
                out[name] = "linked" if inp.is_linked else (
                    [float(x) for x in v] if hasattr(v, "__len__") else float(v))
            return out
    return {}


def _describe() -> dict:
    objs = _mesh_objects()
    mats: dict[str, list] = {}
    bsdfs: dict[str, dict] = {}
    meshes = []
    for o in objs:
        used = [s.material.name for s in o.material_slots if s.material is not None]
        for s in o.material_slots:
            if s.material is not None and s.material.name not in mats:
                mats[s.material.name] = _images_of(s.material)
                bsdfs[s.material.name] = _bsdf_of(s.material)
        meshes.append({"name": o.name, "triangles": _triangles(o), "materials": used,
                       "bounds": _exact_bounds([o])})
    return {"meshes": meshes, "materials": mats, "bsdf": bsdfs, "bounds": _exact_bounds(objs)}


def _world_for_a_dome(scene) -> None:
    """A world for the importer to turn the file's DomeLight into (it converts one only into
    an existing world): its Background white (UsdLux's default colour, which the importer
    leaves when the dome authors none) at strength 0, which the importer sets to the dome's
    intensity, so a file without a dome is lit by its other lights alone."""
    world = bpy.data.worlds.new("FileWorld")
    world.use_nodes = True
    bg = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bg.inputs["Strength"].default_value = 0.0
    scene.world = world


def _setup_view(frame, resolution: int, samples: int, diag_px: float | None = None,
                keep: tuple[str, ...] = (), seed: int = 0) -> None:
    scene = bpy.context.scene
    gone = ("CAMERA",) * ("camera" not in keep) + ("LIGHT",) * ("lights" not in keep)
    for o in list(scene.objects):
        if o.type in gone:
            bpy.data.objects.remove(o, do_unlink=True)
    _render_settings(scene, resolution, samples, seed)
    if "lights" in keep:
        scene.cycles.max_bounces = 0  # direct light only, as texelbake's gt
    if "camera" in keep:
        cams = sorted((o for o in scene.objects if o.type == "CAMERA"), key=lambda o: o.name)
        if not cams:
            raise SystemExit("keep 'camera': the file has no camera")
        scene.camera = cams[0]
    else:
        _place_camera(scene, frame, resolution, diag_px)
    if "lights" not in keep:
        _add_sun_and_world(scene)


def _place_camera(scene, frame, resolution: int, diag_px: float | None) -> None:
    lo, hi = np.asarray(frame[0]), np.asarray(frame[1])
    center = (lo + hi) / 2
    # camera: azimuth 30 deg, elevation 25 deg (Blender is Z-up), 40 deg field of view, at
    # the distance where the frame box's 8 corners fit the image with a 5 % margin
    az, el, fov = math.radians(30.0), math.radians(25.0), math.radians(40.0)
    view = np.array([math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az), math.sin(el)])
    right = np.cross(-view, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, -view)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) - center
    t = math.tan(fov / 2) / 1.05
    d = float(np.max(corners @ view + np.maximum(np.abs(corners @ right),
                                                 np.abs(corners @ up)) / t))
    radius = float(np.linalg.norm(hi - lo) / 2) or 1.0
    if diag_px:  # at the distance where the frame box's diagonal covers diag_px pixels
        d = 2.0 * radius * resolution / (2.0 * float(diag_px) * math.tan(fov / 2))
    cam_data = bpy.data.cameras.new("DccCamera")
    cam_data.angle = fov
    cam_data.clip_start = max(d - 2 * radius, 1e-4) * 0.5
    cam_data.clip_end = (d + 2 * radius) * 2
    cam = bpy.data.objects.new("DccCamera", cam_data)
    scene.collection.objects.link(cam)
    cam.location = Vector((center + d * view).tolist())
    cam.rotation_euler = Vector((-view).tolist()).to_track_quat("-Z", "Y").to_euler()
    scene.camera = cam


def _add_sun_and_world(scene) -> None:
    az = math.radians(30.0)  # the camera's azimuth (`_place_camera`)
    sun_data = bpy.data.lights.new("DccSun", type="SUN")
    sun_data.energy = 3.0
    sun_data.angle = math.radians(2.0)
    sun = bpy.data.objects.new("DccSun", sun_data)
    scene.collection.objects.link(sun)
    sdir = np.array([math.cos(math.radians(50)) * math.sin(az - math.radians(50)),
                     -math.cos(math.radians(50)) * math.cos(az - math.radians(50)),
                     math.sin(math.radians(50))])
    sun.rotation_euler = Vector((-sdir).tolist()).to_track_quat("-Z", "Y").to_euler()
    world = bpy.data.worlds.new("DccWorld")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    bg.inputs["Color"].default_value = (0.05, 0.05, 0.05, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    scene.world = world


def _render_settings(scene, resolution: int, samples: int, seed: int = 0) -> None:
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.seed = seed
    scene.cycles.max_bounces = 4
    scene.render.film_transparent = True
    scene.render.resolution_x = resolution
    scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.render.image_settings.color_depth = "8"


def main() -> None:
    argv = sys.argv[sys.argv.index("--") + 1:]
    spec = json.loads(Path(argv[0]).read_text())
    out_dir = Path(spec["out_dir"])
    out_dir.mkdir(parents=True, exist_ok=True)
    frame = spec.get("frame")
    results = []
    for f in spec["files"]:
        _reset()
        keep = tuple(f.get("keep", ()))
        if "lights" in keep:
            _world_for_a_dome(bpy.context.scene)
        t0 = time.perf_counter()
        res = bpy.ops.wm.usd_import(filepath=str(f["path"]), **f.get("options", {}))
        info = {"name": f["name"], "path": str(f["path"]), "import": sorted(res),
                "import_seconds": time.perf_counter() - t0}
        # the importer sets the frame range from the stage's start and end time codes and
        # leaves the current frame at 1; texelbake bakes the earliest time (the start), so
        # the render is made there (BoxAnimated's lid has moved by frame 1), unless the file
        # names its frame ("scene_frame": an animated asset posed elsewhere)
        scene = bpy.context.scene
        scene.frame_set(int(f.get("scene_frame", scene.frame_start)))
        info["frame_current"] = scene.frame_current
        info.update(_describe())
        if frame is None:
            frame = info["bounds"]
        png = out_dir / f"{f['name']}.png"
        if spec.get("render", True) and info["bounds"] is not None:
            _setup_view(frame, int(spec.get("resolution", 160)), int(spec.get("samples", 16)),
                        spec.get("diag_px"), keep, int(f.get("seed", 0)))
            bpy.context.scene.render.filepath = str(png)
            t0 = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            info["render_seconds"] = time.perf_counter() - t0
            info["png"] = str(png)
        results.append(info)
    print(json.dumps({"frame": frame, "files": results}))


if __name__ == "__main__":
    main()
