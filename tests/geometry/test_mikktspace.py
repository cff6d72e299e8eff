"""MikkTSpace tangents (`geometry.mikktspace`): against a corner-by-corner transcription of
MikkTSpace's `InitTriInfo` + `EvalTspace` (dict welding, one loop per corner), the plane's
exact frames in both uv orientations, and encode/decode as inverses. Blender's own tangents
and bake: tests/dcc/test_mikktspace_blender.py."""

from __future__ import annotations

import math

import numpy as np

from texelbake.geometry.mikktspace import decode, encode, frames_at, mikk_tangents


def _wrapped_band(n: int = 12, rows: int = 4, mirror: bool = True):
    """A cylinder band of n x rows quads (a uv seam where it closes, smooth vertex normals),
    its uvs mirrored in u on the second half (orientation flips there) when `mirror`."""
    ang = 2 * np.pi * np.arange(n + 1) / n
    z = np.linspace(0.0, 1.0, rows + 1)
    aa, zz = np.meshgrid(ang, z, indexing="ij")
    pos = np.stack([np.cos(aa), np.sin(aa), zz], axis=-1).reshape(-1, 3)
    pos[n * (rows + 1):] = pos[:rows + 1]  # the seam: the last column is the first's points
    nrm = pos.copy()
    nrm[:, 2] = 0.0
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    u = np.arange(n + 1) / n
    if mirror:
        u = np.where(np.arange(n + 1) <= n // 2, u, 1.0 - u)
    uv = np.stack(np.meshgrid(u, z, indexing="ij"), axis=-1).reshape(-1, 2)
    faces = []
    for i in range(n):  # the small test mesh's quads
        for j in range(rows):
            a, b = i * (rows + 1) + j, (i + 1) * (rows + 1) + j
            faces += [(a, b, b + 1), (a, b + 1, a + 1)]
    f = np.asarray(faces)
    # positions by index (the seam's two columns share points but not uvs)
    return pos, f, nrm[f], uv[f]


def _reference(pos, faces, cn, cuv):
    """MikkTSpace corner by corner (the C code's structure), Python loops on a small mesh."""
    tri = []
    for fi, face in enumerate(faces):
        p = pos[face]
        d1, d2 = p[1] - p[0], p[2] - p[0]
        t21, t31 = cuv[fi, 1] - cuv[fi, 0], cuv[fi, 2] - cuv[fi, 0]
        area = t21[0] * t31[1] - t21[1] * t31[0]
        vos = t31[1] * d1 - t21[1] * d2
        s = 1.0 if area > 0 else -1.0
        if abs(area) > 1e-30 and np.linalg.norm(vos) > 1e-30:
            vos = s * vos / np.linalg.norm(vos)
        tri.append((vos, s))
    sums: dict = {}
    keys = {}
    for fi, face in enumerate(faces):
        for c in range(3):
            n = cn[fi, c] / np.linalg.norm(cn[fi, c])
            vos, s = tri[fi]
            t = vos - np.dot(n, vos) * n
            if np.linalg.norm(t) > 1e-30:
                t = t / np.linalg.norm(t)
            p0, p1, p2 = pos[face[(c + 2) % 3]], pos[face[c]], pos[face[(c + 1) % 3]]
            v1, v2 = p0 - p1, p2 - p1
            v1 = v1 - np.dot(n, v1) * n
            v2 = v2 - np.dot(n, v2) * n
            v1, v2 = v1 / np.linalg.norm(v1), v2 / np.linalg.norm(v2)
            angle = math.acos(min(max(float(np.dot(v1, v2)), -1.0), 1.0))
            key = (tuple(np.float32(pos[face[c]])), tuple(np.float32(cn[fi, c])),
                   tuple(np.float32(cuv[fi, c])), s)
            keys[(fi, c)] = key
            sums[key] = sums.get(key, 0.0) + angle * t
    out = np.zeros((len(faces), 3, 3))
    for (fi, c), key in keys.items():
        out[fi, c] = sums[key] / np.linalg.norm(sums[key])
    return out, np.array([s for _, s in tri])


def test_matches_a_corner_by_corner_transcription():
    pos, f, cn, cuv = _wrapped_band()
    t, s = mikk_tangents(pos, f, cn, cuv)
    ref_t, ref_s = _reference(pos, f, cn, cuv)
    assert np.array_equal(s, ref_s)
    assert (s < 0).any() and (s > 0).any()  # both orientations present
    np.testing.assert_allclose(t, ref_t, atol=1e-12)
    # the tangents are unit and in the plane of their corner's normal
    np.testing.assert_allclose(np.linalg.norm(t, axis=2), 1.0, atol=1e-12)
    assert np.abs(np.einsum("fcj,fcj->fc", t, cn)).max() < 1e-12


def test_welding_shares_a_tangent_and_seams_split_it():
    pos, f, cn, cuv = _wrapped_band(mirror=False)
    t, _ = mikk_tangents(pos, f, cn, cuv)
    corner_pos = pos[f].reshape(-1, 3)
    flat_t = t.reshape(-1, 3)
    key = np.round(np.concatenate([corner_pos, cuv.reshape(-1, 2)], axis=1), 9)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    # every corner of one welded vertex has the same tangent
    for g in np.unique(inv)[:20]:
        members = flat_t[inv == g]
        np.testing.assert_allclose(members, np.broadcast_to(members[0], members.shape),
                                   atol=1e-12)
    # on a smooth cylinder with u around it, the tangent is the circumferential direction
    circ = np.stack([-corner_pos[:, 1], corner_pos[:, 0], np.zeros(len(corner_pos))], axis=1)
    np.testing.assert_allclose(np.einsum("ij,ij->i", flat_t, circ), 1.0, atol=2e-2)


def test_plane_frames_in_both_orientations_and_round_trip():
    pos = np.array([[0.0, 0, 0], [2, 0, 0], [0, 3, 0]])
    f = np.array([[0, 1, 2]])
    cn = np.tile([0.0, 0.0, 1.0], (1, 3, 1))
    for mirror in (1.0, -1.0):  # u along +x, then along -x (a mirrored chart)
        cuv = np.array([[[0.0, 0.0], [2.0 * mirror, 0.0], [0.0, 3.0]]])
        t, s = mikk_tangents(pos, f, cn, cuv)
        np.testing.assert_allclose(t[0], np.tile([mirror, 0.0, 0.0], (3, 1)), atol=1e-15)
        assert s[0] == mirror
        fr = frames_at(t, s, cn, np.array([0]), np.array([[0.2, 0.3, 0.5]]))
        np.testing.assert_allclose(fr[0][:, 1], [0.0, 1.0, 0.0], atol=1e-15)  # B = dp/dv
    rng = np.random.default_rng(3)
    pos, f, cn, cuv = _wrapped_band()
    t, s = mikk_tangents(pos, f, cn, cuv)
    m = 200
    face = rng.integers(0, len(f), m)
    b = rng.dirichlet(np.ones(3), m)
    fr = frames_at(t, s, cn, face, b)
    local = rng.normal(size=(m, 3))
    local[:, 2] = np.abs(local[:, 2]) + 0.5
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    np.testing.assert_allclose(encode(fr, decode(fr, local)), local, atol=1e-12)
