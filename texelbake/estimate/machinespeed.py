"""How fast this machine runs the bake's kinds of work, against the machine the cost model's
coefficients were fitted on: a short reference workload timed at estimate
time, so that `texelbake.estimate.costmodel.estimate` carries its coefficients across machines.

The coefficients are CPU seconds of one machine; another machine runs the same bake 3x slower
(`docs/profile.md` third pass) and the estimate was 0.42-0.44 of the outcome. A
single factor would not do: machines differ per kind of work (vector width for the Grams,
Embree's kernels for rays, the interpreter for the per-texel bookkeeping). The workload has
one part per kind of work the cost model prices, each sized like the fit's own calls:

    grid    elementwise float64 arithmetic on a (p, A, B) direction grid (BRDF evaluation
            building R, the held-out truth, a_vis tables): r_entry, held,
            avis_fixed, export, geometry
    blas    Gram matrices (m x d by its transpose, m ~ 100, d = 4,096) and a stack of
            symmetric eigendecompositions: gram, eigh
    rays    one batch of 2^18 rays against a 20k-triangle mesh in open3d's Embree scene: avis,
            classify, fit_avis, filtered
    python  small NNLS solves and array bookkeeping, one call at a time (the per-texel draws,
            bisection and trials): texel, process, fixed

Each part's factor = its seconds here / its seconds on the reference machine (`REFERENCE`);
a coefficient is multiplied by its part's factor. A part is timed as the least of five
interleaved runs of `time.process_time()` (CPU seconds of this process, so other processes'
load is left to the estimate's own `load` term). Pure numpy / scipy / open3d calls, not texelbake's code: a
change to the bake's code changes the coefficients (re-fit them), not the reference.

`REFERENCE` is not a measurement on the coefficients' machine (gone when this was written):
the parts were timed on an AMD EPYC machine and multiplied by the cost model's
prediction over the measured CPU seconds of its calibration run on that machine
(`CALIBRATION_RATIO`), i.e. every part is assumed to differ between those two machines by the
fit's overall ratio (docs/decisions.md). Re-fitting the coefficients on a machine
means timing the parts there (`python -m texelbake.estimate.machinespeed`) and setting both.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass

import numpy as np

#: the kernels of R's entries and of the held-out truth, as shares of `build_R`'s CPU seconds
#: on the coefficients' machine (the full cylinder at 64^2, `cpm_cpu.py --breakdown`: the BRDF
#: grid `brdf_product` 1.60 s, the rays of `visibility_cos` 1.04 s, the gathers, products and
#: sums around them 2.28 s of 4.92 s, the last priced like the per-call work): a term of that
#: mix is scaled by the parts' weighted factors, not the BRDF grid's alone (on an Intel Xeon the
#: grid part read 1.92 where build_R ran 1.61x slower, and the weighted factors 1.61)
R_MIX = {"grid": 1.60 / 4.92, "rays": 1.04 / 4.92, "python": 2.28 / 4.92}

#: coefficient -> the part that scales it, or parts with weights (`Coefficients` field names);
#: the ratio fields (brdf_ggx, held_ggx, btf_cell, widened) are not seconds and are not scaled
PART_OF: dict[str, str | dict[str, float]] = {
    "r_entry": R_MIX, "held": R_MIX, "lobe": R_MIX,
    "avis_fixed": "grid", "export": "grid", "geometry": "grid",
    "gram": "blas", "eigh": "blas",
    "avis": "rays", "classify": "rays", "fit_avis": "rays", "filtered": "rays",
    "texel": "python", "process": "python", "fixed": "python", "avis_stage": "python",
}

#: the cost model's CPU seconds for the coefficients' calibration run
#: (`benchmarks/cpm_cpu.py --scene cylinder --atlas 32`, priced on the run's own texel sizes by
#: `benchmarks/calibrate_costmodel.py`) against the seconds measured on the machine `_MEASURED`
#: was timed on (AMD EPYC, 2 cores, alone): 42.36 / 57.58 (that machine is 1.36x
#: slower per CPU second than the coefficients' on the fit)
CALIBRATION_RATIO = 42.36 / 57.58
#: the parts' seconds on that AMD EPYC machine (`python -m texelbake.estimate.machinespeed`,
#: the median of five processes, each the least of five interleaved rounds)
_MEASURED = {"grid": 0.0226, "blas": 0.0446, "rays": 0.0520, "python": 0.0250}
#: the parts' seconds on the machine the cost model's coefficients hold on
REFERENCE = {k: v * CALIBRATION_RATIO for k, v in _MEASURED.items()}

#: a factor outside this range is a broken measurement (a suspended process, a clock jump),
#: not a machine: it is clamped and the estimate says so through `MachineSpeed.clamped`
FACTOR_RANGE = (0.05, 20.0)


@dataclass(frozen=True)
class MachineSpeed:
    """Seconds per part here against the reference machine (> 1: slower here)."""

    factors: dict[str, float]
    seconds: dict[str, float]  # the parts' measured seconds here
    clamped: bool = False

    def factor(self, coefficient: str) -> float:
        """The factor that scales the cost model's `coefficient` (1 for a ratio field)."""
        part = PART_OF.get(coefficient)
        if isinstance(part, dict):
            return sum(w * self.factors[p] for p, w in part.items())
        return self.factors[part] if part else 1.0

    def to_dict(self) -> dict:
        return {"factors": {k: round(v, 3) for k, v in self.factors.items()},
                "seconds": {k: round(v, 5) for k, v in self.seconds.items()},
                "clamped": self.clamped}


