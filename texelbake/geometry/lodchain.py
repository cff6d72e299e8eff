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
