"""The cylinder of sharp ridges with alternating reflectance (seed 000, Fig. 1)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from texelbake.model import SHADER_LAMBERT, SHADER_PHONG
from texelbake.testscenes.params import CYLINDER
from texelbake.testscenes.spec import LightSpec, MaterialSpec, MeshSpec, SceneSpec, unit


def build_cylinder(p: Mapping[str, int], rng: np.random.Generator) -> SceneSpec:
    del rng  # the cylinder is fully regular
    n_ridge, rings = p["ridges"], p["rings"]
    r0, height = CYLINDER["radius"], CYLINDER["height"]
    # ridge height: facets rise at ridge_slope_deg over half a ridge's arc
    h = r0 * (math.pi / n_ridge) * math.tan(math.radians(CYLINDER["ridge_slope_deg"]))
    n_prof = 2 * n_ridge  # profile: valley, peak, valley, ...
    k = np.arange(n_prof)
    phi = k * (math.pi / n_ridge)
    rad = np.where(k % 2 == 0, r0, r0 + h)
    ys = np.linspace(-height / 2, height / 2, rings + 1)
    prof = np.stack([rad * np.cos(phi), rad * np.sin(phi)], axis=1)  # (2N, 2) x, z
    side = np.empty((rings + 1, n_prof, 3))
    side[..., 0], side[..., 1], side[..., 2] = prof[None, :, 0], ys[:, None], prof[None, :, 1]
    c_top, c_bot = (rings + 1) * n_prof, (rings + 1) * n_prof + 1
    points = np.concatenate([side.reshape(-1, 3), [[0, height / 2, 0], [0, -height / 2, 0]]])

    # side quads (ring i, facet k): up the axis first, then around -> outward normal
    i_idx, k_idx = np.meshgrid(np.arange(rings), k, indexing="ij")  # (rings, 2N)
    k_next = (k_idx + 1) % n_prof
    quads = np.stack([i_idx * n_prof + k_idx, (i_idx + 1) * n_prof + k_idx,
                      (i_idx + 1) * n_prof + k_next, i_idx * n_prof + k_next], axis=-1)
    quads = quads.reshape(-1, 4)
    top = np.stack([np.full(n_prof, c_top), rings * n_prof + (k + 1) % n_prof,
                    rings * n_prof + k], axis=1)
    bot = np.stack([np.full(n_prof, c_bot), k, (k + 1) % n_prof], axis=1)
    counts = np.concatenate([np.full(len(quads), 4), np.full(2 * n_prof, 3)]).astype(np.int32)
    indices = np.concatenate([quads.ravel(), top.ravel(), bot.ravel()]).astype(np.int32)

    # facet normals in closed form: the edge (ex, ez) of the profile has outward (ez, -ex)
    edge = np.roll(prof, -1, axis=0) - prof  # (2N, 2)
    facet_n = unit(np.stack([edge[:, 1], np.zeros(n_prof), -edge[:, 0]], axis=1))
    quad_n = np.repeat(np.tile(facet_n, (rings, 1)), 4, axis=0)
    cap_n = np.repeat(np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]), 3 * n_prof, axis=0)
    normals = np.concatenate([quad_n, cap_n])

    # st: u around (1 at the seam's far side), v along; caps: planar in x, z
    k_corner = np.stack([k_idx, k_idx, k_idx + 1, k_idx + 1], axis=-1).reshape(-1)
    i_corner = np.stack([i_idx, i_idx + 1, i_idx + 1, i_idx], axis=-1).reshape(-1)
    st_side = np.stack([k_corner / n_prof, i_corner / rings], axis=1)
    cap_pts = points[np.concatenate([top.ravel(), bot.ravel()])]
    st_cap = 0.5 + 0.5 * cap_pts[:, [0, 2]] / (r0 + h)
    st = np.concatenate([st_side, st_cap])

    # materials: facets rising from a valley with phi (even k; they face toward decreasing
    # phi, i.e. toward the camera on the left rim) are blue, so the left rim turns blue by
    # masking as in Fig. 1(d); the others and the caps are yellow. Face order: quads
    # (ring-major, facet-minor), then the caps.
    quad_k = np.tile(k, rings)
    face_ids = np.arange(len(counts), dtype=np.int32)
    is_yellow = np.concatenate([quad_k % 2 == 1, np.ones(2 * n_prof, bool)])
    mesh = MeshSpec(
        name="RidgedCylinder", points=points, counts=counts, indices=indices,
        normals=normals, normals_interp="faceVarying", st=st, st_interp="faceVarying",
        subsets=(("YellowFacets", face_ids[is_yellow], "YellowLambert"),
                 ("BlueFacets", face_ids[~is_yellow], "BluePhong")),
    )
    exponent = 60.0
    materials = (
        MaterialSpec(
            name="YellowLambert",
            # exact Lambertian in UsdPreviewSurface: specular workflow, zero specular
            preview={"diffuseColor": (0.85, 0.7, 0.08), "useSpecularWorkflow": 1,
                     "specularColor": (0.0, 0.0, 0.0), "roughness": 1.0},
            texelbake_id=SHADER_LAMBERT,
            texelbake_inputs={"diffuseColor": (0.85, 0.7, 0.08)},
        ),
        MaterialSpec(
            name="BluePhong",
            # Phong exponent n ~ Beckmann/GGX alpha^2 = 2 / (n + 2); UsdPreviewSurface's
            # alpha = roughness^2, so roughness = (2 / (n + 2)) ** 0.25
            preview={"diffuseColor": (0.05, 0.12, 0.55), "useSpecularWorkflow": 1,
                     "specularColor": (0.4, 0.4, 0.4),
                     "roughness": (2.0 / (exponent + 2.0)) ** 0.25},
            texelbake_id=SHADER_PHONG,
            texelbake_inputs={"diffuseColor": (0.05, 0.12, 0.55),
                              "specularColor": (0.4, 0.4, 0.4), "exponent": exponent},
        ),
    )
    # as Fig. 1: seen from the side, lit from the upper front-left, so the left rim shows
    # masking and the right rim shadowing
    lights = (LightSpec("Sun", "distant", 3.0, (1.0, 1.0, 1.0),
                         toward=unit([-0.6, 0.5, 1.0])),)
    return SceneSpec("Cylinder", (mesh,), materials, lights, unit([0.0, 0.15, 1.0]), {})
