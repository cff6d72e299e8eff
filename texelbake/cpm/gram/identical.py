"""Candidates whose columns of F are identical, fitted as one column.

Samples with the same normal, material and area weight that see every direction of the grid
alike (a flat, unoccluded, single-material stretch of a texel) have byte-identical columns of
F = diag(1/a_vis) R. The seed's fit (seed 000 §4.1 with DMM06 Table 2) treats each as its own
column: each enters the Grams (m^2 d), the eigendecompositions (m^3) and the draws, and two
drawn copies of one column are one point's worth of information stored twice.

A group of k identical columns f is replaced by the one column sqrt(k) f, and the weights are
fitted to Eq. 7's sum over every candidate (sum_g k_g f_g, which the merged columns span).
With A (u x m) the groups' indicator matrix, F = F_u A and the candidates' Gram is
A^T G_u A; its nonzero eigenpairs are (lam, A^T D^-1/2 v) for the eigenpairs (lam, v) of
D^1/2 G_u D^1/2 (D = A A^T = diag(k)), the Gram of the merged columns. So the spectrum, the psi
rank and every group's total probability of Table 2 (its members' leverage and energy summed)
are the seed's, the i.i.d. draws of groups are distributed as the seed's draws mapped to their
groups, and a draw's NNLS residual is that of its distinct groups: the fit is the seed's in
distribution, with the Gram and eigen work of u columns and no point stored twice. A group's
stored sample is drawn uniformly among its members (as the seed's draw would be), from the
texel's own stream `MERGE_STREAM`, so reruns are identical.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from texelbake.cpm.matrix import points_sum, snr_db
from texelbake.cpm.texel_fit import TexelFit, storable_weights

#: the stream of a texel's seed that draws each merged group's stored member
MERGE_STREAM = 0x1DE47C
#: entries of a column (evenly spaced direction pairs) in its fingerprint
PRINT_TAPS = 64


@dataclasses.dataclass(frozen=True)
class Merge:
    """A texel's identical columns grouped: rep (u,) the stored member of each group (candidate
    indices, groups in order of their first member), count (u,) the group sizes."""

    rep: np.ndarray
    count: np.ndarray

    @property
    def scale(self) -> np.ndarray:
        return np.sqrt(self.count.astype(np.float64))

    @property
    def merged(self) -> int:
        """Candidates fitted as copies of others: m - u."""
        return int(self.count.sum() - self.rep.size)

    def groups(self) -> tuple[np.ndarray, np.ndarray]:
        """Every group's stored member, sorted (as a TexelFit's columns), and its size (float)."""
        order = np.argsort(self.rep, kind="stable")
        return self.rep[order], self.count[order].astype(np.float64)

    def columns(self, F: np.ndarray) -> np.ndarray:
        """The merged columns sqrt(k_g) f_g: (ch, u, d), a copy."""
        return F[:, self.rep] * self.scale[None, :, None]


def identical_columns(F: np.ndarray, seed: int) -> Merge | None:
    """Group the candidates of F (ch, m, d) whose columns are equal bit for bit in every
    channel; None when no two are (nothing to merge). Bits, not a tolerance: merging is exact.
    Each row is fingerprinted by two sums of the float64 bit patterns (as uint64, modulo 2^64:
    plain and with odd weights) of PRINT_TAPS of its entries: exact integer arithmetic, so equal
    rows print equal on any machine, whatever the BLAS, at a cost of m PRINT_TAPS. Rows are
    grouped by print and every member is then compared with its group's first member over all
    d entries; one that differs stays alone (a fingerprint is not a proof)."""
    ch, m, d = F.shape
    if m < 2:
        return None
    taps = np.unique(np.linspace(0, d - 1, min(d, PRINT_TAPS)).astype(np.int64))
    odd = np.random.default_rng(MERGE_STREAM).integers(0, 2**62, taps.size, dtype=np.uint64)
    odd = odd * np.uint64(2) + np.uint64(1)
    prints = np.empty((m, 2 * ch), np.uint64)
    for c in range(ch):  # loop over <= 3 channels
        bits = F[c][:, taps].view(np.uint64)  # (m, taps): a copy of a few columns
        prints[:, 2 * c] = bits.sum(axis=1, dtype=np.uint64)
        prints[:, 2 * c + 1] = (bits * odd).sum(axis=1, dtype=np.uint64)
    _, first, label = np.unique(prints, axis=0, return_index=True, return_inverse=True)
    if first.size == m:
        return None
    head = first[label.ravel()]  # each candidate's group's first member
    other = np.flatnonzero(head != np.arange(m))
    same = np.ones(other.size, bool)
    for c in range(ch):  # loop over <= 3 channels: every member against its first, all of d
        same &= np.all(F[c, other] == F[c, head[other]], axis=1)
    head[other[~same]] = other[~same]  # equal prints, unequal rows: alone
    _, first, label = np.unique(head, return_index=True, return_inverse=True)
    n_groups = first.size
    if n_groups == m:
        return None
    order = np.argsort(label, kind="stable")  # members of a group together, in index order
    count = np.bincount(label, minlength=n_groups)
    start = np.r_[0, np.cumsum(count)[:-1]]
    pick = np.random.default_rng((seed, MERGE_STREAM)).random(n_groups)
    member = order[start + np.minimum((pick * count).astype(np.int64), count - 1)]
    # np.unique numbers the labels (first members) in increasing order: groups in order of
    # their first member
    return Merge(rep=member, count=count)


def unmerge(fit: TexelFit, merge: Merge, F: np.ndarray, targets: np.ndarray,
            valid: np.ndarray, eps_db: float) -> TexelFit:
    """A fit over the merged columns as a fit over the texel's candidates: each point is its
    group's stored member with weight alpha sqrt(k) (the same approximation: sqrt(k) f = k^1/2
    times the member's column), the float32 weights and the in-sample SNR recomputed against
    Eq. 7 over every candidate of F (ch, m, d), `targets` (ch, d) = F's row sums."""
    if fit.c == 0:
        return dataclasses.replace(fit, merged=merge.merged)
    cols = merge.rep[fit.columns]
    w32 = storable_weights(fit.weights.astype(np.float64) * merge.scale[fit.columns][:, None])
    order = np.argsort(cols, kind="stable")  # TexelFit's columns are sorted
    cols, w32 = cols[order], w32[order]
    w = w32.astype(np.float64)
    approx = points_sum(F, cols, w)
    snr = snr_db(targets.T, approx, valid)  # (d, ch): Eq. 7
    return dataclasses.replace(fit, columns=cols, weights=w32, snr_db_insample=snr,
                               eps_reached=bool(snr >= eps_db), merged=merge.merged)


__all__ = ["MERGE_STREAM", "PRINT_TAPS", "Merge", "identical_columns", "unmerge"]
