"""Runs inside Blender (headless `bpy`, scripts/dcc-venv.sh), only through
`tests.helpers.dcc.run_blender`: Blender's own MikkTSpace tangents of a low mesh and its own
tangent-space normal bake of a high mesh onto it.

    python mikk_bake.py -- SPEC.json

SPEC: {"meshes": NPZ, "out": NPZ, "resolution": n, "extrusion": cage distance}. NPZ holds
low_vertices (n, 3), low_faces (f, 3), low_uvs (f, 3, 2), low_normals (f, 3, 3) (per corner:
custom split normals) and high_vertices, high_faces, high_normals likewise. Writes to `out`:
tangent (f, 3, 3) and sign (f, 3) per corner (`Mesh.calc_tangents` on the uv map), and
normal (n, n, 4) the baked image's float pixels (row 0 at v = 0; Cycles, selected to active,
tangent space, no margin, one sample a texel). The last stdout line is a JSON summary.
"""

from __future__ import annotations

import json
import sys
import time

import bpy
import numpy as np


def _object(name: str, v: np.ndarray, f: np.ndarray, cn: np.ndarray,
            uv: np.ndarray | None) -> bpy.types.Object:
    me = bpy.data.meshes.new(name)
    me.from_pydata(v.tolist(), [], f.tolist())
    me.update()
    if uv is not None:
        layer = me.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", uv.reshape(-1).astype(np.float32))
    me.polygons.foreach_set("use_smooth", np.ones(len(f), dtype=bool))
    me.normals_split_custom_set(cn.reshape(-1, 3).tolist())
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def main() -> None:
    spec = json.loads(open(sys.argv[sys.argv.index("--") + 1]).read())
    d = np.load(spec["meshes"])
    bpy.ops.wm.read_factory_settings(use_empty=True)
    t0 = time.time()
    low = _object("low", d["low_vertices"], d["low_faces"], d["low_normals"], d["low_uvs"])
    high = _object("high", d["high_vertices"], d["high_faces"], d["high_normals"], None)
    me = low.data
    me.calc_tangents(uvmap="UVMap")
    nl = len(me.loops)
    tan = np.empty(nl * 3, dtype=np.float32)
    me.loops.foreach_get("tangent", tan)
    sign = np.empty(nl, dtype=np.float32)
    me.loops.foreach_get("bitangent_sign", sign)
    # the bake: an image on the low mesh's active image node
    n = int(spec["resolution"])
    img = bpy.data.images.new("nm", n, n, float_buffer=True, is_data=True)
    mat = bpy.data.materials.new("bake")
    mat.use_nodes = True
    node = mat.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = img
    mat.node_tree.nodes.active = node
    me.materials.append(mat)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1
    scene.cycles.use_denoising = False
    scene.cycles.seed = 0
    for ob in scene.objects:
        ob.select_set(ob is high)
    bpy.context.view_layer.objects.active = low
    low.select_set(True)
    bpy.ops.object.bake(type="NORMAL", normal_space="TANGENT", use_selected_to_active=True,
                        cage_extrusion=float(spec["extrusion"]), margin=0,
                        target="IMAGE_TEXTURES", use_clear=True)
    px = np.empty(n * n * 4, dtype=np.float32)
    img.pixels.foreach_get(px)
    np.savez(spec["out"], tangent=tan.reshape(-1, 3, 3), sign=sign.reshape(-1, 3),
             normal=px.reshape(n, n, 4))
    print(json.dumps({"loops": nl, "resolution": n, "seconds": round(time.time() - t0, 2)}))


if __name__ == "__main__":
    main()