#: the reference machine itself: every factor 1
REFERENCE_SPEED = MachineSpeed(factors=dict.fromkeys(REFERENCE, 1.0), seconds=dict(REFERENCE))


def _grid(rng: np.random.Generator):
    # a GGX-like lobe on a (p, A, B) = (192, 64, 64) grid with per-sample parameters broadcast,
    # float64 like `brdf_product`: dots, a power, a division, a sqrt, an exp. Into buffers
    # allocated once: fresh 19 MB temporaries cost page faults whose price depends on the
    # process's heap (a long-running process measured 10 % faster than a fresh one)
    p, a, b = 192, 64, 64
    wi = rng.standard_normal((p, a, 1, 3))
    wo = rng.standard_normal((p, 1, b, 3))
    a2 = rng.uniform(0.1, 0.9, (p, 1, 1)) ** 2
    h = np.empty((p, a, b, 3))
    c, x, y = np.empty((p, a, b)), np.empty((p, a, b)), np.empty((p, a, b))

    def run() -> float:
        t0 = time.process_time()
        np.add(wi, wo, out=h)
        np.sqrt(np.einsum("pabk,pabk->pab", h, h, out=c), out=c)
        np.abs(np.divide(h[..., 2], c + 1e-12, out=c), out=c)  # |cos| of the half vector
        np.multiply(c, c, out=x)
        np.add(np.multiply(x, a2 - 1.0, out=x), 1.0, out=x)
        np.divide(a2, np.multiply(np.pi, np.multiply(x, x, out=x), out=x), out=x)  # D
        np.subtract(1.0, c, out=c)
        np.add(0.04, np.multiply(0.96, np.power(c, 5, out=c), out=c), out=c)  # Fresnel
        np.multiply(x, c, out=x)
        np.abs(np.multiply(wi[..., 2], wo[..., 2], out=y), out=y)
        np.exp(np.multiply(-y, a2, out=c), out=c)  # shadowing-like
        np.multiply(x, c, out=x)
        np.divide(x, np.add(np.multiply(4.0, y, out=y), 1e-3, out=y), out=x)
        t = time.process_time() - t0
        assert np.isfinite(x).all()
        return t
    return run


