"""Rendering a baked asset under a warp Ψ (seed 002 §4): M_org, every M_i and the
characteristic points follow Ψ (`deform_scene`), and the modes of a deformed frame
(`render_deformed`):

- ``gt`` — the deformed M_org, brute force (as `render.gt`): shading normals carried by the
  cofactor of the Jacobian, cof(J) n (the normal of the deformed surface), shadows on the
  deformed M_org.
- ``cpm`` — the characteristic point maps through the look-up rotation L (Eq. 10). Per texel
  and frame (as `render.cpm`): p* = the deformed weighted centroid of the texel's points, the
  view direction v* from p* to the camera, and per point and light the direction l* from
  the deformed point Ψ(x̂k) to the light with the attenuation of Eq. 11 (A(d) = 1/d² from
  the deformed point). (l, v) = L (l*, v*) are the rest-frame directions at which Eq. 12 of
  seed 000 is evaluated with the rest points, normals, weights and a_vis tables. The
  seed's L of a texel (`lookup="vertex"`) comes from the impostor parameterization of M1
  (Table 1): the rest centroid's closest point on M1, R0 and the deformed (u, v) = J (u0, v0)
  of the triangle's vertices interpolated there (`texelbake.deform.lookup`); it gives the
  texel's view direction, view term and a_vis. The default (`lookup="point"`,
  `DEFAULT_LOOKUP`) turns each point's light and view directions for its BRDF by the point's
  own L (its shading frame carried by Ψ's Jacobian at the point), the seed's limit where the
  impostor is the surface (§4.4). Shadow rays are traced from the deformed
  points toward the lights against the deformed M_org, so shadows one part casts on another
  after the deformation are seen (inter-object shadows on the deformed geometry). The view
  term V(x̂k, ωo) is traced at rest (rest point, rest-frame direction, rest M_org): Eq. 12
  divides by a_vis, the rest texel's visible projected area toward ωo from the baked table,
  and only a numerator with the same masking keeps the ratio a weighted mean of the points'
  radiance. Traced on the deformed M_org instead, a deformation that opens a masked groove
  (a twist, a bend's outer side) gave visible points where the table's a_vis was ~1e-11, and
  texel radiances up to 1e7 (the twisted cylinder's cpm image at −3 dB). Masking by other
  parts after the deformation is left to the eye rays, which meet the deformed M_i. Eye rays
  are traced against the deformed M_i; the atlas uv of a hit is unchanged by Ψ, the mip
  level follows the deformed triangle's uv density.
  Option `lookup="texel"`: the texel itself as the impostor point, R0 its baked frame and
  (u, v) = J (t, b) at its centroid (no interpolation across M1's coarse triangles; see
  `LOOKUPS`, measured beside the default in `benchmarks/deform.py` as ``cpm-texel``).
  Option `lookup="affine"`: as the default, but the texel's view term, projected areas and
  a_vis are read along J⁻¹ v* (J Ψ's Jacobian at the texel's centroid) instead of L v*: a
  rotation cannot follow a non-uniform stretch (§4.4), the inverse Jacobian can, exactly
  for a locally affine Ψ (`_level_geometry`; ``cpm-affine`` in the benchmark).
- ``cpm-naive`` — the same with L = I: the rest tables looked up with the deformed world's
  directions (what L buys).
- ``normalmap`` — the studio baseline on the deformed M1: its tangent frame rebuilt from the
  deformed triangles and the atlas uvs (what a game engine's skinned tangent space does).
- ``equal-time`` — the deformed M_org shaded as ``gt`` for cpm's time.
- ``srf`` / ``srf-naive`` — the captured reflectance field through L / without it
  (`texelbake.srf.mode`).
"""

from __future__ import annotations

