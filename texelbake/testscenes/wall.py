"""A wall of detailed blocks with a Lambertian colour texture."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from texelbake.testscenes.params import WALL
from texelbake.testscenes.spec import (
    LightSpec,
    MaterialSpec,
    MeshSpec,
    SceneSpec,
    to_srgb8,
    unit,
    vertex_normals,
)


def _wall_blocks(cols: int, rows: int) -> np.ndarray:
    """(nb, 4) float64 block footprints x0, x1, y0, y1 in running bond (odd rows shifted by
    half a block and clipped to the wall, so their end blocks are halves)."""
    bw, bh, gap = WALL["block_w"], WALL["block_h"], WALL["gap"]
    px, py = bw + gap, bh + gap
    width = cols * px
    out = []
    for j in range(rows):  # a handful of rows
        odd = j % 2
        x0 = np.arange(cols + odd) * px + gap / 2 - odd * px / 2
        x1 = np.minimum(x0 + bw, width - gap / 2)
        x0 = np.maximum(x0, gap / 2)
        y0 = np.full_like(x0, j * py + gap / 2)
        out.append(np.stack([x0, x1, y0, y0 + bh], axis=1))
    return np.concatenate(out)


def build_wall(p: Mapping[str, int], rng: np.random.Generator) -> SceneSpec:
    cols, rows, s = p["cols"], p["rows"], p["front_cells"]
    bw, bh, gap = WALL["block_w"], WALL["block_h"], WALL["gap"]
    depth, bevel, jitter = WALL["depth"], WALL["bevel"], WALL["jitter"]
    width, height = cols * (bw + gap), rows * (bh + gap)
    fp = _wall_blocks(cols, rows)  # (nb, 4)
    nb = len(fp)

    # front grid of each block: (s+1)^2 vertices, interior ones jittered in depth
    t = np.linspace(0.0, 1.0, s + 1)
    gx, gy = np.meshgrid(t, t, indexing="xy")  # (s+1, s+1), row = y
    fx0, fx1 = fp[:, 0] + bevel, fp[:, 1] - bevel
    fy0, fy1 = fp[:, 2] + bevel, fp[:, 3] - bevel
    front = np.empty((nb, s + 1, s + 1, 3))
    front[..., 0] = fx0[:, None, None] + gx[None] * (fx1 - fx0)[:, None, None]
    front[..., 1] = fy0[:, None, None] + gy[None] * (fy1 - fy0)[:, None, None]
    interior = np.zeros((s + 1, s + 1), bool)
    interior[1:-1, 1:-1] = True
    front[..., 2] = depth + jitter * rng.uniform(-1.0, 1.0, (nb, s + 1, s + 1)) * interior
    a, b = np.meshgrid(np.arange(s), np.arange(s), indexing="xy")
    v00 = (b * (s + 1) + a).ravel()
    v10, v01, v11 = v00 + 1, v00 + s + 1, v00 + s + 2
    grid_tris = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    nfv = (s + 1) ** 2
    tris = grid_tris[None] + (np.arange(nb) * nfv)[:, None, None]  # (nb, 2s^2, 3)
    front_pts = front.reshape(-1, 3)  # (nb * (s+1)^2, 3), block-major
    front_tris = tris.reshape(-1, 3)
    front_n = vertex_normals(front_pts, front_tris)

    # chamfers and sides: 8 planar quads per block, 4 own vertices each, CCW from outside
    rim_xy = np.stack([fp[:, [0, 2]], fp[:, [1, 2]], fp[:, [1, 3]], fp[:, [0, 3]]], 1)
    fr_xy = np.stack([np.stack([fx0, fy0], 1), np.stack([fx1, fy0], 1),
                      np.stack([fx1, fy1], 1), np.stack([fx0, fy1], 1)], 1)  # (nb, 4, 2)

    def at_z(xy: np.ndarray, z: float) -> np.ndarray:
        return np.concatenate([xy, np.full(xy.shape[:-1] + (1,), z)], axis=-1)

    rim, frt, base = at_z(rim_xy, depth - bevel), at_z(fr_xy, depth), at_z(rim_xy, 0.0)
    ca, cb = np.arange(4), (np.arange(4) + 1) % 4  # edge a -> b, CCW seen from +z
    chamfer = np.stack([rim[:, ca], rim[:, cb], frt[:, cb], frt[:, ca]], axis=2)
    sides = np.stack([base[:, ca], base[:, cb], rim[:, cb], rim[:, ca]], axis=2)
    quads = np.concatenate([chamfer, sides], axis=1).reshape(-1, 4, 3)  # (nb*8, 4, 3)
    quad_n = unit(np.cross(quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0]))
    n_q = len(quads)
    q_base = len(front_pts)
    points = np.concatenate([front_pts, quads.reshape(-1, 3)])
    counts = np.concatenate([np.full(len(front_tris), 3), np.full(n_q, 4)]).astype(np.int32)
    indices = np.concatenate([front_tris.ravel(), q_base + np.arange(4 * n_q)]).astype(np.int32)
    normals = np.concatenate([front_n, np.repeat(quad_n, 4, axis=0)])
    st = points[:, :2] / np.array([width, height])
    blocks = MeshSpec("Blocks", points, counts, indices, normals, "vertex", st, "vertex",
                       material="WallAlbedo")

    # mortar plane: (2 cols) x rows quads at z = 0
    mx, my = 2 * cols, rows
    xs, ys = np.linspace(0, width, mx + 1), np.linspace(0, height, my + 1)
    mgx, mgy = np.meshgrid(xs, ys, indexing="xy")
    m_pts = np.stack([mgx.ravel(), mgy.ravel(), np.zeros(mgx.size)], axis=1)
    a, b = np.meshgrid(np.arange(mx), np.arange(my), indexing="xy")
    m00 = (b * (mx + 1) + a).ravel()
    m_quads = np.stack([m00, m00 + 1, m00 + mx + 2, m00 + mx + 1], axis=1)
    mortar = MeshSpec(
        "Mortar", m_pts, np.full(len(m_quads), 4, np.int32), m_quads.ravel().astype(np.int32),
        np.tile([0.0, 0.0, 1.0], (len(m_pts), 1)), "vertex",
        m_pts[:, :2] / np.array([width, height]), "vertex", material="WallAlbedo",
    )
    material = MaterialSpec(
        name="WallAlbedo",
        preview={"useSpecularWorkflow": 1, "specularColor": (0.0, 0.0, 0.0), "roughness": 1.0},
        texture=("diffuseColor", "albedo"),
    )
    texture = _wall_texture(cols, rows, p["tex_res"], rng)
    lights = (LightSpec("Sun", "distant", 3.0, (1.0, 0.97, 0.92),
                         toward=unit([-0.55, 0.45, 0.7])),)
    return SceneSpec("Wall", (blocks, mortar), (material,), lights,
                      unit([0.25, 0.2, 1.0]), {"albedo": texture})


def _wall_texture(cols: int, rows: int, res: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) uint8 sRGB albedo: a colour per block (one texel wider than its footprint,
    so bilinear look-ups at block edges stay on the block), speckle, grey mortar."""
    bw, bh, gap = WALL["block_w"], WALL["block_h"], WALL["gap"]
    px, py = bw + gap, bh + gap
    width, height = cols * px, rows * py
    w_px, h_px = res, max(8, round(res * height / width))
    texel = width / w_px
    x = (np.arange(w_px) + 0.5) / w_px * width
    y = (1.0 - (np.arange(h_px) + 0.5) / h_px) * height  # row 0 is the top (t = 1)
    X, Y = np.meshgrid(x, y, indexing="xy")  # (h, w)
    row = np.clip(np.floor(Y / py).astype(int), 0, rows - 1)
    shift = (row % 2) * px / 2
    col = np.floor((X + shift) / px).astype(int)
    lx, ly = X + shift - col * px, Y - row * py
    lo, hi_x, hi_y = gap / 2 - texel, gap / 2 + bw + texel, gap / 2 + bh + texel
    on_block = ((lx >= lo) & (lx <= hi_x) & (ly >= lo) & (ly <= hi_y)
                & (X >= lo) & (X <= width - lo))
    stone = np.array([0.62, 0.50, 0.38])
    # per block: mostly a brightness change, a little hue
    block_rgb = np.clip(stone + rng.normal(0.0, 0.025, (rows, cols + 1, 3))
                        + rng.normal(0.0, 0.08, (rows, cols + 1, 1)), 0.05, 0.95)
    mortar_rgb = np.array([0.58, 0.57, 0.54])
    rgb = np.where(on_block[..., None], block_rgb[row, np.clip(col, 0, cols)], mortar_rgb)
    rgb = rgb + rng.normal(0.0, 0.03, (h_px, w_px, 1))  # speckle
    return to_srgb8(rgb)
