"""Small assets and stores for the surface-reflectance-field tests (tests/srf/)."""

from __future__ import annotations

import numpy as np

from tests.helpers.render import icosphere, lambert, model
from texelbake.model import Material


def sphere_asset(levels: int = 2, lights=()):
    """A unit icosphere (smooth normals) with a Lambertian half and a Phong half (a colour
    step across x = 0 and a specular lobe: appearance a field must keep)."""
    pts, faces = icosphere(levels)
    mats = (lambert((0.7, 0.4, 0.2)),
            Material(path="/Looks/Phong", model="phong",
                     params={"diffuseColor": np.array([0.1, 0.3, 0.6]),
                             "specularColor": np.array([0.4, 0.4, 0.4]), "exponent": 20.0}))
    asset = model(pts, faces, normals=pts, lights=lights, materials=mats)
    cen = pts[faces].mean(axis=1)
    fm = (cen[:, 0] > 0).astype(np.int32)
    import dataclasses

    return dataclasses.replace(asset, face_material=fm)