import copy
import dataclasses
import time

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.brdf.evaluate import shading_normal
from texelbake.deform.impostor import ImpostorParams, decode_frames, impostor_params
from texelbake.deform.lbs import SkinWarp, transfer_weights
from texelbake.deform.lookup import (
    align_quarter_turns,
    deformed_tangents,
    lookup_rotation,
    rest_frames_at,
)
from texelbake.deform.normals import cofactor, deform_normals
from texelbake.deform.refine import refine_levels, subdivide
from texelbake.deform.skinbind import dense_weights
from texelbake.deform.warps import MeshWarp, Warp
from texelbake.errors import SettingsError
from texelbake.geometry.basis import tangent_frames
from texelbake.geometry.mesh import face_normals
from texelbake.geometry.normal_input import mapped_normals
from texelbake.geometry.raycast import RayCaster
from texelbake.render.cpm import CpmFrame
from texelbake.render.scene import RenderScene, _hausdorff, _uv_ratio, set_atlas_surface
from texelbake.render.texel_radiance import texel_points
from texelbake.tol import TOL
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.shade import light_at
from texelbake.usd.lodmesh import LodMesh

#: the Jacobian field the characteristic points, the LOD vertices and the look-up read when
#: the frame follows the deformed M_org (`deform_scene(follow="mesh")`): "vertex" — Ψ's own
#: Jacobian at M_org's vertices interpolated on its triangles, the field gt's shading normals
#: cof(J) n come from; "triangle" — each M_org triangle's constant affine map (a flat face of a coarse M_org then turns as one piece while gt shades it as the
#: warped, curved surface)
JACOBIAN_FIELDS = ("vertex", "triangle")


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


def lod_impostor(scene: RenderScene, i: int) -> ImpostorParams:
    """The Table 1 parameterization of M_{i+1}: read from the payload when the bake stored
    it (`LodMesh.impostor`), else computed from the rest mesh and its atlas uvs."""
    mesh = scene.baked.meshes[i]
    stored = getattr(mesh, "impostor", None)
    if stored:
        return ImpostorParams(*(np.asarray(stored[k], np.float64)
                                for k in ("p0", "r0", "u0", "v0")))
    return impostor_params(mesh.vertices, mesh.faces, mesh.corner_uvs)


def _refined_lods(scene: RenderScene, refine: float, n_joints: int = 0
                  ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], list[np.ndarray],
                             np.ndarray, list[np.ndarray | None]]:
    """The rest LOD meshes refined (`deform.refine`) until no edge is longer than
    diag / refine (0: unrefined): [(vertices, faces, corner_uvs)], the uv-exact flag of each
    refined face, R0 (n, 3, 3) of the refined M1's vertices (the stored parameterization on
    M1's own vertices, a new one — `impostor_params` of the refined mesh — on the added), and
    per LOD its dense skin weights (n, n_joints) from the payload's binding on the LOD's own
    vertices and, on the added ones, transferred from M_org's skin as the payload's binding
    was (`lbs.transfer_weights`: closest point, barycentric blend, ≤ 4 influences) (None:
    no binding, or n_joints = 0). The mean of an edge's ends' weights would put the added vertices of the arm's long M1 edges up to 0.38 (10 % of the
    diagonal) off the bent M_org: linear blending of averaged weights is not the skinning of
    the surface between two vertices whose weights differ."""
    out, exact, weights = [], [], []
    frames0 = np.zeros((0, 3, 3))
    for i, m in enumerate(scene.baked.meshes):
        v, f, cuv = m.vertices, m.faces, m.corner_uvs
        ex = np.asarray(scene.lod_uv_exact[i])
        w = (dense_weights(m.skin["indices"], m.skin["weights"], n_joints)
             if n_joints and m.skin else None)
        k = refine_levels(v, f, scene.diag / refine) if refine > 0 else 0
        n_own = v.shape[0]
        for _ in range(k):  # a loop over the few subdivision levels
            v, f, cuv, extra, parent = subdivide(v, f, cuv, () if w is None else (w,))
            ex = ex[parent]
            w = extra[0] if w is not None else None
        skin = scene.asset.skin
        if w is not None and k and skin is not None and skin.weights.shape[1] == n_joints:
            w[n_own:] = transfer_weights(v[n_own:], scene.asset.points, scene.asset.faces,
                                         skin.weights)
        out.append((v, f, cuv))
        exact.append(ex)
        weights.append(w)
        if i == 0:
            prm = lod_impostor(scene, 0)
            frames0 = decode_frames(prm.r0, prm.u0, prm.v0)
            if k:
                added = impostor_params(v, f, cuv)
                fr = decode_frames(added.r0, added.u0, added.v0)
                fr[: frames0.shape[0]] = frames0
                frames0 = fr
    return out, exact, frames0, weights


