"""The LOD chain LOD1 ⊃ LOD2 ⊃ … chosen by the geometric error each level may show where it
is used (DESIGN.md "Geometry"), not by the CPM atlas.

Level i switches in when the asset's bounding-box diagonal D covers `switch_px[i]` pixels on
screen; one pixel there is D / switch_px[i] world units, so the level may deviate from M_org by
at most bound_i = error_px · D / switch_px[i] (the two-sided Hausdorff distance). The level is
the smallest quadric edge collapse (Garland–Heckbert, seed 000 §4.1; pymeshlab with boundary
and normal preservation, `hierarchy._decimate`) of the previous level whose *enclosed* mesh
(`hierarchy.enclose`, which moves faces out to M_org's outline) still lies within the bound:
the bound is checked after enclosing, so enclosing never takes a level out of it. The face
count is found by bisection in log space (QEM error grows with fewer faces, not strictly).

The Hausdorff distance is pymeshlab's (`get_hausdorff_distance`) from a deterministic point set
(the mesh's vertices plus seeded stratified samples, `sampling.sample_surface`) to the other
mesh's surface, both ways; pymeshlab's own face sampling is random per call, and reruns must be
byte-identical.

Hard cases (each tested in tests/geometry/test_lodchain.py):
- M_org already coarser than the bound (no collapse of even 1 - KEEP_FRACTION of its faces
  stays within it): LOD1 *is* M_org, no simplification, said in the level's note.
- A level that would keep more than KEEP_FRACTION of the previous level's faces is not worth
  a switch: the chain stops there and says so (`LodChain.stopped`).
- Many small parts: QEM never joins parts, so a bound coarser than the parts cannot be met by
  collapsing; when the collapse stalls on an asset of `hierarchy.WRAP_MIN_PARTS` parts or more,
  the parts are merged into one wrap at half the bound (`hierarchy.wrap`), tightened back onto
  M_org, and used if it is within the bound and smaller; otherwise the parts are kept and the
  chain stops, saying so.
- Open surfaces keep their boundary (preserveboundary, with the weighted redo of
  `hierarchy._decimate`); non-manifold input is welded and collapsed like any other; both are
  measured by the same two-sided distance, so a level that tears an edge away is rejected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pymeshlab

from texelbake.errors import SettingsError, StageError
from texelbake.geometry.hierarchy import (
    MIN_FACES,
    WRAP_MIN_PARTS,
    _decimate,
    enclose,
    wrap,
)
from texelbake.geometry.mesh import Mesh, bbox_diagonal, compact, face_components, weld
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.sampling import sample_surface

#: a level keeping more than this fraction of the previous level's faces is not a LOD worth
#: switching to (meshoptimizer's and Simplygon's chains stop at about the same point)
KEEP_FRACTION = 0.8
#: surface samples per mesh for the Hausdorff distance (plus the mesh's vertices); the
#: distance of a sample set of spacing s underestimates the true one by at most about s
HAUSDORFF_SAMPLES = 20_000
#: bisection over the face count stops when the bracket is narrower than this ratio
SEARCH_RATIO = 1.08
#: a level searched from a mesh of more faces than this is searched from one collapse of it to
#: this many faces (`_proxy`), when that collapse lies within PROXY_SHARE of the level's
#: bound: the search's collapses then cost what they cost on an asset of this size. The
#: share is what the proxy may take of the bound (every candidate is measured against M_org:
#: the level stays within its bound, it may keep more faces than a search from M_org would).
#: A 1.5 M-triangle wall with jittered fronts (`benchmarks/million.py`) is 15 % of LOD1's
#: bound away from M_org even at 80 % of its faces: a quarter of the bound rejected its
#: 200k proxy
PROXY_FACES = 200_000
PROXY_SHARE = 0.5
#: the wrap tried on assets of many parts uses a marching-cubes grid of at most this many
#: cells along the longest side (400, the M_T wrap's, took 15 s on 36 boxes at 64 px; the
#: distance check rejects a wrap the coarse grid makes too crude)
LOD_WRAP_CELLS = 96


@dataclass(frozen=True, eq=False)
class LodLevel:
    """One level of the chain. distances in world units; `hausdorff` = max of the two."""

    mesh: Mesh
    switch_px: float
    bound: float
    hausdorff: float
    lod_to_org: float
    org_to_lod: float
    method: str  # "original" | "qem" | "wrap"
    enclosed: bool
    note: str = ""

    def report(self, diag: float) -> dict:
        return {
            "triangles": int(self.mesh.num_faces),
            "switch_px": float(self.switch_px),
            "bound": float(self.bound),
            "bound_rel": float(self.bound / diag),
            "hausdorff": float(self.hausdorff),
            "hausdorff_rel": float(self.hausdorff / diag),
            "hausdorff_lod_to_org": float(self.lod_to_org),
            "hausdorff_org_to_lod": float(self.org_to_lod),
            "within_bound": bool(self.hausdorff <= self.bound),
            "method": self.method,
            "enclosed": bool(self.enclosed),
            "note": self.note,
        }


@dataclass
class LodChain:
    levels: list[LodLevel]
    diag: float
    stopped: str = ""
    notes: list[str] = field(default_factory=list)

    def report(self) -> dict:
        return {"diag": float(self.diag), "levels": [lv.report(self.diag) for lv in self.levels],
                "stopped": self.stopped, "notes": list(self.notes)}


def error_bounds(diag: float, switch_px: tuple[float, ...] | list[float],
                 error_px: float) -> list[float]:
    """bound_i = error_px · D / switch_px[i] (module docstring); switch sizes must decrease."""
    px = [float(p) for p in switch_px]
    if not px or any(not p > 0 for p in px):
        raise SettingsError(f"lod_switch_px must be positive pixel sizes, got {list(switch_px)}")
    if any(b >= a for a, b in zip(px, px[1:], strict=False)):
        raise SettingsError(f"lod_switch_px must decrease (LOD1 switches in first), got {px}")
    if not float(error_px) > 0:
        raise SettingsError(f"lod_error_px must be > 0, got {error_px}")
    return [float(error_px) * float(diag) / p for p in px]


def _cloud(mesh: Mesh, n: int, seed: int) -> np.ndarray:
    s = sample_surface(mesh.vertices, mesh.faces, n, seed).positions
    return np.concatenate([mesh.vertices, s])


def _one_way(points: np.ndarray, target: Mesh, diag: float) -> float:
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points, dtype=np.float64)))
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(target.vertices),
                               face_matrix=np.ascontiguousarray(target.faces, dtype=np.int32)))
    try:
        r = ms.get_hausdorff_distance(sampledmesh=0, targetmesh=1, samplevert=True,
                                      sampleedge=False, sampleface=False,
                                      samplenum=int(points.shape[0]),
                                      maxdist=pymeshlab.PureValue(4.0 * diag))
    except (pymeshlab.PyMeshLabException, ValueError) as exc:  # pragma: no cover - defensive
        raise StageError(f"geometry: Hausdorff distance failed: {exc}") from exc
    return float(r["max"])


def hausdorff(a: Mesh, b: Mesh, *, org_points: np.ndarray | None = None, seed: int = 0,
              n_samples: int = HAUSDORFF_SAMPLES) -> tuple[float, float]:
    """(max distance from a to b's surface, from b to a's surface), pymeshlab's point-to-surface
    distance from a's vertices plus `n_samples` seeded samples (b's: `org_points` when given,
    so a chain measured against one M_org reuses its samples)."""
    diag = bbox_diagonal(np.concatenate([a.vertices, b.vertices]))
    pa = _cloud(a, n_samples, seed)
    pb = org_points if org_points is not None else _cloud(b, n_samples, seed)
    return _one_way(pa, b, diag), _one_way(pb, a, diag)


class _Evaluator:
    """Candidate levels measured against one M_org: collapse, enclose, two-sided distance."""

    def __init__(self, org: Mesh, probe: np.ndarray, do_enclose: bool, seed: int):
        self.org = org
        self.diag = bbox_diagonal(org.vertices)
        self.org_points = _cloud(org, HAUSDORFF_SAMPLES, seed)
        self.org_caster = RayCaster(org.vertices, org.faces)
        self.probe = probe
        self.do_enclose = do_enclose
        self.seed = seed

    def distances(self, mesh: Mesh) -> tuple[float, float]:
        """The two one-way distances of `hausdorff` from the same point sets, by Embree's
        closest points (the search's many candidates: ~5x faster than pymeshlab's filter;
        the chosen levels are measured again by pymeshlab, `build_lod_chain`)."""
        pts = _cloud(mesh, HAUSDORFF_SAMPLES, self.seed)
        cp, _, _ = self.org_caster.closest_points(pts)
        cq, _, _ = RayCaster(mesh.vertices, mesh.faces).closest_points(self.org_points)
        return (float(np.linalg.norm(cp - pts, axis=1).max()),
                float(np.linalg.norm(cq - self.org_points, axis=1).max()))

    def measure(self, mesh: Mesh, bound: float, *, tighten: bool = False
                ) -> tuple[Mesh, float, float, bool]:
        """The enclosed mesh and its two one-way distances when enclosing keeps it within
        `bound`, else the mesh as collapsed (enclosing never takes a level out of its bound)."""
        if self.do_enclose:
            moved, step = enclose(mesh, self.probe, tighten=tighten)
            if step > 0.0:
                enc = self.distances(moved)
                if max(enc) <= bound:
                    return moved, enc[0], enc[1], True
        plain = self.distances(mesh)
        return mesh, plain[0], plain[1], False

    def collapse(self, prev: Mesh, target: int, level: int, bound: float):
        """(mesh, d_lo, d_ol, enclosed), or None when the collapse degenerates."""
        try:
            mesh = _decimate(prev, target, level)
        except StageError:
            return None
        return self.measure(mesh, bound)


def _within(cand, bound: float) -> bool:
    return cand is not None and max(cand[1], cand[2]) <= bound


def _proxy(ev: _Evaluator, prev: Mesh, bound: float, level: int):
    """(source, candidate): a mesh whose levels keep fewer than PROXY_FACES faces anyway
    (KEEP_FRACTION of it is more) is collapsed once to PROXY_FACES, and when that collapse lies within PROXY_SHARE of the bound the search's
    candidates are collapsed from it (source) with it as the first candidate; else (prev,
    None). Every candidate is still measured against M_org, so a level found from the proxy
    is within its bound like any other; only the search's cost changes (each of its ~10
    quadric collapses starts from PROXY_FACES faces, not from a million)."""
    if math.floor(KEEP_FRACTION * prev.num_faces) <= PROXY_FACES:
        return prev, None
    try:
        proxy = _decimate(prev, PROXY_FACES, level)
    except StageError:
        return prev, None
    cand = ev.measure(proxy, bound)
    if max(cand[1], cand[2]) > PROXY_SHARE * bound:
        return prev, None
    return proxy, cand


def _search(ev: _Evaluator, prev: Mesh, bound: float, level: int):
    """The smallest collapse of `prev` within `bound`: (mesh, d_lo, d_ol, enclosed) or None
    when no collapse to at most KEEP_FRACTION of prev's faces stays within it. A collapse with
    locked boundaries may stop above its target (`hierarchy._decimate` redoes it unlocked only
    past 1.5x), so the targets are bisected and the result judged by its actual faces."""
    keep = math.floor(KEEP_FRACTION * prev.num_faces)
    hi = max(MIN_FACES, keep)
    if hi >= prev.num_faces:
        return None
    source, best = _proxy(ev, prev, bound, level)
    if best is None:
        best = ev.collapse(prev, hi, level, bound)
    else:
        hi = best[0].num_faces
    if not _within(best, bound):
        return None
    lo = MIN_FACES
    low = ev.collapse(source, lo, level, bound)
    if _within(low, bound):
        best, hi = low, lo
    while hi / lo > SEARCH_RATIO:  # a bisection over the face count (log space), ~8 steps
        mid = int(round(math.sqrt(hi * lo)))
        if mid in (hi, lo):
            break
        cand = ev.collapse(source, mid, level, bound)
        if _within(cand, bound):
            hi = mid
            if cand[0].num_faces < best[0].num_faces:
                best = cand
        else:
            lo = mid
    return best if best[0].num_faces <= keep else None


def _parts(mesh: Mesh) -> int:
    labels = face_components(mesh.faces, mesh.num_vertices)
    return int(labels.max()) + 1 if labels.size else 0


def _try_wrap(ev: _Evaluator, bound: float, level: int, below: int):
    """Many parts merged into one wrap at half the bound, tightened onto M_org and collapsed
    within the bound: (mesh, d_lo, d_ol) with fewer than `below` faces, or None."""
    try:
        sheet = wrap(ev.org.vertices, ev.org.faces, 0.5 * bound, max_cells=LOD_WRAP_CELLS)
    except StageError:
        return None
    found = None
    target = max(MIN_FACES, min(below - 1, sheet.num_faces - 1))
    for _ in range(12):  # halve the wrap's faces while it stays within the bound
        if target < MIN_FACES or target >= sheet.num_faces:
            break
        try:
            mesh = _decimate(sheet, target, level)
        except StageError:
            break
        moved, d_lo, d_ol, _ = ev.measure(mesh, bound, tighten=True)
        if max(d_lo, d_ol) > bound:
            break
        found = (moved, d_lo, d_ol)
        target //= 2
    return found


def build_lod_chain(points: object, faces: object, switch_px: tuple[float, ...] | list[float],
                    error_px: float = 1.0, *, enclose_meshes: bool = True,
                    probe: np.ndarray | None = None, seed: int = 0) -> LodChain:
    """LOD1..LODn of M_org, level i the smallest collapse within bound_i (module docstring).

    points : (n, 3); faces : (f, 3); switch_px : decreasing screen sizes (pixels the bbox
    diagonal covers) at which each level switches in; error_px : deviation allowed there;
    probe : (m, 3) dense samples of M_org for the enclosing step (default: seeded samples).
    returns : LodChain with 1 .. len(switch_px) levels
    raises SettingsError for bad switch sizes, StageError when M_org has < MIN_FACES faces."""
    welded, _, _ = weld(points, faces)
    org, _ = compact(Mesh(welded.vertices, welded.faces[~welded.degenerate_faces()]))
    if org.num_faces < MIN_FACES:
        raise StageError(f"geometry: M_org has {org.num_faces} nondegenerate faces after "
                         f"welding (expected >= {MIN_FACES})")
    diag = bbox_diagonal(org.vertices)
    bounds = error_bounds(diag, switch_px, error_px)
    if probe is None:
        probe = sample_surface(org.vertices, org.faces, HAUSDORFF_SAMPLES, seed + 1).positions
    ev = _Evaluator(org, np.asarray(probe, dtype=np.float64), enclose_meshes, seed)
    parts = _parts(org)
    chain = LodChain([], diag)
    prev = org

    def method_of(mesh: Mesh) -> str:
        return chain.levels[-1].method if chain.levels and mesh is chain.levels[-1].mesh else ""

    for i, (px, bound) in enumerate(zip(switch_px, bounds, strict=True), start=1):
        found = _search(ev, prev, bound, i)
        method = "qem"
        note = ""
        if parts >= WRAP_MIN_PARTS and method_of(prev) != "wrap":
            below = math.floor(KEEP_FRACTION * prev.num_faces)
            if found is not None:
                below = min(below, found[0].num_faces)
            wrapped = _try_wrap(ev, bound, i, below)
            if wrapped is not None:
                found = (*wrapped, True)
                method = "wrap"
                note = (f"{parts} parts merged into one wrap, smaller than QEM's collapse, "
                        f"which keeps the parts apart")
        if found is None:
            if i == 1:
                chain.levels.append(LodLevel(org, float(px), bound, 0.0, 0.0, 0.0, "original",
                                             False, "M_org is already coarser than the bound: "
                                             "LOD1 is the original, not simplified"))
                prev = org
                continue
            why = (f"LOD{i} (bound {bound:.4g} at {px:g} px) would keep more than "
                   f"{KEEP_FRACTION:.0%} of LOD{i - 1}'s {prev.num_faces} triangles")
            if parts >= WRAP_MIN_PARTS:
                why += f"; {parts} parts kept (a wrap within the bound was not smaller)"
            chain.stopped = why + ": the chain stops here"
            break
        mesh, _, _, enclosed = found
        d_lo, d_ol = hausdorff(mesh, org, org_points=ev.org_points, seed=seed)  # pymeshlab's
        chain.levels.append(LodLevel(mesh, float(px), bound, max(d_lo, d_ol), d_lo, d_ol,
                                     method, enclosed, note))
        prev = mesh
    return chain


#: a LOD edge whose faces' normals are more than this apart is a crease of the LOD's smooth
#: normals (`smooth_corner_normals`): the corners on either side do not share a normal
CREASE_DEG = 60.0
#: corner pairs held at once while the corners of each vertex are averaged (memory bound)
PAIR_CHUNK = 4_000_000
#: a LOD corner looks M_org's normal up this far into its own face (fraction of the way to
#: the face's centroid): the side of a sharp edge the face is on, not the edge itself
CORNER_INSET = 0.1
#: M_org's normal at a corner within FACET_DEG[0] of the LOD face's normal (and nearer it than
#: the LOD's smooth normal there): M_org is that facet there (flat-shaded, as the LOD), and
#: the corner keeps the face's normal; beyond FACET_DEG[1] the corner takes the LOD's smooth
#: normal; between, a blend
FACET_DEG = (2.0, 5.0)


def lod_corner_normals(vertices: np.ndarray, faces: np.ndarray,
                       org_faces_normals: np.ndarray, caster: RayCaster, *,
                       crease_deg: float = CREASE_DEG) -> np.ndarray:
    """Shading normals for a LOD's face corners (what a DCC shades a LOD with): the LOD's own
    surface at its scale, M_org's detail left to the normal map. A corner where M_org is
    flat-shaded like the LOD face (M_org's normal there, `org_corner_normals`, within
    FACET_DEG of the face's) keeps the face's normal: sharp facets stay sharp (the
    cylinder's ridges, the bolt's bumps on its LOD1) whatever their angle. Elsewhere the
    corner takes the LOD's smooth normal (`smooth_corner_normals`, split at `crease_deg`):
    smooth surfaces stay smooth (the Teapot), and M_org's bumps, which the LOD does not
    have, do not tilt it (a viewer would interpolate them across the face, where the
    texel-rate normal map cannot undo them between texel centres).

    vertices (n, 3), faces (f, 3); org_faces_normals : (F, 3, 3) M_org's unit corner normals
    (`AssetModel.corner_normals`); caster : closest points on M_org;
    returns (f, 3, 3) float64 unit normals
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if not len(f):
        return np.zeros((0, 3, 3))
    smooth = smooth_corner_normals(v, f, crease_deg=crease_deg).reshape(-1, 3)
    org = org_corner_normals(v, f, org_faces_normals, caster).reshape(-1, 3)
    tri = v[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(fn, axis=1, keepdims=True)
    face = np.repeat(np.divide(fn, length, out=np.zeros_like(fn), where=length > 0), 3, axis=0)
    lo, hi = (math.cos(math.radians(d)) for d in FACET_DEG)
    cos_face = np.einsum("md,md->m", org, face)
    w = np.clip((cos_face - hi) / (lo - hi), 0.0, 1.0)  # (3f,)
    w[cos_face < np.einsum("md,md->m", org, smooth)] = 0.0  # M_org nearer the smooth normal
    w = w[:, None]
    n = w * face + (1.0 - w) * smooth
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=smooth.copy(), where=norm > 0.5)
    return n.reshape(-1, 3, 3)


def org_corner_normals(vertices: np.ndarray, faces: np.ndarray,
                       org_faces_normals: np.ndarray, caster: RayCaster) -> np.ndarray:
    """M_org's shading normals at a LOD's face corners: each corner, moved CORNER_INSET of the
    way towards its face's centroid (the side of a sharp edge the face is on), takes M_org's
    interpolated corner normal at the closest point (`caster` over M_org). A normal facing
    away from the LOD face (a thin part's other side) or not finite takes the LOD face's
    normal.

    vertices (n, 3), faces (f, 3); org_faces_normals : (F, 3, 3) M_org's unit corner normals
    (`AssetModel.corner_normals`); returns (f, 3, 3) float64 unit normals
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]  # (f, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    if not len(f):
        return np.zeros((0, 3, 3))
    q = tri + CORNER_INSET * (tri.mean(axis=1, keepdims=True) - tri)
    _, prim, b2 = caster.closest_points(q.reshape(-1, 3))
    bary = np.column_stack([1.0 - b2[:, 0] - b2[:, 1], b2])
    n = np.einsum("mk,mkd->md", bary, np.asarray(org_faces_normals, dtype=np.float64)[prim])
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    face = np.repeat(fn, 3, axis=0)
    bad = ~np.isfinite(n).all(axis=1) | (np.einsum("md,md->m", n, face) <= 0.0)
    n[bad] = face[bad]
    return n.reshape(-1, 3, 3)


def smooth_corner_normals(vertices: np.ndarray, faces: np.ndarray, *,
                          crease_deg: float = CREASE_DEG) -> np.ndarray:
    """The smooth normals of a mesh's face corners, split at its creases: a corner's normal
    is the corner-angle weighted mean of the normals of the faces around its vertex
    (vertices at one position are one) that lie within `crease_deg` of the corner's own
    face's normal.

    vertices (n, 3), faces (f, 3); returns (f, 3, 3) float64 unit normals, each within
    `crease_deg` of its face's normal (a degenerate face's corners: the mean of its
    neighbours', or +z when it has none)
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if not len(f):
        return np.zeros((0, 3, 3))
    if not 0.0 < float(crease_deg) < 180.0:
        raise SettingsError(f"crease_deg must be in (0, 180), got {crease_deg}")
    tri = v[f]  # (f, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(fn, axis=1, keepdims=True)
    fn = np.divide(fn, length, out=np.zeros_like(fn), where=length > 0)
    degenerate = length[:, 0] == 0
    to_next, to_prev = np.roll(tri, -1, axis=1) - tri, np.roll(tri, 1, axis=1) - tri
    angle = np.arctan2(np.linalg.norm(np.cross(to_next, to_prev), axis=2),
                       np.einsum("fkd,fkd->fk", to_next, to_prev)).ravel()  # (3f,)
    _, weld_id = np.unique(v, axis=0, return_inverse=True)
    corner_vertex = weld_id.reshape(-1)[f].ravel()  # (3f,)
    corner_face = np.repeat(np.arange(len(f)), 3)
    # the corners of each vertex, contiguous: every ordered pair within a group
    order = np.argsort(corner_vertex, kind="stable")
    count = np.bincount(corner_vertex)  # corners per vertex
    size = count[corner_vertex[order]]  # (3f,) the group's size at each sorted position
    first = (np.cumsum(count) - count)[corner_vertex[order]]  # (3f,) the group's start
    cos_crease = math.cos(math.radians(float(crease_deg)))
    acc = np.zeros((3 * len(f), 3))
    start = 0
    while start < len(order):  # chunks of corners whose pairs fit in PAIR_CHUNK
        cum = np.cumsum(size[start:])
        stop = start + max(1, int(np.searchsorted(cum, PAIR_CHUNK, side="right")))
        rep = size[start:stop]
        i = np.repeat(np.arange(start, stop), rep)  # (p,) sorted positions
        j = first[i] + (np.arange(len(i)) - np.repeat(np.cumsum(rep) - rep, rep))
        ci, cj = order[i], order[j]  # corners
        fi, fj = corner_face[ci], corner_face[cj]
        keep = (np.einsum("pd,pd->p", fn[fi], fn[fj]) >= cos_crease) | degenerate[fi]
        w = angle[cj[keep]][:, None] * fn[fj[keep]]  # (p', 3)
        for d in range(3):
            acc[:, d] += np.bincount(ci[keep], weights=w[:, d], minlength=3 * len(f))
        start = stop
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    face = np.repeat(fn, 3, axis=0)
    out = np.divide(acc, norm, out=face.copy(), where=norm > 0)
    bad = ~(np.linalg.norm(out, axis=1) > 0.5)
    out[bad] = [0.0, 0.0, 1.0]
    return out.reshape(-1, 3, 3)
