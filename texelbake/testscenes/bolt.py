"""A bolt with diamond bumps and a high-frequency metallic BRDF."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from texelbake.testscenes.params import BOLT
from texelbake.testscenes.spec import (
    LightSpec,
    MaterialSpec,
    MeshSpec,
    SceneSpec,
    face_normals_fv,
    to_srgb8,
    unit,
)


def build_bolt(p: Mapping[str, int], rng: np.random.Generator) -> SceneSpec:
    n_a, n_l = p["around"], p["along"]
    r, length = BOLT["radius"], BOLT["length"]
    cell_w = 2 * math.pi * r / n_a
    bump = BOLT["bump_ratio"] * cell_w
    y0 = -length / 2
    # half-step lattice: corners (even, even), edge midpoints (mixed), apexes (odd, odd)
    n_p, n_q = 2 * n_a, 2 * n_l + 1
    pp, qq = np.meshgrid(np.arange(n_p), np.arange(n_q), indexing="xy")  # (n_q, n_p)
    theta = pp * (math.pi / n_a)
    rad = np.where((pp % 2 == 1) & (qq % 2 == 1), r + bump, r)
    lattice = np.stack([rad * np.cos(theta), y0 + qq * (length / (2 * n_l)),
                        rad * np.sin(theta)], axis=-1).reshape(-1, 3)
    c_bot = len(lattice)
    points = np.concatenate([lattice, [[0.0, y0, 0.0]]])

    # 8 triangles per cell; corners written with unwrapped p (for st), wrapped for indices.
    # Each triangle is clockwise in the (theta, y) plane, i.e. counter-clockwise seen from
    # outside (x = r cos theta, z = r sin theta).
    ii, jj = np.meshgrid(np.arange(n_a), np.arange(n_l), indexing="xy")
    pc, qc = (2 * ii + 1).ravel(), (2 * jj + 1).ravel()
    rel = {"C": (0, 0), "B": (0, -1), "T": (0, 1), "L": (-1, 0), "R": (1, 0),
           "C00": (-1, -1), "C10": (1, -1), "C11": (1, 1), "C01": (-1, 1)}
    tri_names = [("C", "B", "L"), ("C", "L", "T"), ("C", "T", "R"), ("C", "R", "B"),
                 ("C00", "L", "B"), ("C10", "B", "R"), ("C11", "R", "T"), ("C01", "T", "L")]
    tri_p = np.stack([np.stack([pc + rel[v][0] for v in t], 1) for t in tri_names], 1)
    tri_q = np.stack([np.stack([qc + rel[v][1] for v in t], 1) for t in tri_names], 1)
    tri_p, tri_q = tri_p.reshape(-1, 3), tri_q.reshape(-1, 3)  # (8 cells, 3) unwrapped
    shaft_tris = tri_q * n_p + tri_p % n_p
    k = np.arange(n_p)
    cap = np.stack([np.full(n_p, c_bot), k, (k + 1) % n_p], axis=1)
    tris = np.concatenate([shaft_tris, cap])
    counts = np.full(len(tris), 3, np.int32)
    indices = tris.ravel().astype(np.int32)
    normals = face_normals_fv(points, counts, indices)
    st_shaft = np.stack([tri_p.ravel() / n_p, tri_q.ravel() / (n_q - 1)], axis=1)
    st_cap = 0.5 + 0.5 * points[cap.ravel()][:, [0, 2]] / (r + bump)
    shaft = MeshSpec("Shaft", points, counts, indices, normals, "faceVarying",
                      np.concatenate([st_shaft, st_cap]), "faceVarying", material="StainedMetal")

    # hex head on top of the open upper end of the shaft
    rh, hh, y1 = BOLT["head_radius"], BOLT["head_height"], y0 + length
    ang = np.arange(6) * (math.pi / 3)
    ring = np.stack([rh * np.cos(ang), np.zeros(6), rh * np.sin(ang)], axis=1)
    h_pts = np.concatenate([ring + [0.0, y1, 0.0], ring + [0.0, y1 + hh, 0.0]])  # bot, top
    k6, k6n = np.arange(6), (np.arange(6) + 1) % 6
    h_quads = np.stack([k6, k6 + 6, k6n + 6, k6n], axis=1)
    h_counts = np.array([4] * 6 + [6, 6], np.int32)
    h_indices = np.concatenate([h_quads.ravel(), 6 + k6[::-1], k6]).astype(np.int32)
    h_normals = face_normals_fv(h_pts, h_counts, h_indices)
    h_st_side = np.stack([np.stack([k6, k6, k6 + 1, k6 + 1], 1).ravel() / 6.0,
                          np.tile([0.0, 1.0, 1.0, 0.0], 6)], axis=1)
    h_st_caps = 0.5 + 0.5 * h_pts[np.concatenate([6 + k6[::-1], k6])][:, [0, 2]] / rh
    head = MeshSpec("Head", h_pts, h_counts, h_indices, h_normals, "faceVarying",
                     np.concatenate([h_st_side, h_st_caps]), "faceVarying",
                     material="StainedMetal")
    material = MaterialSpec(
        name="StainedMetal",
        preview={"metallic": 1.0, "roughness": 0.15},  # GGX alpha = 0.0225: a sharp lobe
        texture=("diffuseColor", "stain"),
    )
    lights = (
        LightSpec("Sun", "distant", 2.5, (1.0, 1.0, 1.0), toward=unit([-0.4, 0.6, 1.0])),
        # ~1 W/m^2 at the bolt: intensity * pi * r^2 / d^2 with d ~ 3.4
        LightSpec("Fill", "sphere", 300.0, (0.9, 0.95, 1.0),
                   position=np.array([2.2, 1.4, 2.2]), radius=0.1),
    )
    stain = _stain_texture(p["tex_res"], rng)
    return SceneSpec("Bolt", (shaft, head), (material,), lights, unit([0.3, 0.35, 1.0]),
                      {"stain": stain})


def _periodic_noise(shape: tuple[int, int], sigma_px: float, rng: np.random.Generator
                    ) -> np.ndarray:
    """(h, w) float64 tileable smooth noise in [0, 1]: white noise low-passed by a Gaussian
    in the Fourier domain (periodic by construction, O(n log n) for any sigma)."""
    noise = rng.standard_normal(shape)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    gain = np.exp(-2.0 * (math.pi * sigma_px) ** 2 * (fx ** 2 + fy ** 2))
    smooth = np.fft.irfft2(np.fft.rfft2(noise) * gain, s=shape)
    lo, hi = smooth.min(), smooth.max()
    return (smooth - lo) / (hi - lo) if hi > lo else np.zeros(shape)


def _stain_texture(res: int, rng: np.random.Generator) -> np.ndarray:
    """(res, res, 3) uint8 sRGB: silver with tileable rust-brown stains and fine grain."""
    big = _periodic_noise((res, res), res / 24.0, rng)
    grain = _periodic_noise((res, res), 1.0, rng)
    t = np.clip((big - 0.55) / 0.2, 0.0, 1.0)
    mask = (t * t * (3.0 - 2.0 * t))[..., None]  # smoothstep
    silver, stain = np.array([0.80, 0.80, 0.82]), np.array([0.42, 0.30, 0.18])
    rgb = (1.0 - mask) * silver + mask * stain + 0.06 * (grain[..., None] - 0.5)
    return to_srgb8(rgb)