def deform_scene(scene: RenderScene, warp: Warp, *, follow: str = "mesh",
                 jacobian: str = "exact", refine: float = 16.0,
                 jacobian_field: str = "vertex") -> RenderScene:
    """A copy of `scene` whose M_org and M_i are warped by Ψ (module docstring); the baked
    tables stay at rest.

    follow : "mesh" (default) — Ψ moves M_org's vertices (what a deformer does to an asset:
        the surface between them stays flat), and everything else (M_i, the characteristic
        points, the Jacobians of the look-up) follows the deformed M_org
        (`deform.warps.MeshWarp`: closest rest triangle, barycentrics, normal offset; its
        affine Jacobian); "warp" — Ψ itself everywhere, which matches the deformed M_org only
        where M_org is tessellated finely against Ψ's curvature (the small cylinder has 2
        rings along its axis: bent by Ψ its M_org is a flat chord while the characteristic
        points lie on the arc, and its cpm image lost 10–16 dB to that alone).
    jacobian : "exact" (the warp's) or "central" (Eq. 6) for (u, v).
    refine : the LOD meshes are subdivided until no rest edge exceeds diag / refine, so that
        they can follow Ψ (`deform.refine`; 0: as baked)."""
    if follow not in ("mesh", "warp"):
        raise SettingsError(f"field 'follow': 'mesh' or 'warp', got {follow!r}")
    if jacobian_field not in JACOBIAN_FIELDS:
        raise SettingsError(f"field 'jacobian_field': one of {JACOBIAN_FIELDS}, got "
                            f"{jacobian_field!r}")
    t0 = time.perf_counter()
    # the asset's own skinning (`warp_at_time` of a skinned asset): LOD meshes with a UsdSkel
    # binding in the payload follow it with their own weights, as UsdSkel animates them
    skin_xf = getattr(warp, "transforms", None)
    skin_rest = getattr(warp, "rest_transforms", None)
    n_joints = 0 if skin_xf is None else int(np.shape(skin_xf)[0])
    d = copy.copy(scene)
    a = scene.asset
    jac_v = warp.jacobian(a.points)  # shading normals: Ψ's own Jacobian at the vertices
    pts = warp.positions(a.points)
    if follow == "mesh":
        warp = MeshWarp(a.points, pts, a.faces, name=warp.name, scale=warp.scale,
                        vertex_jacobians=jac_v if jacobian_field == "vertex" else None)
    corner = deform_normals(jac_v[a.faces.reshape(-1)],
                            a.corner_normals.reshape(-1, 3)).reshape(a.corner_normals.shape)
    d.asset = dataclasses.replace(a, points=pts, corner_normals=corner)
    d.eye_box = None  # the rest pose's box does not hold the warped meshes: no eye-ray cull
    d.org = RayCaster(pts, a.faces, cutout=scene.org.cutout)  # cut-outs move with the surface
    d.org_face_normals = face_normals(d.asset.points, d.asset.faces)
    # the materials' normal maps decode in the deformed surface's own tangent frames
    d.normal_input = mapped_normals(d.asset, shading_normal)
    # diag and ray_eps stay the rest scene's: a length of the object, not of its axis-aligned
    # box, which a rotation changes (a rigidly moved asset must render as the unmoved one)
    rest_lods, exact, frames0, lod_w = _refined_lods(scene, refine, n_joints)
    lod_warps: list[Warp] = [
        warp if w is None else SkinWarp(np.asarray(skin_xf), v, f, w, name=warp.name,
                                        scale=warp.scale, rest_transforms=skin_rest)
        for (v, f, _), w in zip(rest_lods, lod_w, strict=True)]
    meshes = [LodMesh(lw.positions(v), f, cuv)
              for (v, f, cuv), lw in zip(rest_lods, lod_warps, strict=True)]
    d.baked = dataclasses.replace(scene.baked, meshes=meshes)
    d.lod_uv_exact = tuple(exact)
    d.lods = [RayCaster(m.vertices, m.faces) for m in meshes]
    if scene.atlas_separate:  # the CPM's atlas mesh follows the warp too
        av, af, ac = scene.atlas_arrays
        d.atlas_arrays = (warp.positions(av), af, ac)
        d.atlas_caster = RayCaster(d.atlas_arrays[0], af)
    d.lod_face_normals = [face_normals(m.vertices, m.faces) for m in meshes]
    d.lod_uv_ratio = tuple(
        _uv_ratio(m.vertices, m.faces, m.corner_uvs, i == 0 and not scene.atlas_separate,
                  exact=ex)[0]
        for i, (m, ex) in enumerate(zip(meshes, exact, strict=True)))
    set_atlas_surface(d)
    d.lod_error = [_hausdorff(d.org, c, pts, m.vertices) for c, m in zip(d.lods, meshes,
                                                                          strict=True)]
    d._nm = None  # the normal map's tangent frames follow the deformed M1
    d._btf = None
    # the impostor parameterization of M1 and its deformed tangents (Eq. 6 / exact J)
    # (u0, v0) are R0's first two columns, decoded from r0 (orthonormal to rounding whatever
    # precision r0 was stored at), so that a rigid motion Q gives L = R0 R0ᵀ Qᵀ = Qᵀ exactly
    m1_rest, m1_faces, _ = rest_lods[0]
    u, v = deformed_tangents(lod_warps[0], m1_rest, frames0[:, :, 0], frames0[:, :, 1], jacobian)
    d.warp = warp  # type: ignore[attr-defined]
    d.rest = scene  # type: ignore[attr-defined]
    d.m1_rest = (RayCaster(m1_rest, m1_faces), m1_faces)  # type: ignore[attr-defined]
    d.m1_frames0 = frames0  # type: ignore[attr-defined]
    d.m1_uv = (u, v)  # type: ignore[attr-defined]
    d.deformed_levels = {}  # type: ignore[attr-defined]
    d.setup_seconds = time.perf_counter() - t0
    return d