def _blas(rng: np.random.Generator):
    # the Grams of a few texels of m ~ 100 candidates on d = 4,096 direction pairs, and the
    # eigendecompositions of a stack of them (level_batched's two LAPACK / BLAS calls)
    r = rng.standard_normal((24, 96, 4096))

    def run() -> float:
        t0 = time.process_time()
        g = np.matmul(r, r.transpose(0, 2, 1))
        w = np.linalg.eigh(g)[0]
        t = time.process_time() - t0
        assert np.isfinite(w).all()
        return t
    return run


def _rays(rng: np.random.Generator):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=100)  # 19,800 faces
    scene = o3d.t.geometry.RaycastingScene(nthreads=1)
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    n = 2**18
    o = rng.uniform(-0.9, 0.9, (n, 3)) * (1.0 / np.sqrt(3.0))  # inside the sphere: all hit
    d = rng.standard_normal((n, 3))
    rays = o3d.core.Tensor.from_numpy(np.hstack([o, d]).astype(np.float32))

    def run() -> float:
        t0 = time.process_time()
        hit = scene.cast_rays(rays, nthreads=1)["t_hit"].numpy()
        t = time.process_time() - t0
        assert np.isfinite(hit).all()
        return t
    return run


def _python(rng: np.random.Generator):
    # 1,500 small problems one call each: an NNLS on a reduced r x c system and a few small
    # array operations, as the per-texel draws, bisection and trials do
    import scipy.optimize

    a = rng.uniform(0.0, 1.0, (1500, 24, 12))
    y = rng.uniform(0.0, 1.0, (1500, 24))

    def run() -> float:
        t0 = time.process_time()
        s = 0.0
        for i in range(a.shape[0]):  # a loop per problem: the per-call overhead is timed
            x = scipy.optimize.nnls(a[i], y[i])[0]
            k = np.argsort(x)[-4:]
            s += float(np.linalg.norm(a[i][:, k] @ x[k] - y[i]))
        t = time.process_time() - t0
        assert np.isfinite(s)
        return t
    return run


_PARTS = {"grid": _grid, "blas": _blas, "rays": _rays, "python": _python}


def time_parts(repeats: int = 5, seed: int = 0) -> dict[str, float]:
    """Each part's least CPU seconds over `repeats` rounds in this process (one thread each).
    The rounds interleave the parts, so a short disturbance (another process, the host taking
    the virtual CPU away) spoils one round of each part, not every run of one part."""
    import threadpoolctl

    rng = np.random.default_rng(seed)
    out: dict[str, float] = {}
    with threadpoolctl.threadpool_limits(1):  # the bake's fit runs one BLAS thread a process
        runs = {name: make(rng) for name, make in _PARTS.items()}
        for run in runs.values():
            run()  # warm: first-call imports, page faults, Embree's scene build
        for _ in range(max(int(repeats), 1)):  # rounds, each part once
            for name, run in runs.items():
                t = run()
                out[name] = min(out.get(name, t), t)
    return out


def measure(repeats: int = 5) -> MachineSpeed:
    """This machine's `MachineSpeed` (~1 s). `TEXELBAKE_MACHINE_SPEED=1` skips the
    measurement and returns the reference machine (every factor 1)."""
    if os.environ.get("TEXELBAKE_MACHINE_SPEED", "").strip() == "1":
        return REFERENCE_SPEED
    sec = time_parts(repeats)
    lo, hi = FACTOR_RANGE
    raw = {k: sec[k] / REFERENCE[k] for k in REFERENCE}
    factors = {k: float(np.clip(v, lo, hi)) for k, v in raw.items()}
    return MachineSpeed(factors=factors, seconds=sec, clamped=factors != raw)


_lock = threading.Lock()
_this: list[MachineSpeed] = []


def this_machine() -> MachineSpeed:
    """`measure()` once per process (thread-safe: a second caller waits for the first's)."""
    with _lock:
        if not _this:
            _this.append(measure())
        return _this[0]


def main() -> None:
    m = measure(repeats=7)
    print("part     seconds here   reference   factor")
    for k, v in m.seconds.items():
        print(f"{k:<8} {v:12.5f} {REFERENCE[k]:11.5f} {m.factors[k]:8.3f}")


if __name__ == "__main__":
    main()