def vertex_lookup(d: RenderScene, prim: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """The seed's look-up rotation L (Eqs. 7–10) at points of M1 given by triangle `prim`
    (k,) and barycentrics `bary` (k, 3): R0 and the deformed (u, v) of the Table 1
    parameterization on the triangle's vertices (quarter turns aligned), interpolated.
    Returns (k, 3, 3) deformed world -> rest world."""
    _, m1_faces = d.m1_rest  # type: ignore[attr-defined]
    corners = m1_faces[prim]  # (k, 3)
    f0 = d.m1_frames0  # type: ignore[attr-defined]
    u, v = d.m1_uv  # type: ignore[attr-defined]
    cu0, cv0, cu, cv = align_quarter_turns(f0[corners, :, 0], f0[corners, :, 1],
                                           u[corners], v[corners])

    def interp(x: np.ndarray) -> np.ndarray:
        return np.einsum("nk,nkj->nj", bary, x)

    r0 = rest_frames_at(interp(cu0), interp(cv0))
    lrot, _ = lookup_rotation(r0, interp(cu), interp(cv),
                              fallback_normal=d.lod_face_normals[0][prim])
    return lrot


def _level_geometry(d: RenderScene, level: int) -> dict[str, np.ndarray]:
    """Per level, once per deformed scene: the deformed points Ψ(x̂k), their deformed
    geometric normals (ray offsets), and per texel the look-up rotation L (t, 3, 3)."""
    cache = d.deformed_levels  # type: ignore[attr-defined]
    if level in cache:
        return cache[level]
    warp: Warp = d.warp  # type: ignore[attr-defined]
    rest: RenderScene = d.rest  # type: ignore[attr-defined]
    cp = rest.points(level)
    pos = cp["position"]
    jac = warp.jacobian(pos)
    out = {"position": warp.positions(pos), "geom_normal": deform_normals(jac, cp["geom_normal"])}
    # per texel: the rest weighted centroid, its closest point on the rest M1
    offsets = rest.baked.levels[level]["texel_offsets"]
    n_tex = offsets.shape[0] - 1
    tex = np.repeat(np.arange(n_tex), np.diff(offsets))
    ws = np.abs(cp["weight"]).sum(axis=1)
    ws = np.where(np.bincount(tex, ws, n_tex)[tex] > 0, ws, 1.0)
    wsum = np.bincount(tex, ws, n_tex)
    cen = np.stack([np.bincount(tex, ws * pos[:, c], n_tex) for c in range(3)], axis=1)
    live = wsum > 0
    cen = np.divide(cen, wsum[:, None], out=np.zeros_like(cen), where=live[:, None])
    lrot = np.broadcast_to(np.eye(3), (n_tex, 3, 3)).copy()
    if live.any():
        m1_caster, _ = d.m1_rest  # type: ignore[attr-defined]
        _, prim, b2 = m1_caster.closest_points(cen[live])
        lrot[live] = vertex_lookup(d, prim, np.column_stack([1.0 - b2[:, 0] - b2[:, 1], b2]))
    out["lookup:vertex"] = lrot
    # the texel as the impostor point (seed 002 §4.2 allows point-sampled impostors): R0 the
    # texel's own frame (rows t, b, n), (u, v) = J (t, b) at the texel's centroid
    frames = rest.baked.levels[level]["frames"].astype(np.float64)
    r0_tex = np.transpose(frames, (0, 2, 1))  # columns (t, b, n)
    lrot_t = np.broadcast_to(np.eye(3), (n_tex, 3, 3)).copy()
    if live.any():
        jc = warp.jacobian(cen[live])
        lrot_t[live], _ = lookup_rotation(
            r0_tex[live], np.einsum("nij,nj->ni", jc, frames[live, 0]),
            np.einsum("nij,nj->ni", jc, frames[live, 1]),
            fallback_normal=deform_normals(jc, frames[live, 2]))
    out["lookup:texel"] = lrot_t
    # option "affine": the texel's view term, projected area and a_vis along J⁻¹ v* (J Ψ's
    # Jacobian at the texel's centroid), not L v*. Under an affine Ψ a ray x + t ω of the rest
    # texel maps to Ψ(x) + t J ω, so the points that see ω* = J ω in the deformed world are
    # exactly those that see ω at rest, and by Nanson's formula (dA* n* = cof(J) dA n) a
    # point's deformed projected area toward ω* is det J |J⁻¹ ω*| times its rest one toward
    # J⁻¹ ω* / |J⁻¹ ω*| — a factor common to the texel's points, which Eq. 12's division by
    # a_vis cancels. L (a rotation) is the same where J is a rotation times a scale; under a
    # non-uniform stretch it is not (seed §4.4, limitation 2). J⁻¹ is taken as adj(J) =
    # cof(J)ᵀ (its scale drops out of the unit direction); where det J ≤ AFFINE_MIN_DET of
    # (|J|_F / √3)³ (a squeezed or folded texel) the texel keeps the vertex L.
    view_aff = lrot.copy()
    if live.any():
        det = np.linalg.det(jc)
        scale = (np.linalg.norm(jc, axis=(1, 2)) / np.sqrt(3.0)) ** 3
        ok = det > AFFINE_MIN_DET * scale
        view_aff[np.flatnonzero(live)[ok]] = np.transpose(cofactor(jc[ok]), (0, 2, 1))
    out["view:affine"] = view_aff
    # each characteristic point as its own impostor point (the seed's limit where the impostor
    # is the surface, §4.4): R0 its shading frame, (u, v) = J (t, b) with J the deformed
    # M_org's own affine map at the point (per point, not per texel)
    fr = tangent_frames(cp["normal"])  # rows (t, b, n)
    out["lookup:point"], _ = lookup_rotation(
        np.transpose(fr, (0, 2, 1)), np.einsum("nij,nj->ni", jac, fr[:, 0]),
        np.einsum("nij,nj->ni", jac, fr[:, 1]), fallback_normal=out["geom_normal"])
    cache[level] = out
    return out


#: where the look-up rotation L of a texel comes from: "texel" (the texel as the impostor
#: point: R0 its baked frame, J at its centroid), "vertex" (the seed's: Table 1 on M1's
#: vertices, from the payload, interpolated at the centroid's closest point), "none" (L = I,
#: ``cpm-naive``), "point" (the default: each characteristic point's BRDF directions through
#: its own L — its shading frame carried by the deformed M_org's Jacobian at the point —, the
#: texel's view direction, view term and a_vis through "vertex"), "affine" (as "point", but the
#: texel's view direction, view term, projected areas and a_vis through Ψ's inverse Jacobian
#: at the texel's centroid instead of a rotation: exact for a locally affine Ψ, a
#: non-uniform stretch included; `_level_geometry`)
LOOKUPS = ("texel", "vertex", "none", "point", "affine")
#: a texel whose det J is at or below this fraction of (|J|_F / √3)³ (1 for a rotation) keeps
#: the vertex L under "affine": J⁻¹ would be dominated by rounding, or the texel is folded
#: (det J < 0); 1e-9 is far below any real stretch (a 1000:1 squeeze in every direction)
AFFINE_MIN_DET = 1e-9
#: the default look-up (docs/decisions.md: measured in `benchmarks/deform.py` against the
#: seed's "vertex", ``cpm-vertex`` there, it never loses and wins on 7 of 8 deformed frames,
#: by up to 40 dB where M1's interpolated frame is a few degrees off a faceted metal's own
#: rotation and puts a false mirror highlight in a texel)
DEFAULT_LOOKUP = "point"


def deformed_texel_radiance(d: RenderScene, level: int, cam_pos: np.ndarray,
                            texels: np.ndarray, lookup: str = DEFAULT_LOOKUP
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Eq. 12 of seed 000 for texels of one level of a deformed scene (module docstring);
    the same contract as `render.texel_radiance.texel_radiance`. lookup : one of LOOKUPS."""
    rest: RenderScene = d.rest  # type: ignore[attr-defined]
    lv = rest.baked.levels[level]
    offsets = lv["texel_offsets"]
    texels, exists, tex, pt = texel_points(offsets, texels)
    n_tex, n_pts = texels.shape[0], pt.shape[0]
    radiance = np.zeros((n_tex, 3))
    avis = np.zeros(n_tex)
    if n_pts == 0:
        return radiance, avis, exists, 0
    cp = rest.points(level)
    geo = _level_geometry(d, level)
    ng, ns, w = cp["geom_normal"][pt], cp["normal"][pt], cp["weight"][pt]
    pos_d, ng_d = geo["position"][pt], geo["geom_normal"][pt]
    per_point = lookup in ("point", "affine")
    lrot = (np.broadcast_to(np.eye(3), (n_tex, 3, 3)) if lookup == "none"
            else geo["lookup:vertex"][texels] if per_point
            else geo[f"lookup:{lookup}"][texels])  # (t, 3, 3) deformed world -> rest world
    lpt = geo["lookup:point"][pt] if per_point else None  # (k, 3, 3) per point
    # one view direction per texel: deformed weighted centroid -> camera
    ws = np.abs(w).sum(axis=1)
    ws = np.where(np.bincount(tex, ws, n_tex)[tex] > 0, ws, 1.0)
    wsum = np.bincount(tex, ws, n_tex)
    cen = np.stack([np.bincount(tex, ws * pos_d[:, c], n_tex) for c in range(3)], axis=1)
    cen = np.divide(cen, wsum[:, None], out=np.zeros_like(cen), where=wsum[:, None] > 0)
    wo_d_tex = _unit(cam_pos[None, :] - cen)
    wo_tex = (_unit(np.einsum("nij,nj->ni", geo["view:affine"][texels], wo_d_tex))
              if lookup == "affine"  # J⁻¹ v* (`_level_geometry`)
              else np.einsum("nij,nj->ni", lrot, wo_d_tex))  # rest frame (Eq. 10)
    wo = wo_tex[tex]
    g = TOL.grazing_cos
    cos_go = np.einsum("ij,ij->i", ng, wo)
    view = (cos_go > g) & (np.einsum("ij,ij->i", ns, wo) > g)
    rays = 0
    vi = np.flatnonzero(view)
    if vi.size:  # V(x̂k, ωo) at rest, along the rest-frame direction (docstring)
        tmax = np.linalg.norm(cam_pos[None, :] - pos_d[vi], axis=1)
        occ = rest.org.occluded(cp["position"][pt][vi] + rest.ray_eps * ng[vi], wo[vi],
                                tmax=tmax)
        rays += vi.size
        view[vi[occ]] = False
    mat, uv = cp["material"][pt], cp["uv"][pt]
    lit = np.zeros((n_pts, 3))
    seen = np.flatnonzero(view)
    if seen.size:
        frames = tangent_frames(ns[seen])
        for light in d.lights:  # a loop over the few lights
            wi_d, e, tmax = light_at(light, pos_d[seen])  # Eq. 11: 1/d² from Ψ(x̂k)
            wi = np.einsum("nij,nj->ni", lrot[tex[seen]] if lpt is None else lpt[seen], wi_d)
            cos_s = np.einsum("ij,ij->i", ns[seen], wi)
            ok = (np.einsum("ij,ij->i", ng[seen], wi) > g) & (cos_s > g) & (e.max(axis=1) > 0)
            idx = np.flatnonzero(ok)
            if idx.size == 0:
                continue
            tm = tmax[idx] if np.isfinite(tmax[idx]).any() else np.inf
            occ = d.org.occluded(pos_d[seen[idx]] + d.ray_eps * ng_d[seen[idx]], wi_d[idx],
                                 tmax=tm)
            rays += idx.size
            idx = idx[~occ]
            if idx.size == 0:
                continue
            fr = frames[idx]
            wi_l = np.einsum("nij,nj->ni", fr, wi[idx])
            wo_b = (wo[seen[idx]] if lpt is None else np.einsum(
                "nij,nj->ni", lpt[seen[idx]], wo_d_tex[tex[seen[idx]]]))
            wo_l = np.einsum("nij,nj->ni", fr, wo_b)
            f = brdf_mod.evaluate_by_face(d.materials, mat[seen[idx]], wi_l, wo_l,
                                          uv[seen[idx]],
                                          var=None if cp["var"] is None
                                          else cp["var"][pt][seen[idx]])
            lit[seen[idx]] += e[idx] * f * cos_s[idx, None]
    contrib = np.where(view[:, None], lit * w * cos_go[:, None], 0.0)
    num = np.stack([np.bincount(tex, contrib[:, c], n_tex) for c in range(3)], axis=1)
    live = np.flatnonzero(exists)
    wo_local = np.einsum("nij,nj->ni", lv["frames"][texels[live]], wo_tex[live])
    a, valid = rest.avis_table(level).evaluate(texels[live], wo_local)
    radiance[live] = np.where(valid[:, None], num[live] / np.where(valid, a, 1.0)[:, None], 0.0)
    avis[live] = np.where(valid, a, 0.0)
    return radiance, avis, exists, rays


class DeformedCpmFrame(CpmFrame):
    """`render.cpm.CpmFrame` whose texel radiance is `deformed_texel_radiance`."""

    def __init__(self, scene: RenderScene, cam: PinholeCamera, mesh: int, lookup: str) -> None:
        if lookup not in LOOKUPS:
            raise SettingsError(f"field 'lookup': one of {LOOKUPS}, got {lookup!r}")
        super().__init__(scene, cam, mesh)
        self.lookup = lookup

    def _compute(self, j: int, todo: np.ndarray) -> None:
        if todo.size:
            rad, avis, ex, done, _ = self._arrays(j)
            r, a, e, n_rays = deformed_texel_radiance(self.scene, j, self.cam_pos, todo,
                                                      self.lookup)
            rad[todo], avis[todo], ex[todo], done[todo] = r, a, e, True
            self.rays += n_rays
