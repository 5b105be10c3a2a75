r"""Ξ in compressed form, computed tile by tile from the sparse factor on a Dask cluster.

The form (near field exact, far field in low-rank blocks over a cluster tree) and its reader are in
:mod:`pmask.runtime.compressed`; this module builds it without ever forming the dense Ξ (or, where the dense Ξ
fits and no Dask option is given, from it in one process: :class:`DenseSource`, the same tiles asking it for
their rows and sketches in place of W's passes):

1. **Cluster tree** of the contact vertices: recursive bisection at the median of the longest side of
   the bounding box, down to :data:`LEAF` vertices.  Its order puts nearby vertices together.
2. **Block partition** (a hierarchical matrix): a pair of clusters (I, J) is *admissible*, stored as
   U Vᵀ, when no vertex of I is within r_max of a vertex of J (so no pair a mask can reach,
   ‖x_i − x_j‖ ≤ r_max, is ever approximated: the near field stays exact; :meth:`ClusterTree.close`) and
   the boxes are more than half the larger box's diagonal apart
   (η = 2: Ξ_IJ is then smooth, the Green's function's 1/r far from its pole; the rank adapts to the
   tolerance, so η trades block count for rank, not accuracy).
   Otherwise both are split; pairs of leaves are stored densely.
3. **Tiles**: the columns are cut into panels (clusters of at most ``panel`` vertices, fewer for large
   n so that a panel stays near :data:`PANEL_BYTES`).  A tile computes the columns of Ξ its panel holds and
   compresses its share of each block; one task, a *pass* (:func:`tiles`), runs a run of neighbouring tiles
   together, reading each of W's blocks once for all of them (:func:`passes`: as many as :data:`PASS_SHARE` of the
   worker's memory per thread holds by :func:`pass_bytes`, :func:`pass_budget`; about equal shares of the work, at least
   :data:`PASSES_PER_THREAD` per thread, the largest handed out first: every pass reads most of W, so W is read
   about once a pass and once more for the tiles' own columns).  A far
   block wide and tall enough (:func:`sketches`: most of the far field's entries) is never formed: the pass takes
   its range sketch :math:`B\Omega` (64 columns, 16 of them a test) and forms 64 of its rows, and
   :func:`from_sketches` interpolates the block from them, the error estimated by the test columns (a block
   they cannot show within ε is formed after all).  Any other block is formed and compressed by a randomized
   range finder grown until :math:`\|B - QQ^TB\|_F \le \varepsilon\|B\|_F/2`, then the SVD of
   :math:`Q^TB` truncated to the smallest rank within :math:`\varepsilon\|B\|_F` in all (the error is
   computed: B is at hand).  A block whose factors would not be smaller stays dense.  At tolerances of 1e-4 and
   more the factors are stored in 16 bits (format 1.8, :func:`far_words`): the blocks are truncated to half the
   tolerance (:func:`truncation_tolerance`) and the rounding, computed block by block, takes the other half.  Only one pass's formed
   rows, at most 3n x 3 #J numbers a tile (the rows its formed blocks need), exist at a time on a worker thread.
   The blocks are the tree's, not the panels': a far block
   whose column cluster holds several panels comes back from each as a *piece* (compressed within ε/2)
   and :func:`assemble` merges the pieces (:func:`merge_pieces`, within the other ε/2).  So the stored
   blocks are the hierarchical matrix's whatever the panel width (blocks cut at the panels stored ~3n·k
   numbers per panel; measured at 20,427 vertices that was 1 % of the total: the near field dominates).
   For P1, Ξ = G diag(a) with G symmetric and the partition symmetric, so only the blocks on and above the
   diagonal are computed into the store (:func:`is_symmetric`; the reader transposes the rest): half the
   bytes, near field and far field alike.

   The columns come from the selected inversion's W (:mod:`pmask.precompute.selinv`): with P1's load
   :math:`\Xi = W^T W\,\mathrm{diag}(a)`, W = L⁻¹PE, so :math:`\Xi_{:,J} = \sum_s X_s X_{s,J}^T a_J`
   over the supernodes s that J's columns reach (X_s: W's rows of s, :func:`sweep`).  W is computed
   once, by one forward sweep on a worker (:func:`factor_and_sweep`; the pipeline's assembly and factorisation
   run there too, :class:`FactorJob`, so the client never holds the factor), and written supernode by supernode
   to a file in the run's work folder (:class:`SweepStore`; under a tenth of the dense Ξ: the bench page gives it
   at 20,427 vertices);
   a pass reads the X_s on its tiles' columns' tree paths, once for them all (W in all about as many times as
   there are passes, where tiles alone read it about once each: the top separators' blocks, most of W, are on
   every column's path).  So the tiles together do the dense route's
   :math:`W^TW` products for the rows they form (each once: a tile computes only the rows above the diagonal,
   P1 being symmetric), and for the sketched rows the products with 64 columns instead of the panel's; the
   tiles need no factor.
   P2 (a consistent load B ≠ E diag(a)): :math:`\Xi = W_E^T W_B`, W_B = L⁻¹PB swept after W into the same
   store (:func:`pmask.precompute.selinv.load_sweep`; a column of W_B reaches the tree paths up from all its
   non-zeros, the vertex's neighbours), and a tile sums :math:`X_s Y_{s,J}^T` over the supernodes its columns
   reach: the dense P2 route's gemms, every block (Ξ is not symmetric).  Before, P2's tiles solved each panel
   from the factor, which the client made and sent to every worker: the 20,427-vertex kidney (a 6.4 GiB factor)
   was refused on a 24 GiB machine.
4. **Dask**: the tasks run on ``dask.distributed``: by default a LocalCluster of worker processes on
   this machine, or a real cluster (``--scheduler ADDRESS``; the work folder must then be on a
   filesystem every worker sees, for W's store and the passes' tiles: checked before the tiles).  A pass writes
   each tile to a file in the work folder as it is compressed, and the client moves them into a tile store in the
   run's work folder (HDF5) one at a time as the pass arrives.  A lost worker's
   passes are run again (by the scheduler, or here if the task's inputs went with it); finished tiles
   are in the store and are never recomputed, also by a rerun after a crash.  The artifact's arrays
   are then filled from the store one tile at a time (:func:`assemble`).
"""
from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from pmask.errors import InputError, ResourceError
from pmask.runtime.artifact import READ_BLOCK_BYTES
from pmask.runtime.files import Background
from pmask.runtime.compressed import PAIR_WORDS, SlicedArray, encode_near, pack_exact

log = logging.getLogger(__name__)

#: the default far-field tolerance, relative per block in the Frobenius norm
TOLERANCE = 1e-4
#: vertices per leaf cluster (dense near-field blocks are up to 3·LEAF square)
LEAF = 32
#: admissibility: blocks whose boxes are farther apart than the larger diagonal / ETA are low-rank (measured
#: on the 3,882-vertex kidney at r_max = 10 mm: η = 1 stores 3.7x less than dense, η = 2 5.7x, η = 3 6.0x
#: with twice the blocks of rank below 2; leaves of 16 vertices 6.3x with 3x the blocks)
ETA = 2.0
#: vertices per panel (one task); 3n x 3·PANEL doubles on a worker at a time
PANEL = 512
#: fewer vertices per panel where 3n x 3·panel doubles would exceed this (panels of at most 314 vertices at
#: n = 47,467).  Wider panels read W fewer times: measured at 47,467 vertices (by hand, a cluster of 742 vertices
#: done as panels of at most 78, 156 and 312 vertices) the tiles took 23, 17 and 15 s; 256 MiB gave panels of 78
PANEL_BYTES = 2**30
#: W's blocks are read by a tile in row chunks of at most this many bytes
READ_BYTES = 64 * 2**20
#: the W store's file layout (a store of another layout is swept again)
LAYOUT = "X_s row-major, supernodes in postorder"
#: the tile store's layout (a store of another layout is computed again): pieces of the tree's blocks
TILE_LAYOUT = ("tree blocks, pieces per panel, near = a pair within r_max, dense blocks pair by pair, "
               "far blocks truncated to truncation_tolerance")
#: seconds a client waits for a lost scheduler to come back before the run stops (a rerun resumes)
SCHEDULER_WAIT = 10.0
#: tolerances at least this large store the far field's factors in float32 (:func:`far_dtype`)
FLOAT32_TOLERANCE = 1e-5
#: tolerances at least this large store them in 16 bits (format 1.8, :func:`pmask.runtime.compressed.encode_far`):
#: the tiles truncate to :data:`ROUNDING_SHARE` less of the tolerance and the rounding takes that share
INT16_TOLERANCE = 1e-4
#: the share of the tolerance a 16-bit far block's rounding may take (:func:`truncation_tolerance`).  On a kidney's
#: far blocks (P2, 4,338 vertices, by hand) the rounding was 2.7e-5 of a block at the median and 4.4e-5 at most:
#: with half of 1e-4 no block needed the rank-3k form, with 0.4 one in a hundred, with 0.3 a quarter; truncated to
#: half the tolerance the factors held 13 % more numbers than at the whole, each in half the bytes (float32 → int16;
#: at organ scale the far field came to 0.59-0.60 of float32's bytes, the bench page's rows)
ROUNDING_SHARE = 0.5
#: a pass of tiles (:func:`tiles`) holds at most this share of its worker's memory limit per thread, by its model
#: (:func:`pass_budget`): the more tiles a pass holds, the fewer times W is read (by hand at 20,427 vertices: 16
#: tiles in one pass read 2.4 GB of W, the same tiles one by one 21.3 GB; the bench page compares the whole run's
#: tiles both ways).  The workers peaked at 0.88-0.97 of the model at 51,519 vertices (the organ rows of
#: 2026-11-29, 3 and 4.7 GiB passes), so a pass stays below 0.4 of the limit, well below where Dask pauses a worker
#: (80 %), which leaves the worker its own few hundred MiB; two local workers on this 24 GiB machine (12 GiB each)
#: hold 4.8 GiB passes, their process tree within issue #27's 12 GiB.  (A fixed 3 GiB, as before, cut the
#: 51,519-vertex run into 13 passes.)
PASS_SHARE = 0.4
#: a pass's memory where no worker has a memory limit (a scheduler's workers started without one)
UNLIMITED_PASS_BYTES = 3 * 2**30
#: a cap on a pass's memory below its share (None: none; the bench's one tile a task sets 0)
PASS_BYTES: float | None = None
#: a tile is run again at most this often when workers are lost (then the run stops with the error)
TILE_ATTEMPTS = 4


@dataclass
class ClusterTree:
    """Clusters of the contact vertices: node k holds positions ``start[k]:stop[k]`` of ``perm``
    (position -> contact index), its box ``lo[k]``, ``hi[k]``, children ``kids[k]`` (-1: leaf); ``points``:
    the vertices' positions (contact order), which :meth:`close` reads."""

    perm: np.ndarray
    start: np.ndarray
    stop: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    kids: np.ndarray
    points: np.ndarray | None = None
    _close: dict = field(default_factory=dict, repr=False, compare=False)

    def leaf(self, k: int) -> bool:
        return self.kids[k, 0] < 0

    def size(self, k: int) -> int:
        return int(self.stop[k] - self.start[k])

    def __getstate__(self) -> dict:
        """Pickled for every tile's task without what only the partition reads (the points and
        :meth:`close`'s memo: 7 MiB at 47,467 vertices against 0.6 MiB for the rest)."""
        return {k: v for k, v in self.__dict__.items() if k not in ("points", "_close")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, points=None, _close={})

    def gap(self, i: int, j: int) -> float:
        """The distance between the boxes of clusters i and j (0 where they overlap)."""
        return float(np.linalg.norm(np.maximum(0.0, np.maximum(self.lo[i] - self.hi[j], self.lo[j] - self.hi[i]))))

    def close(self, i: int, j: int, r_max: float) -> bool:
        """Whether a vertex of cluster i lies within r_max of a vertex of cluster j: a pair a mask can reach,
        which the near field must hold exactly.  The boxes' gap says no where it exceeds r_max; else leaves
        compare their ≤ LEAF² distances and larger clusters ask their children (memoised).  Boxes within r_max
        often hold no such pair (a curved patch's box is mostly empty): at 47,467 vertices and r_max = 10 mm
        their blocks were 6 % of the near field's bytes (by hand), now low-rank.  Counts a pair up to
        r_max (1 + 1e-9) as close: the masks' own distances may round the other way."""
        key = (min(i, j), max(i, j), float(r_max))
        hit = self._close.get(key)
        if hit is None:
            reach = float(r_max) * (1.0 + 1e-9)
            if self.gap(i, j) > reach:
                hit = False
            elif self.leaf(i) and self.leaf(j):
                a = self.points[self.perm[self.start[i]:self.stop[i]]]
                b = self.points[self.perm[self.start[j]:self.stop[j]]]
                hit = bool(np.min(np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=2)) <= reach * reach)
            else:
                hit = any(self.close(a, b, r_max) for a, b in _split(self, i, j))
            self._close[key] = hit
        return hit

    @property
    def leaves(self) -> np.ndarray:
        """First position of each leaf cluster, and n (the reader's ``leaves``)."""
        is_leaf = self.kids[:, 0] < 0
        return np.concatenate([np.sort(self.start[is_leaf]), [len(self.perm)]]).astype(np.int64)


def cluster_tree(points: np.ndarray, leaf: int | None = None) -> ClusterTree:
    """Recursive bisection of ``points`` (n, 3) at the median of the longest side of each box, down to
    ``leaf`` vertices (default :data:`LEAF`)."""
    leaf = leaf or LEAF
    points = np.asarray(points, float)
    perm = np.arange(len(points))
    start, stop, lo, hi, kids = [], [], [], [], []

    def add(s, e):
        p = points[perm[s:e]]
        start.append(s), stop.append(e), lo.append(p.min(axis=0)), hi.append(p.max(axis=0)), kids.append([-1, -1])
        return len(start) - 1

    stack = [add(0, len(points))] if len(points) else []
    while stack:
        k = stack.pop()
        s, e = start[k], stop[k]
        if e - s <= leaf:
            continue
        axis = int(np.argmax(hi[k] - lo[k]))
        mid = (e - s) // 2
        seg = perm[s:e]
        perm[s:e] = seg[np.argpartition(points[seg, axis], mid, kind="introselect")]
        kids[k] = [add(s, s + mid), add(s + mid, e)]
        stack.extend(kids[k])
    return ClusterTree(perm, np.array(start, np.int64), np.array(stop, np.int64), np.array(lo).reshape(-1, 3),
                       np.array(hi).reshape(-1, 3), np.array(kids, np.int64).reshape(-1, 2), points)


def panel_size(n: int) -> int:
    """Vertices per panel for n contact vertices: :data:`PANEL`, or fewer so that a panel's 3n x 3·panel
    doubles stay within :data:`PANEL_BYTES` (never below a leaf)."""
    return int(min(PANEL, max(LEAF, PANEL_BYTES // (8 * 9 * max(n, 1)))))


def panels(tree: ClusterTree, size: int = PANEL) -> list[int]:
    """Column panels: the largest clusters of at most ``size`` vertices, in position order."""
    out, stack = [], [0] if len(tree.start) else []
    while stack:
        k = stack.pop()
        if tree.size(k) <= size or tree.leaf(k):
            out.append(k)
        else:
            stack.extend(tree.kids[k][::-1])
    return sorted(out, key=lambda k: tree.start[k])


def admissible(tree: ClusterTree, i: int, j: int, r_max: float, eta: float | None = None) -> bool:
    """Whether Ξ_IJ may be low-rank: no pair of its vertices within r_max (:meth:`ClusterTree.close`; boxes
    farther apart than r_max where the tree has no points) and the boxes apart by more than the larger
    diagonal / η."""
    dist = tree.gap(i, j)
    diam = max(float(np.linalg.norm(tree.hi[i] - tree.lo[i])), float(np.linalg.norm(tree.hi[j] - tree.lo[j])))
    if not diam <= (eta or ETA) * dist:
        return False
    return dist > r_max or (tree.points is not None and not tree.close(i, j, r_max))


def _split(tree: ClusterTree, i: int, j: int) -> list[tuple[int, int]]:
    """The pairs a non-admissible pair (I, J), not both leaves, is split into: both clusters' children, or
    the one that is not a leaf's.  One rule for the whole matrix (so any panel's share of the partition is
    the same blocks) and symmetric ((J, I) splits into the transposes), so that a symmetric Ξ stores each
    pair of blocks once."""
    ki = [i] if tree.leaf(i) else list(tree.kids[i])
    kj = [j] if tree.leaf(j) else list(tree.kids[j])
    return [(a, b) for a in ki for b in kj]


def partition(tree: ClusterTree, column: int, r_max: float, eta: float | None = None) -> list[tuple[int, int, bool]]:
    """The blocks (I, J, low-rank?) of Ξ's partition that hold the columns of cluster ``column`` (all rows).

    The partition is the cluster tree's over the whole matrix, from (root, root): an admissible pair is a
    block, a pair of leaves a dense block, any other pair split (:func:`_split`).  Its blocks are set by
    the tree, not by the panels the columns are computed in: a far block's J may hold many panels
    (then J is an ancestor of ``column`` and the panel computes its piece Ξ_{I,column}), which is what
    keeps the stored size near n log n (a block per panel would store ~3n·k numbers per panel: n³ as
    panels shrink like 1/n)."""
    out, stack = [], [(0, 0)]
    c0, c1 = tree.start[column], tree.stop[column]
    while stack:
        i, j = stack.pop()
        if tree.stop[j] <= c0 or tree.start[j] >= c1:
            continue  # this pair holds none of the panel's columns
        if admissible(tree, i, j, r_max, eta):
            out.append((i, j, True))
        elif tree.leaf(i) and tree.leaf(j):
            out.append((i, j, False))
        else:
            stack.extend(_split(tree, i, j))
    return out


def low_rank(B: np.ndarray, tol: float, rng: np.random.Generator):
    r"""U, V with :math:`\|B - UV^T\|_F \le` ``tol`` :math:`\|B\|_F`, or None where dense is not larger.

    Randomized range finder (Halko, Martinsson & Tropp 2011, alg. 4.2 with the error computed exactly,
    :math:`\|B - QQ^TB\|_F^2 = \|B\|_F^2 - \|Q^TB\|_F^2`), doubling the sample until half the error
    budget is met, then the SVD of :math:`Q^T B` truncated within the other half."""
    m, n = B.shape
    norm2 = float(np.sum(B * B))
    if norm2 == 0.0:
        return np.zeros((m, 0)), np.zeros((n, 0))
    budget = tol * tol * norm2
    k = 16
    while True:
        if k * (m + n) >= m * n:
            return None
        Q, _ = np.linalg.qr(B @ rng.standard_normal((n, k)))
        C = Q.T @ B
        err = max(norm2 - float(np.sum(C * C)), 0.0)
        if err <= 0.25 * budget:
            break
        k *= 2
    Us, s, Vt = np.linalg.svd(C, full_matrices=False)
    tail = np.concatenate([np.cumsum((s * s)[::-1])[::-1], [0.0]])  # tail[r] = Σ_{q≥r} s_q²
    r = int(np.argmax(err + tail <= budget))
    if r * (m + n) >= m * n:
        return None
    return Q @ (Us[:, :r] * s[:r]), Vt[:r].T


#: sketched far blocks (:class:`Sketch`): range sketch columns (twice the largest rank measured at 1e-4, 25, less
#: one), test columns that estimate the error, and the rows of each block formed to solve for its co-range
SKETCH_RANK = 48
SKETCH_TESTS = 16
SKETCH_SAMPLES = SKETCH_RANK + SKETCH_TESTS


@dataclass
class SketchGroup:
    r"""The sketched blocks of a tile that share a column range, columns ``q0:q1`` of the tile's (the panel's
    share of J): ``rows`` marks their rows among the asked rows; ``omega`` ((q1 - q0) x (k + t)) is the range
    map, its last t columns the test's; ``samples[b]`` the rows of block b (among the asked rows) that are formed
    too.  The pass sets ``Y`` (the group's rows' :math:`\Xi_{r,J}\Omega`, in W's order) and ``at`` (its rows
    sorted, and where each is in Y: two numbers a row of the group, not one for every asked row, since a tile has
    several groups and its asked rows are most of 3n: :meth:`y`)."""

    q0: int
    q1: int
    rows: np.ndarray
    omega: np.ndarray
    samples: list
    Y: np.ndarray | None = None
    at: tuple | None = None

    def y(self, r0: int, r1: int) -> np.ndarray:
        """Y's rows of the asked rows r0 .. r1 (one block's, all of them the group's), in that order."""
        rows, where = self.at
        k = int(np.searchsorted(rows, r0))
        return self.Y[where[k:k + r1 - r0]]


@dataclass
class Sketch:
    """What a tile asks of its pass over W (:meth:`SweepStore.sorted_columns`): the rows it forms (``formed``
    marks them among the asked rows: those of the blocks it forms and the sketched blocks' samples) and the
    range sketches of its :class:`SketchGroup` s."""

    formed: np.ndarray
    groups: list


def sketch_group(n_rows: int, q0: int, q1: int, spans: list[tuple[int, int]], rng: np.random.Generator) -> SketchGroup:
    """The maps for blocks over columns ``q0:q1`` whose rows are the asked rows ``spans`` (start, stop): a
    Gaussian Ω, and for each block :data:`SKETCH_SAMPLES` of its rows drawn uniformly without replacement."""
    omega = rng.standard_normal((q1 - q0, SKETCH_RANK + SKETCH_TESTS))
    marked = np.zeros(n_rows, bool)
    samples = []
    for r0, r1 in spans:
        marked[r0:r1] = True
        samples.append(r0 + np.sort(rng.choice(r1 - r0, SKETCH_SAMPLES, replace=False)))
    return SketchGroup(q0, q1, marked, omega, samples)


def sketches(tree: ClusterTree, i: int, j: int, c0: int, c1: int) -> bool:
    """Whether far block (I, J) is sketched in the tile of panel c0..c1: the panel's share of J has at least
    four times the sketch's columns and I at least twice as many rows (a narrower or smaller block is formed for
    less work and memory than its sketches)."""
    width = SKETCH_RANK + SKETCH_TESTS
    cols = min(int(tree.stop[j]), c1) - max(int(tree.start[j]), c0)
    return 3 * cols >= 4 * width and 3 * tree.size(i) >= 2 * width


def from_sketches(Yb: np.ndarray, Sb: np.ndarray, samples: np.ndarray, omega: np.ndarray, tol: float):
    r"""U, V (V's columns orthonormal) of a block B from its range sketch Yb = BΩ and its rows ``samples``
    (Sb = B[samples]), within ``tol`` of :math:`\|B\|_F`, or None where they cannot show it (then the block is
    formed).  Q: the range sketch's left singular vectors down to ``tol``/100 of its largest (B's range to
    well within the tolerance: a far block's spectrum falls geometrically); :math:`X = Q_S^+ S_B`, the rows
    interpolated from the samples (Q_S: Q's rows there; an interpolative decomposition on random rows, which a
    far block's smooth, incoherent range allows), so that B ≈ QX.  The error of QX is estimated from the t
    test columns, :math:`e = \|B\Omega_t - QX\Omega_t\|_F/\sqrt t` (for a Gaussian Ω_t its square's mean is
    :math:`\|B - QX\|_F^2`), and must be within ``tol``/4.2 of ‖X‖_F: it stays within tol/2 even if it is an
    underestimate by 2 (for 16 test columns a χ²₁₆ below 4, probability 6e-4 where the error is one direction,
    less where it is spread).  The SVD of X is then truncated within what is left, tol − 2.1 e (at least
    tol/2), so that the block is within ``tol`` (the two add at most; 2.1 rather than 2 for
    ‖B‖ ≥ ‖X‖ − ‖B − QX‖)."""
    k = SKETCH_RANK
    m, n = Yb.shape[0], Sb.shape[1]
    if not np.any(Yb) and not np.any(Sb):
        return np.zeros((m, 0)), np.zeros((n, 0))
    Uy, sy, _ = np.linalg.svd(Yb[:, :k], full_matrices=False)
    Q = Uy[:, :int(np.sum(sy > tol / 100 * sy[0]))]
    X = np.linalg.lstsq(Q[samples], Sb, rcond=None)[0]
    normX = float(np.linalg.norm(X))
    miss = Yb[:, k:] - Q @ (X @ omega[:, k:])
    e = float(np.linalg.norm(miss)) / np.sqrt(miss.shape[1])
    if not normX > 0.0 or e > tol / 4.2 * normX:
        return None
    Ux, s, Vt = np.linalg.svd(X, full_matrices=False)
    tail = np.concatenate([np.cumsum((s * s)[::-1])[::-1], [0.0]])  # tail[r] = Σ_{q≥r} s_q²
    r = int(np.argmax(tail <= (tol * normX - 2.1 * e) ** 2))
    if r * (m + n) >= m * n:
        return None
    return Q @ (Ux[:, :r] * s[:r]), Vt[:r].T


class SweepStore:
    """W's supernode blocks X_s (:func:`pmask.precompute.selinv.forward_sweep`) of a factor, in a
    file of the run's work folder, and the index a tile needs to read them: for each supernode its
    range of wanted columns (sorted by pivot) and its parent; for each contact dof its sorted position
    and its first supernode.  A P2 factor's load B (Ξ = W_Eᵀ W_B, W_B = L⁻¹PB) adds W_B's blocks after
    W_E's (:func:`pmask.precompute.selinv.load_sweep`): for each supernode the sorted set of B's columns
    that reach it, for each column its position and the supernodes of its non-zeros.  Small to pickle
    (the index); the blocks stay in the file."""

    def __init__(self, path: Path):
        self.path = Path(path)
        with np.load(self.index_path(self.path)) as ix:
            self.index = {k: ix[k] for k in ix.files}
        self.key = str(self.index["key"])
        self.largest = int(self.index["largest"])  # doubles in the largest X_s (of W_E or W_B)
        self.load = "setptr" in self.index  # W_B stored (P2): Ξ = W_Eᵀ W_B, no area scaling
        self.bytes_read = 0  # of the file, by this copy's passes (:meth:`passed`)

    @staticmethod
    def index_path(path: Path) -> Path:
        return Path(path).with_suffix(".index.npz")

    def columns(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Ξ[rows, cols] for contact dofs ``rows`` (any of them, in any order) and ``cols``
        (:meth:`sorted_columns`, its rows put in the order asked: a copy)."""
        D, at = self.sorted_columns(rows, cols)
        return D[at]

    def sorted_columns(self, rows: np.ndarray, cols: np.ndarray, sketch: "Sketch | None" = None):
        r"""Ξ's rows ``rows`` (contact dofs, any of them) at the columns ``cols``, in W's order, and where each
        asked row is in it: ``D[at[i]] = Ξ[rows[i], cols]``.  :math:`\sum_s X_s X_{s,J}^T` over the supernodes
        on the tree paths up from the columns' first supernodes, scaled by the columns' areas (Ξ = G diag(a));
        with a load (P2) :math:`\sum_s X_s Y_{s,J}^T`, Y_s = W_B's block, over the paths up from the supernodes of
        the columns' non-zeros.
        Only the rows asked for are multiplied and held (a symmetric Ξ's tile: those above it), in W's order so
        that each chunk of X_s adds to a run of D's rows.  A block larger than :data:`READ_BYTES` is read in row
        chunks (its rows are contiguous in the file), and each product X Xᴶᵀ is formed in slices of at most
        :data:`READ_BYTES`, so a tile holds D, one chunk and one slice, not the root's whole block (3n rows by
        the top separator's columns) nor a reordered copy.

        ``sketch``: only the rows it marks ``formed`` are formed (their ``at``; -1 for the others), and its groups'
        rows are sketched in the same pass over W (:class:`SketchGroup`): their range sketch
        :math:`\Xi_{R,J}\,\Omega`, for each chunk of X_s :math:`X_R (X_J^T \Omega)`, so that their work is the
        sketch's width, not the columns'.  The sketches are set on the groups."""
        return self.passed([(rows, cols, sketch)])[0]

    def passed(self, asks: list[tuple]) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`sorted_columns` for several tiles' ``(rows, cols, sketch)`` in one pass over W: each chunk of
        W's blocks is read once and added to every tile whose rows and columns it reaches (each tile's own
        products, in the order its own pass makes them: the same numbers).  A pass of many tiles reads W once
        where as many passes of one tile each read it about once each (their columns' paths share the top
        separators, whose blocks are most of W)."""
        ix = self.index
        lo, hi, ncol, offset = ix["lo"], ix["hi"], ix["ncol"], ix["offset"]
        todo = [_Asked(self, rows, cols, sketch) for rows, cols, sketch in asks]
        reached = np.any([a.reached for a in todo], 0) if todo else np.zeros(len(lo), bool)
        with open(self.path, "rb") as f:
            for s in np.flatnonzero(reached):
                m, nc, off = int(hi[s] - lo[s]), int(ncol[s]), int(offset[s])
                step = max(1, READ_BYTES // (8 * nc))
                mine = [(a, a.sel(s)) for a in todo if a.reached[s] and a.asks(lo[s], hi[s])]
                mine = [(a, sel) for a, sel in mine if len(sel)]
                if not mine:
                    continue  # none of its rows asked for, or none of the tiles' columns reach it
                if not self.load and m <= step:
                    X = self._read(f, off, m * nc).reshape(m, nc)
                    for a, sel in mine:
                        XJ = X[a.pj[sel] - lo[s]]
                        a.add(int(lo[s]), X, XJ, a.products(XJ, sel), sel)
                    continue
                work, whole = [], None
                for a, sel in mine:
                    if self.load:  # the tile's columns that reach s: their rows of W_B's block Y_s (read once)
                        nB = int(ix["setptr"][s + 1] - ix["setptr"][s])
                        if nB * nc * 8 <= READ_BYTES:
                            whole = self._read(f, int(ix["offsetB"][s]), nB * nc).reshape(nB, nc) if whole is None \
                                else whole
                            XJ = whole[a.kB[sel]]
                        else:
                            XJ = self._rows(f, int(ix["offsetB"][s]), nc, a.kB[sel])
                    else:
                        XJ = self._rows(f, off, nc, a.pj[sel] - lo[s])  # the tile's rows of X_s (row by row)
                    work.append((a, sel, XJ, a.products(XJ, sel)))
                del whole
                for r0 in range(0, m, step):
                    r1 = min(m, r0 + step)
                    want = [w for w in work if w[0].asks(lo[s] + r0, lo[s] + r1)]
                    if want:
                        X = self._read(f, off + r0 * nc, (r1 - r0) * nc).reshape(r1 - r0, nc)
                        for a, sel, XJ, OJ in want:
                            a.add(int(lo[s]) + r0, X, XJ, OJ, sel)
        return [a.finish() for a in todo]

    def _read(self, f, off: int, count: int) -> np.ndarray:  # ``count`` doubles from double ``off`` on
        f.seek(8 * off)
        self.bytes_read += 8 * count
        return np.fromfile(f, np.float64, count)

    def _rows(self, f, off: int, nc: int, idx: np.ndarray) -> np.ndarray:
        """Rows ``idx`` of the row-major (·, nc) block at ``off`` (doubles), row by row."""
        out = np.empty((len(idx), nc))
        for q, r in enumerate(idx):
            out[q] = self._read(f, off + int(r) * nc, nc)
        return out


class _Asked:
    """One tile's share of a pass over W (:meth:`SweepStore.passed`): which supernodes its columns reach, the
    rows it forms (D, in W's order) and sketches, and the products each chunk of W adds to them."""

    def __init__(self, store: SweepStore, rows: np.ndarray, cols: np.ndarray, sketch: "Sketch | None"):
        ix = store.index
        pos, parent = ix["pos"], ix["parent"]
        self.load = store.load
        self.pj = pos[cols]
        self.lo, self.hi = ix["lo"], ix["hi"]
        self.ncols = len(cols)
        if self.load:
            own, optr = ix["ownB"], ix["ownptr"]
            starts = np.unique(np.concatenate([own[optr[c]:optr[c + 1]] for c in cols] + [own[:0]]))
            self.pb, self.sets, self.sptr = ix["posB"][cols], ix["setsB"], ix["setptr"]
        else:
            starts = np.unique(ix["first"][cols])
        self.reached = np.zeros(len(ix["lo"]), bool)
        for s in starts:
            while s >= 0 and not self.reached[s]:
                self.reached[s] = True
                s = parent[s]
        self.groups = groups = [] if sketch is None else sketch.groups
        self.rows = rows
        asked = np.ones(len(rows), bool) if sketch is None else sketch.formed | np.any([g.rows for g in groups], 0)
        rows_in = np.flatnonzero(asked)
        self.order = order = rows_in[np.argsort(pos[rows[rows_in]])]  # the rows formed or sketched, in W's order
        self.ps = ps = pos[rows[order]]  # their positions, sorted
        formed = np.ones(len(order), bool) if sketch is None else sketch.formed[order]
        self.fbefore = np.concatenate([[0], np.cumsum(formed)])  # formed rows before each sorted row
        self.at = np.full(len(rows), -1, np.int64)
        self.at[order[formed]] = np.arange(int(self.fbefore[-1]))  # D's rows: the formed ones, in W's order
        self.D = np.zeros((int(self.fbefore[-1]), len(cols)))
        self.scale = np.ones(len(cols)) if self.load else ix["scale"][cols]
        self.live = []  # per group: its rows' positions (sorted: Y's rows are in W's order), Ω scaled
        for g in groups:
            pg = ps[g.rows[order]]
            g.Y = np.zeros((len(pg), g.omega.shape[1]))
            self.live.append((g, pg, g.omega * self.scale[g.q0:g.q1, None]))
        self.pf = ps[formed]  # the formed rows' positions

    def asks(self, first, stop) -> bool:  # whether any of its rows are at positions first .. stop
        return bool(np.searchsorted(self.ps, first) < np.searchsorted(self.ps, stop))

    def sel(self, s: int) -> np.ndarray:
        """The tile's columns whose rows of supernode s's block it multiplies (P2: those of W_B's columns that
        reach s, at their rows ``kB`` of its block)."""
        if not self.load:
            return np.flatnonzero((self.pj >= self.lo[s]) & (self.pj < self.hi[s]))
        cs = self.sets[self.sptr[s]:self.sptr[s + 1]]
        k = np.minimum(np.searchsorted(cs, self.pb), max(len(cs) - 1, 0))
        self.kB = k
        return np.flatnonzero(cs[k] == self.pb) if len(cs) else np.zeros(0, np.int64)

    def products(self, XJ: np.ndarray, sel: np.ndarray) -> list:
        """Per group: X_Jᵀ Ω over the supernode's columns in its range (None: none are)."""
        out = []
        for g, _, omega in self.live:
            idx = np.flatnonzero((sel >= g.q0) & (sel < g.q1))
            out.append(XJ[idx].T @ omega[sel[idx] - g.q0] if len(idx) else None)
        return out

    def add(self, first: int, X: np.ndarray, XJ: np.ndarray, OJ: list, sel: np.ndarray) -> None:
        """The rows at positions first .. first + len(X): D += X XJᵀ (in slices of at most :data:`READ_BYTES`),
        each group's Y += X_R (X_Jᵀ Ω)."""
        ps, D = self.ps, self.D
        a, b = np.searchsorted(ps, first), np.searchsorted(ps, first + len(X))
        for (g, pg, _), OJg in zip(self.live, OJ):
            y0, y1 = int(np.searchsorted(pg, first)), int(np.searchsorted(pg, first + len(X)))  # its rows here
            if y1 > y0 and OJg is not None:
                g.Y[y0:y1] += (X if y1 - y0 == len(X) else X[pg[y0:y1] - first]) @ OJg
        d0, d1 = int(self.fbefore[a]), int(self.fbefore[b])
        if d1 == d0:
            return
        Xk = X if d1 - d0 == len(X) else X[self.pf[d0:d1] - first]
        step = max(1, READ_BYTES // (8 * max(len(sel), 1)))
        for q in range(0, len(Xk), step):
            P = Xk[q:q + step] @ XJ.T
            if len(sel) == self.ncols:
                D[d0 + q:d0 + q + len(P)] += P
            else:
                D[d0 + q:d0 + q + len(P), sel] += P

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.load:
            self.D *= self.scale[None, :]
        for g in self.groups:
            mine = self.order[g.rows[self.order]]  # the asked rows of Y's rows, in Y's order
            by_row = np.argsort(mine)
            g.at = (mine[by_row], by_row)
        D, at = self.D, self.at
        self.D = None  # (the pass hands D on: the tile drops it once compressed)
        return D, at


class DenseSource:
    r"""Ξ's rows and columns from the dense Ξ in memory, in place of W's store (:class:`SweepStore`), where the
    dense route's Ξ fits on this machine (:func:`compressed_greens` with ``dense``): a tile asks it what it asks a
    pass over W, its formed rows and its groups' range sketches :math:`\Xi_{R,J}\Omega`, and gets the same
    numbers to round-off (gathered and multiplied here, not summed over W's supernodes).  Ξ is already
    :math:`G\,\mathrm{diag}(a)` (P2: :math:`W_E^T W_B`), so nothing is scaled.  ``D``'s rows are the formed rows
    in the order asked, and each group's Y its rows in the order asked (:meth:`SweepStore.sorted_columns`'
    ``at`` and :attr:`SketchGroup.at` say where: the tile reads them through those)."""

    def __init__(self, Xi: np.ndarray):
        self.Xi = Xi
        self.bytes_read = 0  # (no file: the route reads no W)

    def passed(self, asks: list[tuple]) -> list[tuple[np.ndarray, np.ndarray]]:
        return [self._asked(rows, cols, sketch) for rows, cols, sketch in asks]

    def _asked(self, rows: np.ndarray, cols: np.ndarray, sketch: "Sketch | None"):
        formed = np.flatnonzero(np.ones(len(rows), bool) if sketch is None else sketch.formed)
        at = np.full(len(rows), -1, np.int64)
        at[formed] = np.arange(len(formed))
        D = self.Xi[np.ix_(rows[formed], cols)]
        for g in ([] if sketch is None else sketch.groups):
            mine = np.flatnonzero(g.rows)  # the group's asked rows, ascending: Y's rows in that order
            g.Y = self.Xi[np.ix_(rows[mine], cols[g.q0:g.q1])] @ g.omega
            g.at = (mine, np.arange(len(mine)))
        return D, at


def sweep_reusable(path: Path, key: str) -> bool:
    """Whether W's store at ``path`` holds this factor's W (``key``) in this layout, complete (its index is
    written last)."""
    path = Path(path)
    if not (SweepStore.index_path(path).exists() and path.exists()):
        return False
    try:
        store = SweepStore(path)
    except (OSError, ValueError, KeyError):
        return False  # a damaged index: sweep again
    return store.key == key and str(store.index.get("layout")) == LAYOUT and "factor_stats" in store.index


#: the W sweep's memory on its worker (beside the factor): the wanted columns are swept in as many batches as keep each
#: batch's peak (:func:`pmask.precompute.selinv.sweep_memory`) below this (#27: bounded at any n)
SWEEP_BUDGET = 1.5 * 2**30


def sweep_batches(tree, piv_sorted: np.ndarray, budget: float = SWEEP_BUDGET) -> tuple[list, int]:
    """Contiguous ranges of the wanted pivots (sorted) whose sweeps each peak below ``budget`` bytes: the
    fewest of 1, 2, 4, ... equal ranges (W's columns are independent: a batch's sweep is the same
    arithmetic on its own columns).  Returns the ranges and the largest batch's modelled peak."""
    from pmask.precompute import selinv

    return _batches(len(piv_sorted), lambda a, b: selinv.sweep_memory(tree, tree.perm[piv_sorted[a:b]],
                                                                      READ_BYTES)["peak"],
                    8 * (3 * len(piv_sorted) + 3 * tree.ns), budget)


def load_batches(tree, B, sets: list, posB: np.ndarray, budget: float = SWEEP_BUDGET) -> tuple[list, int]:
    """As :func:`sweep_batches` for W_B = L⁻¹PB (a P2 load; :func:`pmask.precompute.selinv.load_sweep`): contiguous
    ranges of B's columns by position, each batch's peak modelled from the number of its columns reaching each
    supernode."""
    from pmask.precompute import selinv

    members = np.concatenate([np.asarray(c, np.int64) for c in sets] + [np.zeros(0, np.int64)])
    owner = np.repeat(np.arange(len(sets)), [len(c) for c in sets])  # each set member's supernode
    nnz_pos = np.sort(posB[np.repeat(np.arange(B.shape[1]), np.diff(B.indptr))])

    def peak(a, b):
        size = np.bincount(owner[(members >= a) & (members < b)], minlength=len(sets))
        nnz = int(np.searchsorted(nnz_pos, b) - np.searchsorted(nnz_pos, a))
        return selinv.sweep_memory(tree, nnz, READ_BYTES, size=size)["peak"]

    return _batches(B.shape[1], peak, 8 * (3 * B.shape[1] + 3 * tree.ns + len(members)), budget)


def _batches(n: int, peak, index: int, budget: float) -> tuple[list, int]:
    """The fewest of 1, 2, 4, ... equal contiguous ranges of n columns whose ``peak(a, b)`` each, beside the
    ``index`` bytes :func:`sweep` holds, stays below ``budget``; the ranges and the largest modelled peak."""
    k = 1
    while True:
        cuts = np.linspace(0, n, k + 1).round().astype(np.int64)
        ranges = [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
        top = max((peak(a, b) for a, b in ranges), default=0) + index  # sweep()'s own index arrays beside it
        if top <= budget or k >= n:
            return ranges, int(top)
        k *= 2


def sweep_bytes(factor, budget: float = SWEEP_BUDGET) -> int:
    """The W sweep's peak (bytes) for a factor, swept in :func:`sweep_batches` (and a P2 load's W_B in
    :func:`load_batches`, after it), from its elimination tree (:func:`pmask.precompute.selinv.sweep_memory`)."""
    from pmask.precompute import selinv

    tree = selinv._Tree(factor.L)
    piv = np.sort(tree.iperm[np.asarray(factor.rows[:factor.n_observed], np.int64)])
    peak = sweep_batches(tree, piv, budget)[1]
    if factor.load is not None:
        B = _load_columns(factor)
        sets, posB = selinv.column_sets(tree, B)
        peak = max(peak, load_batches(tree, B, sets, posB, budget)[1])
    return peak


def _load_columns(factor) -> sp.csc_matrix:
    """A P2 factor's load B (free dofs x contact dofs), canonical CSC."""
    B = sp.csc_matrix(factor.load)
    B.sum_duplicates()
    B.sort_indices()
    return B


def sweep(factor, path: Path, key: str, budget: float = SWEEP_BUDGET, room: float | None = None) -> SweepStore:
    """W = L⁻¹PE of a factor, supernode by supernode, into ``path`` (:class:`SweepStore`), and for a P2 factor
    (a consistent load B) W_B = L⁻¹PB after it (:func:`pmask.precompute.selinv.load_sweep`); reused when
    its index holds ``key`` (a rerun after a crash does not sweep again).  Both files are written
    atomically, the index last, so a file without one is never read; refused in one line before it starts
    when its modelled peak does not fit (:func:`check_phase_memory`).

    The wanted columns are swept in contiguous batches (:func:`sweep_batches`) so that the client holds at
    most ``budget`` bytes of pending blocks however many contact vertices there are (one sweep at 47,467
    would hold 8.6 GiB by :func:`pmask.precompute.selinv.sweep_memory`, the top separators' blocks over all
    3 n_c rows); each batch writes its rows of every
    supernode's block into their place in the file, which has the layout of a single sweep.  ``room``: the bytes
    this process may still use (a Dask worker's limit less what it holds: :func:`factor_and_sweep`), which the
    batches are cut to fit; refused in one line when a single batch does not."""
    from pmask.precompute import selinv
    from pmask.runtime.files import atomic_write

    path = Path(path)
    index = SweepStore.index_path(path)
    if sweep_reusable(path, key):
        return SweepStore(path)
    tree = selinv._Tree(factor.L)
    nobs = factor.n_observed
    piv = tree.iperm[np.asarray(factor.rows[:nobs], np.int64)]
    lo, hi, pos = tree.ranges(piv)
    m = hi - lo
    offset = np.zeros(tree.ns, np.int64)
    offset[1:] = np.cumsum(m * tree.ncol)[:-1]  # in postorder, as the single sweep emitted them
    ordered = np.sort(piv)
    if room is not None:
        budget = min(budget, room / PHASE_MARGIN)
    batches, peak = sweep_batches(tree, ordered, budget)
    size = int(np.sum(m * tree.ncol))  # doubles of W_E
    largest = int((m * tree.ncol).max()) if len(m) else 0
    gram = float(np.sum(m.astype(float) ** 2 * tree.ncol))  # the dense route's syrks
    extra = {"scale": factor.scale}
    if factor.load is not None:  # P2: W_B's blocks follow W_E's, each supernode's rows its set's columns
        B = _load_columns(factor)
        sets, posB = selinv.column_sets(tree, B)
        mB = np.array([len(c) for c in sets], np.int64)
        offsetB = size + np.concatenate([[0], np.cumsum(mB * tree.ncol)[:-1]]).astype(np.int64)
        load_b, peak_b = load_batches(tree, B, sets, posB, budget)
        peak = max(peak, peak_b)
        size += int(np.sum(mB * tree.ncol))
        largest = max(largest, int((mB * tree.ncol).max()) if len(mB) else 0)
        gram = float(np.sum(2.0 * m * mB * tree.ncol))  # the dense route's gemms W_Eᵀ W_B
        own = [np.unique(tree.snode[tree.iperm[B.indices[B.indptr[c]:B.indptr[c + 1]]]]) for c in range(B.shape[1])]
        extra = {"scale": np.zeros(0), "posB": posB, "setsB": np.concatenate(sets + [np.zeros(0, np.int64)]),
                 "setptr": np.concatenate([[0], np.cumsum(mB)]).astype(np.int64), "offsetB": offsetB,
                 "ownB": np.concatenate(own + [np.zeros(0, np.int64)]),
                 "ownptr": np.concatenate([[0], np.cumsum([len(o) for o in own])]).astype(np.int64)}
    if room is not None and PHASE_MARGIN * peak > room:
        raise ResourceError(f"the compressed route's W sweep needs ~{peak / 2**30:.2f} GiB at its peak beside the "
                            f"factor, more than the {max(room, 0) / 2**30:.2f} GiB left under its Dask worker's "
                            "memory limit; give the workers more (--worker-memory) or use fewer, larger workers")
    check_phase_memory("W sweep", peak, "restrict the region a probe can touch (--contact SELECTOR) or coarsen "
                       "the mesh (--edge-length, --size): its blocks are the contact vertices' rows by the top "
                       "separators' columns")
    flops = [0.0]

    def write(tmp):
        with open(tmp, "wb") as f:
            f.truncate(8 * size)

            def put(first, X):  # X's rows, row-major from double ``first`` on, so that a tile reads row chunks
                f.seek(8 * int(first))
                step = max(1, READ_BYTES // (8 * X.shape[1]))
                for r0 in range(0, X.shape[0], step):
                    np.ascontiguousarray(X[r0:r0 + step]).tofile(f)

            for b0, b1 in batches:
                def emit(s, lo_b, X, b0=b0):  # the batch's rows [b0 + lo_b, ...) of supernode s's block
                    put(offset[s] + (b0 + lo_b - lo[s]) * tree.ncol[s], X)

                flops[0] += selinv.forward_sweep(tree, tree.perm[ordered[b0:b1]], emit)["flops"]
            if factor.load is not None:
                for b0, b1 in load_b:  # W_B: each batch a run of every supernode's set
                    flops[0] += selinv.load_sweep(tree, B, sets, posB, b0, b1, lambda s, first, X: put(
                        offsetB[s] + first * tree.ncol[s], X))["flops"]

    atomic_write(path, write)  # a full disk is one line (W is 8-20 % of the dense Ξ's size, measured)
    arrays = {"key": np.array(key), "layout": np.array(LAYOUT), "pos": pos, "lo": lo, "hi": hi,
              "ncol": tree.ncol, "parent": tree.parent, "first": tree.snode[piv], "offset": offset, **extra,
              "largest": np.array(largest), "flops": np.array(flops[0]), "peak_bytes": np.array(peak),
              "batches": np.array(len(batches) + (len(load_b) if factor.load is not None else 0)),
              "gram_flops": np.array(gram), "factor_stats": np.array(json.dumps(factor.stats))}
    # (the factor's stats: a rerun that reuses W needs no factor)
    atomic_write(index, lambda tmp: np.savez(tmp, **arrays), suffix=".npz")
    return SweepStore(path)


@dataclass
class FactorJob:
    """A factorisation made where W is swept, on a Dask worker (:func:`factor_and_sweep`), so that the client
    holds neither the stiffness's assembly, nor the factor, nor the sweep (#27: at 47,467 contact vertices those
    made the client's 2.42 GiB).  ``make()`` returns (factor, timings): the pipeline's assembly and factorisation,
    pickled by reference.  ``checkpoint``: the factor's file in the work folder, read instead of factorising when
    it is there and written when it is not (a rerun after a crash resumes); ``timeout``: the factorisation's time
    limit (:func:`pmask.precompute.native.budget`).  :func:`compressed_greens` fills in ``stats`` (the factor's),
    ``timings`` and ``resumed`` from what the worker reports.  ``element``: the factor's element (P1's Ξ is
    stored once per symmetric pair of blocks, P2's whole: :func:`is_symmetric`); ``need``: the bytes its worker
    holds at its peak (:func:`factor_phase_bytes` of the factor's estimate; 0: unknown), which the task's worker
    must have under its memory limit (:func:`factor_workers`)."""

    make: Callable
    checkpoint: Path | None = None
    timeout: float | None = None
    element: str = "P1"
    need: float = 0.0
    stats: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    resumed: bool = False

    def build(self) -> tuple:
        """(factor, timings, resumed): the checkpoint's factor, or one made (and then checkpointed by the caller)."""
        from pmask.precompute import greens, native

        t0 = time.perf_counter()
        factor = greens.load_checkpoint(self.checkpoint) if self.checkpoint else None
        if factor is not None:
            return factor, {"assemble": 0.0, "factor": time.perf_counter() - t0}, True
        with native.budget(self.timeout):
            factor, timings = self.make()
        if (factor.load is None) != (self.element == "P1"):
            raise TypeError(f"a FactorJob for {self.element} made a factor of the other element")
        return factor, timings, False

    def summary(self) -> dict:
        """What :func:`factor_and_sweep` reports, without a sweep, for a rerun whose tiles are all stored: the
        loads' scale and the factor's stats read from its checkpoint, not its L (an npz member is read alone);
        made here only when the checkpoint is gone."""
        if self.checkpoint is not None and Path(self.checkpoint).exists():
            try:
                with np.load(self.checkpoint) as ck:  # (P2's load is its own: no scale)
                    return {"scale": ck["scale"] if "scale" in ck else None, "stats": json.loads(str(ck["stats"])),
                            "timings": {}, "resumed": True}
            except (OSError, ValueError, KeyError) as exc:
                log.warning("the factor checkpoint %s cannot be read (%s); factorising again", self.checkpoint, exc)
        factor, timings, resumed = self.build()
        return {"scale": factor.scale, "stats": factor.stats, "timings": timings, "resumed": resumed}


def _blas_cores() -> int:
    """The cores this process may run on (its affinity; a container's share)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _worker_room() -> float | None:
    """Bytes this Dask worker may still use before its nanny restarts it (its memory limit times dask's
    ``distributed.worker.memory.terminate`` fraction, less its resident memory now); None outside a worker or
    without a limit."""
    import dask
    import psutil

    try:
        from distributed import get_worker

        limit = get_worker().memory_manager.memory_limit
    except (ImportError, ValueError, AttributeError):
        return None
    fraction = dask.config.get("distributed.worker.memory.terminate", 0.95) or 1.0
    return float(limit) * float(fraction) - psutil.Process().memory_info().rss if limit else None


def factor_and_sweep(source, path, key: str, budget: float = SWEEP_BUDGET) -> dict:
    """The task that sweeps W (:func:`sweep`) on whichever worker the scheduler picks, from ``source``: a
    :class:`FactorJob` (assembled and factorised here; its checkpoint written while W is swept) or a factor
    sent along.  Its BLAS gets every core of the worker's machine: Dask starts workers with one BLAS thread each,
    right for the tiles, but nothing else of the run is running while W is swept.  Returns what the client keeps:
    the loads' ``scale``, the factor's ``stats``, ``timings``, ``resumed`` (the checkpoint or W reused) and where
    it ran (``pid``, ``host``)."""
    import platform

    from threadpoolctl import threadpool_info, threadpool_limits

    from pmask.precompute import greens, native

    if not native.available():  # CHOLMOD's BLAS loaded, so that the limits below reach it too
        try:
            import cvxopt  # noqa: F401 (the pip-only route's CHOLMOD and its bundled BLAS)
        except ImportError:
            pass
    path = Path(path)
    t0 = time.perf_counter()
    with threadpool_limits(_blas_cores()):
        threads = min((p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"), default=1)
        if sweep_reusable(path, key):
            W = SweepStore(path)
            stats, timings, resumed = json.loads(str(W.index["factor_stats"])), {}, True
        else:
            if isinstance(source, FactorJob):
                factor, timings, resumed = source.build()
            else:
                factor, timings, resumed = source, {}, False
            saving = None
            if isinstance(source, FactorJob) and source.checkpoint and not resumed:
                saving = Background(greens.save_checkpoint, source.checkpoint, factor)  # while W is swept
            t1 = time.perf_counter()
            try:
                W = sweep(factor, path, key, budget, _worker_room())
            finally:  # (a refused sweep still lets the checkpoint be written)
                try:
                    if saving is not None:
                        saving.join()
                except Exception as exc:  # noqa: BLE001 (a checkpoint is an aid: the run goes on without it)
                    log.warning("the factor checkpoint %s was not written (%s); a rerun factorises again",
                                source.checkpoint, exc)
            timings, stats = {**timings, "sweep": time.perf_counter() - t1}, factor.stats
    return {"scale": np.asarray(W.index["scale"]), "stats": stats, "timings": timings, "resumed": resumed,
            "seconds": time.perf_counter() - t0, "pid": os.getpid(), "host": platform.node(), "blas_threads": threads}


def solved_columns(factor, dcols: np.ndarray) -> np.ndarray:
    """Ξ's columns ``dcols`` (contact dofs), rows in contact order, solved from the factor by the selected
    inversion (:func:`pmask.precompute.greens.inverse_columns`): an independent check of the W store's columns
    (the bench's)."""
    from pmask.precompute import greens

    if factor.load is None:  # P1: a traction at dof d is the nodal force scale[d] there
        B = sp.csc_matrix((factor.scale[dcols], (factor.rows[dcols], np.arange(len(dcols)))),
                          shape=(factor.stats["dofs"], len(dcols)))
    else:
        B = factor.load[:, dcols]
    X, _ = greens.inverse_columns(factor.L, factor.rows[:factor.n_observed], B)
    return X


def is_symmetric(factor) -> bool:
    r"""Whether Ξ = G diag(a) with G symmetric, so that :math:`\Xi_{JI} = \mathrm{diag}(a_J)^{-1}\,\Xi_{IJ}^T
    \mathrm{diag}(a_I)` and only the blocks on and above the diagonal need storing: a P1 factor (its load is the
    unit columns times the vertex areas, the same area for a vertex's three dofs).  P2's consistent load
    (Ξ = Eᵀ K⁻¹ B, B ≠ E diag(a)) is not."""
    if factor.load is not None or factor.scale is None:
        return False
    per_dof = np.asarray(factor.scale, float).reshape(-1, 3)
    return bool(np.all(per_dof == per_dof[:, :1]))


def tile(store: SweepStore, tree: ClusterTree, column: int, blocks, tol: float, near=None, sketch: bool = True) -> dict:
    """The panel of cluster ``column`` and its blocks compressed (:func:`tiles`, a pass of this tile alone).
    Returns arrays in the
    reader's layout with offsets relative to this tile (:func:`assemble` shifts them), the low-rank
    index with an eighth column: the block's column cluster J.  Where J is wider than the panel the
    entry is a *piece* Ξ_{I,column} of the block, compressed within ``tol``/2 with V's columns
    orthonormal; :func:`assemble` merges a block's pieces (:func:`merge_pieces`) within the other half.
    ``near``: (the vertices' positions in cluster order, r_max): the dense blocks are stored pair by pair, those
    within r_max exactly and the others in 16 bits (:func:`pmask.runtime.compressed.encode_near`); None: whole.
    ``sketch``: the far blocks :func:`sketches` picks are compressed from sketches taken in the same pass over W
    (:func:`from_sketches`), not formed; one whose sketches cannot show the tolerance is formed after all (the
    tile's ``formed_again``).  False: every block formed (the test's reference)."""
    return tiles(store, tree, [column], [blocks], tol, near, sketch)[0]


def tiles(store: SweepStore, tree: ClusterTree, columns: list[int], plans: list, tol: float, near=None,
          sketch: bool = True, folder: Path | None = None) -> list[dict]:
    """One task: the panels of clusters ``columns`` (their blocks ``plans``) in one pass over W
    (:meth:`SweepStore.passed`), then compressed one after the other (:func:`tile`'s results, the same numbers
    as each tile's own pass), each panel's formed rows dropped once it is.  The sketched blocks whose sketches
    cannot show the tolerance are formed after all in one more pass over W for all the tiles' (each block's
    products its own, so the same numbers as a tile alone), not in a read of W each (at 51,519 vertices, 7 passes
    read W's store 7.9 times in all at r_max = 5 mm, where 40 blocks were formed after all one by one, and 5.6
    times at 10 mm, where 1 was: the bench rows of 2026-11-29 23:01 and 23:20).
    Each result's ``read_bytes`` is its share of the bytes the passes read; ``pass_tiles`` the pass's tiles.
    ``folder``: each tile's arrays are written there once compressed (:func:`_tile_file`), and its result names
    the file (``path``) in their place, so that neither the worker nor the client holds a whole pass's results
    (the client reads them one tile at a time: :func:`read_tile`); a tile with blocks formed after all is written
    after that pass."""
    t0 = time.perf_counter()
    read0 = store.bytes_read
    plan = [_tile_plan(tree, c, blocks, sketch) for c, blocks in zip(columns, plans)]
    made = store.passed([(p["rows"], p["dcols"], p["sketch"]) for p in plan])
    solve = (time.perf_counter() - t0) / max(len(plan), 1)
    out, later, held = [], [], 0
    for k, blocks in enumerate(plans):
        (X, at), p = made[k], plan[k]
        made[k] = plan[k] = None  # (its formed rows and sketches go once it is compressed)
        held += X.nbytes
        tile_out, again = _tile_compress(tree, p, blocks, X, at, tol, near)
        del X, at
        if again:  # (its blocks formed after all, below)
            later.append((k, tile_out, again))
            out.append(None)
        else:
            out.append(_tile_done(tile_out, folder))
    # the blocks formed after all: one more pass over W for all of them, or as many as it takes to form at a
    # time no more than the pass's formed rows held (one a block at most, as each alone would)
    asks = [(tile_out, ij, rows, cols) for _, tile_out, again in later for ij, rows, cols in again]
    while asks:
        n, size = 1, 8 * len(asks[0][2]) * len(asks[0][3])
        while n < len(asks) and size + 8 * len(asks[n][2]) * len(asks[n][3]) <= held:
            size += 8 * len(asks[n][2]) * len(asks[n][3])
            n += 1
        batch, asks = asks[:n], asks[n:]
        for (tile_out, ij, _, _), (D, at) in zip(batch, store.passed([(r, c, None) for _, _, r, c in batch])):
            t1 = time.perf_counter()
            tile_out.put(*ij, D[at])
            tile_out.seconds += time.perf_counter() - t1
    for k, tile_out, _ in later:
        out[k] = _tile_done(tile_out, folder)
    for t in out:
        t.update({"solve_s": solve, "read_bytes": (store.bytes_read - read0) / max(len(out), 1),
                  "pass_tiles": len(out)})
    return out


def _tile_done(tile_out: "_TileOut", folder: Path | None) -> dict:
    t = tile_out.result()
    return t if folder is None else _tile_file(t, Path(folder))


def _tile_file(t: dict, folder: Path) -> dict:
    """Tile ``t``'s arrays written to ``folder``/tile-C.npz (whole, or not at all: written under another name and
    renamed), and ``t`` without them, naming the file."""
    path = folder / f"tile-{t['column']}.npz"
    part = folder / f"tile-{t['column']}.part.npz"
    np.savez(part, **{k: t[k] for k in TileStore.FIELDS})
    os.replace(part, path)
    return {**{k: v for k, v in t.items() if k not in TileStore.FIELDS}, "path": str(path)}


def read_tile(t: dict) -> dict:
    """A tile's result with its arrays, read back from the file a pass wrote (:func:`tiles` with a folder)."""
    if "path" not in t:
        return t
    with np.load(t["path"]) as z:
        return {**{k: v for k, v in t.items() if k != "path"}, **{k: z[k] for k in TileStore.FIELDS}}


def _tile_plan(tree: ClusterTree, column: int, blocks, sketch: bool) -> dict:
    """What tile ``column`` asks of the pass: its rows and columns, the far blocks it sketches (their
    :class:`SketchGroup`, by column range) and the rows it forms."""
    c0, c1 = int(tree.start[column]), int(tree.stop[column])
    upto = max((int(tree.stop[i]) for i, _, _ in blocks), default=0)  # one past the last row any block needs
    rows = (3 * tree.perm[:, None] + np.arange(3)).ravel()[:3 * upto]  # contact dofs in cluster order
    dcols = (3 * tree.perm[c0:c1, None] + np.arange(3)).ravel()  # the panel's traction columns
    sketched = {(i, j) for i, j, far in blocks if far and sketches(tree, i, j, c0, c1)} if sketch else set()
    formed = np.zeros(len(rows), bool)  # the rows of the blocks formed (none of a block below the diagonal)
    spans: dict[tuple[int, int], list] = {}  # the sketched blocks' rows by their columns in the tile
    for i, j, _ in blocks:
        r0, r1 = 3 * int(tree.start[i]), 3 * int(tree.stop[i])
        if (i, j) in sketched:
            q = (3 * (max(int(tree.start[j]), c0) - c0), 3 * (min(int(tree.stop[j]), c1) - c0))
            spans.setdefault(q, []).append(((i, j), r0, r1))
        else:
            formed[r0:r1] = True
    srng = np.random.default_rng([column, 1])  # the sketches' own draws, apart from the formed blocks' (rng)
    groups = [sketch_group(len(rows), q0, q1, [(r0, r1) for _, r0, r1 in spans[q0, q1]], srng)
              for q0, q1 in sorted(spans)]
    for g in groups:
        for rs in g.samples:
            formed[rs] = True
    band = {ij: (g, b) for g, (q0, q1) in zip(groups, sorted(spans)) for b, (ij, _, _) in enumerate(spans[q0, q1])}
    return {"column": column, "c0": c0, "c1": c1, "rows": rows, "dcols": dcols, "sketched": len(sketched),
            "band": band, "sketch": Sketch(formed, groups)}


def _tile_compress(tree: ClusterTree, p: dict, blocks, X: np.ndarray, at: np.ndarray, tol: float,
                   near) -> tuple["_TileOut", list]:
    """Tile ``p`` (:func:`_tile_plan`) compressed from its pass's formed rows X (``at``) and sketches, and the
    blocks its sketches could not show within the tolerance, to be formed after all: ``((i, j, far), rows,
    cols)``, its rows and columns of Ξ (:func:`tiles` forms them and puts them in)."""
    t0 = time.perf_counter()
    c0, c1, rows, dcols, band = p["c0"], p["c1"], p["rows"], p["dcols"], p["band"]
    out = _TileOut(tree, p, tol, near)
    again = []
    for i, j, far in blocks:
        r0, r1 = int(tree.start[i]), int(tree.stop[i])
        b0, b1 = max(int(tree.start[j]), c0), min(int(tree.stop[j]), c1)
        if (i, j) in band:  # from its sketches; formed after all where they cannot show the tolerance
            g, b = band[i, j]
            rs = g.samples[b]
            piece = (b0, b1) != (int(tree.start[j]), int(tree.stop[j]))
            uv = from_sketches(g.y(3 * r0, 3 * r1), X[at[rs], 3 * (b0 - c0):3 * (b1 - c0)], rs - 3 * r0, g.omega,
                               truncation_tolerance(tol) / (2 if piece else 1))
            if uv is None:
                again.append(((i, j, far), rows[3 * r0:3 * r1], dcols[3 * (b0 - c0):3 * (b1 - c0)]))
            else:
                out.put(i, j, far, uv=uv)
        else:
            out.put(i, j, far, X[at[3 * r0:3 * r1], 3 * (b0 - c0):3 * (b1 - c0)])
    out.formed_again = len(again)
    out.seconds += time.perf_counter() - t0
    return out, again


class _TileOut:
    """A tile's arrays as its blocks are put in (:func:`_tile_compress`), in the reader's layout with offsets
    relative to the tile (:func:`tile`)."""

    def __init__(self, tree: ClusterTree, p: dict, tol: float, near):
        self.tree, self.column, self.c0, self.c1 = tree, int(p["column"]), int(p["c0"]), int(p["c1"])
        self.sketched, self.tol, self.near = p["sketched"], tol, near
        self.far_tol = truncation_tolerance(tol)  # (the rest, where the factors are 16-bit, for their rounding)
        self.rng = np.random.default_rng(self.column)  # reproducible: the same tile, the same factors
        self.dense_index, self.dense, self.lr_index, self.Us, self.Vs = [], [], [], [], []
        self.near_index, self.near_q, self.near_mask, self.near_scale = [], [], [], []
        self.d_off = self.u_off = self.v_off = 0
        self.at_near = np.zeros(3, np.int64)  # offsets in near_q, near_mask, near_scale
        self.formed_again, self.seconds = 0, 0.0

    def put(self, i: int, j: int, far: bool, B: np.ndarray | None = None, uv: tuple | None = None) -> None:
        """Block (I, J)'s share of the panel: its low-rank factors ``uv``, or formed (``B``): a far block
        compressed within the tolerance (a piece of a block wider than the panel within half of it), else stored
        dense (the near field pair by pair: :func:`tile`), a piece that does not compress as its exact columns."""
        tree, c0, c1, tol = self.tree, self.c0, self.c1, self.tol
        r0, r1 = int(tree.start[i]), int(tree.stop[i])
        b0, b1 = max(int(tree.start[j]), c0), min(int(tree.stop[j]), c1)
        piece = (b0, b1) != (int(tree.start[j]), int(tree.stop[j]))
        if uv is None and far:
            uv = low_rank(B, self.far_tol / (2 if piece else 1), self.rng)
        if uv is None and piece:  # a piece is merged in low-rank form: its exact columns, V = I
            uv = (np.array(B), np.eye(B.shape[1]))
        if uv is None and self.near is not None:
            pts, r_max = self.near
            exact = np.linalg.norm(pts[r0:r1, None] - pts[None, b0:b1], axis=2) <= r_max * (1.0 + 1e-9)  # (close)
            parts = encode_near(B, exact, tol)
            self.dense_index.append((r0, r1, b0, b1, self.d_off))
            self.near_index.append(tuple(self.at_near))
            for lst, arr in zip((self.dense, self.near_q, self.near_scale, self.near_mask), parts):
                lst.append(arr)
            self.d_off += len(parts[0])
            self.at_near += [len(parts[1]), len(parts[3]), len(parts[2])]
        elif uv is None:
            self.dense_index.append((r0, r1, b0, b1, self.d_off))
            self.dense.append(np.ascontiguousarray(B).ravel())
            self.d_off += B.size
        else:
            U, V = uv
            self.lr_index.append((r0, r1, b0, b1, U.shape[1], self.u_off, self.v_off, j))
            self.Us.append(U.ravel()), self.Vs.append(V.ravel())
            self.u_off += U.size
            self.v_off += V.size

    def result(self) -> dict:
        cat = lambda parts, dt=np.float64: np.concatenate(parts) if parts else np.zeros(0, dt)  # noqa: E731
        return {"column": self.column, "dense_index": np.array(self.dense_index, np.int64).reshape(-1, 5),
                "dense": cat(self.dense), "lowrank_index": np.array(self.lr_index, np.int64).reshape(-1, 8),
                "U": cat(self.Us), "V": cat(self.Vs), "near_index": np.array(self.near_index, np.int64).reshape(-1, 3),
                "near_q": cat(self.near_q, np.int16), "near_mask": cat(self.near_mask, np.uint8),
                "near_scale": cat(self.near_scale), "compress_s": self.seconds, "pid": os.getpid(),
                "sketched": self.sketched, "formed_again": self.formed_again}


def merge_pieces(pieces: list[tuple[np.ndarray, np.ndarray]], tol: float) -> tuple[np.ndarray, np.ndarray]:
    r"""One low-rank block U Vᵀ from its pieces (U_p, V_p) over adjacent column ranges, left to right,
    each V_p with orthonormal columns: merged in pairs up a balanced tree, each merge
    :math:`[U_a\;U_b]\,\mathrm{diag}(V_a, V_b)^T = Q X S Y^T \mathrm{diag}(V_a, V_b)^T` (QR of the stacked
    U, SVD of its R) truncated within ``tol``/(2 L) of the merged block's norm, L the tree's levels.  The
    pieces were compressed within ``tol``/2 each; their errors lie in disjoint columns and add in
    squares, and so do one level's truncations; over L levels the block is within ``tol`` (Frobenius,
    relative).  V stays orthonormal; a block is never wider than the pieces' ranks."""
    level_tol = tol / (2 * max(1, int(np.ceil(np.log2(max(len(pieces), 1))))))
    while len(pieces) > 1:
        out = []
        for q in range(0, len(pieces) - 1, 2):
            (Ua, Va), (Ub, Vb) = pieces[q], pieces[q + 1]
            ka, kb = Ua.shape[1], Ub.shape[1]
            if ka + kb == 0:  # both pieces zero (a block beyond the support's reach)
                out.append((Ua, np.zeros((Va.shape[0] + Vb.shape[0], 0))))
                continue
            Q, R = np.linalg.qr(np.hstack([Ua, Ub]))
            X, S, Yt = np.linalg.svd(R, full_matrices=False)
            norm2 = float(np.sum(S * S))
            tail = np.concatenate([np.cumsum((S * S)[::-1])[::-1], [0.0]])
            r = int(np.argmax(tail <= level_tol * level_tol * norm2))
            V = np.zeros((Va.shape[0] + Vb.shape[0], r))
            V[:Va.shape[0]] = Va @ Yt[:r, :ka].T
            V[Va.shape[0]:] = Vb @ Yt[:r, ka:ka + kb].T
            out.append((Q @ (X[:, :r] * S[:r]), V))
        if len(pieces) % 2:
            out.append(pieces[-1])
        pieces = out
    return pieces[0]


def truncation_tolerance(tol: float) -> float:
    """The tolerance a far block is truncated to (its pieces to half of it, their merge within the other half):
    ``tol`` where its factors are stored in float32 or float64, less :data:`ROUNDING_SHARE` of it where they are
    stored in 16 bits (:func:`far_dtype`), whose rounding takes that share
    (:func:`pmask.runtime.compressed.encode_far`, :func:`far_words`): each block within ``tol`` in all."""
    return tol * (1.0 - ROUNDING_SHARE) if far_dtype(tol) == np.int16 else tol


def far_dtype(tol: float, dtype=np.float64):
    """The far field's factors' dtype as stored: int16 with a scale per column (format 1.8, :func:`far_words`) at
    ``tol`` ≥ :data:`INT16_TOLERANCE`, the truncation leaving the rounding its share (:func:`truncation_tolerance`);
    else float32 where its rounding (2⁻²⁴ ≈ 6e-8 relative, on U and V) is at most 1 % of the tolerance they were
    truncated to (``tol`` ≥ :data:`FLOAT32_TOLERANCE`): eight digits of a float64 below a 1e-5 truncation are
    noise.  The near field stays in ``dtype`` (float64: exact)."""
    if tol >= INT16_TOLERANCE:
        return np.dtype(np.int16)
    return np.dtype(np.float32) if tol >= FLOAT32_TOLERANCE else np.dtype(dtype)


class Concatenated(SlicedArray):
    """One of the artifact's flat arrays (the near field, U, V) as the runs of the tile store's datasets and the
    merged blocks it is the concatenation of, read a slice at a time when the writer stores it: the client never
    holds the compressed Ξ whole (its near field is most of it at organ scale).  ``np.asarray`` reads it
    all (tests).  The tile store must stay on disk until the artifact is written (the run's work folder)."""

    def __init__(self, path: Path, dtype, runs: list):
        self.path, self.dtype = Path(path), np.dtype(dtype)
        self.runs = [r for r in runs if (r[2] - r[1] if isinstance(r[0], str) else len(r[0]))]  # (name, a, b) | array
        sizes = [r[2] - r[1] if isinstance(r[0], str) else len(r[0]) for r in self.runs]
        self.offsets = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)])
        self.shape, self.ndim = (int(self.offsets[-1]),), 1
        self.size, self.nbytes = self.shape[0], self.shape[0] * self.dtype.itemsize

    what = "a Concatenated array"

    def _slice(self, start: int, stop: int) -> np.ndarray:
        import h5py

        out = np.empty(stop - start, self.dtype)
        first = int(np.searchsorted(self.offsets, start, side="right")) - 1
        with h5py.File(self.path, "r") as f:
            for q in range(max(first, 0), len(self.runs)):
                lo, hi = int(self.offsets[q]), int(self.offsets[q + 1])
                if lo >= stop:
                    break
                a, b = max(start, lo), min(stop, hi)
                src = self.runs[q]
                if isinstance(src[0], str):
                    part = f[src[0]][src[1] + a - lo:src[1] + b - lo]
                else:
                    part = src[0][a - lo:b - lo]
                out[a - start:b - start] = part  # (cast to the artifact's dtype: --float32)
        return out


class FixedPointPairs(SlicedArray):
    """A float64 near field's exact pairs (a :class:`Concatenated` of nine values a pair) in fixed point, as format
    1.7 stores them (:func:`pmask.runtime.compressed.pack_exact`, :data:`~pmask.runtime.compressed.PAIR_WORDS`
    uint16 words a pair), packed a slice at a time as the writer reads it."""

    def __init__(self, values: Concatenated):
        self.values = values
        self.dtype = np.dtype(np.uint16)
        self.shape, self.ndim = (len(values) // 9 * PAIR_WORDS,), 1
        self.size, self.nbytes = self.shape[0], self.shape[0] * self.dtype.itemsize

    what = "the fixed-point pairs"

    def _slice(self, start: int, stop: int) -> np.ndarray:
        if stop <= start:
            return np.zeros(0, self.dtype)
        p0, p1 = start // PAIR_WORDS, -(-stop // PAIR_WORDS)  # the whole pairs the slice's words lie in
        return pack_exact(self.values[9 * p0:9 * p1])[start - PAIR_WORDS * p0:stop - PAIR_WORDS * p0]


def _append(ds, values: np.ndarray) -> tuple[int, int]:
    """Append ``values`` to the growing 1-d dataset ``ds`` (cast to its dtype); the run they fill."""
    a = int(ds.shape[0])
    ds.resize((a + len(values),))
    ds[a:] = values
    return a, a + len(values)


def assemble(tree: ClusterTree, store: "TileStore", tol: float = TOLERANCE, dtype=np.float64,
             lowrank_dtype=None) -> tuple[dict, dict]:
    """The artifact's ``greens/hmatrix`` arrays (:mod:`pmask.runtime.compressed`) from the finished tiles
    in ``store``: whole blocks stay where the tiles wrote them, the near field and the factors returned as
    :class:`Concatenated` runs of the store's datasets the writer reads a slice at a time; the pieces of blocks
    wider than a panel are merged (:func:`merge_pieces`, within ``tol``), one block's pieces at a time, and each
    merged block is appended to the store's ``merged`` group as it is made, so the client holds one block's merge
    at a time, not the merged far field (which grows like the far field: by the bench's refit ~1.5 GiB of it at
    200,000 contact vertices).  ``lowrank_dtype`` (:func:`far_dtype`; None: ``dtype``) int16: the factors are
    then rounded to 16 bits after the merges (:func:`far_words`).  Also the tiles' summed timings and the merge's
    and the rounding's."""
    names = sorted(store.tiles(), key=lambda g: tree.start[int(g.split("-")[1])])
    groups = [store.file[g] for g in names]
    index = [g["lowrank_index"][()].reshape(-1, 8) for g in groups]
    whole = [(li[:, 2] == tree.start[li[:, 7]]) & (li[:, 3] == tree.stop[li[:, 7]]) for li in index]
    t0 = time.perf_counter()
    blocks: dict[tuple[int, int, int], list] = {}  # (r0, r1, J) -> [(c0, tile, entry)]
    for t, (li, w) in enumerate(zip(index, whole)):
        for e in np.flatnonzero(~w):
            blocks.setdefault((int(li[e, 0]), int(li[e, 1]), int(li[e, 7])), []).append((int(li[e, 2]), t, e))
    words = np.dtype(lowrank_dtype or dtype) == np.int16  # (format 1.8: the factors rounded from float64 below)
    lowrank_dtype = np.dtype(np.float64 if words else (lowrank_dtype or dtype))
    out_U, out_V = store.merged(lowrank_dtype)
    merged = []  # (r0, r1, c0, c1, k, U's run, V's run) in the store's merged group
    for (r0, r1, j), parts in blocks.items():
        pieces = []
        for _, t, e in sorted(parts):
            _, _, c0, c1, k, uo, vo, _ = (int(x) for x in index[t][e])
            pieces.append((groups[t]["U"][uo:uo + 3 * (r1 - r0) * k].reshape(-1, k),
                           groups[t]["V"][vo:vo + 3 * (c1 - c0) * k].reshape(-1, k)))
        U, V = merge_pieces(pieces, truncation_tolerance(tol))
        merged.append((r0, r1, int(tree.start[j]), int(tree.stop[j]), U.shape[1], _append(out_U, U.ravel()),
                       _append(out_V, V.ravel())))
        del pieces, U, V
    store.file.flush()
    merge_s = time.perf_counter() - t0
    dense_index, lowrank_index, near_index = [], [], []
    runs = {"dense": [], "U": [], "V": [], "near_q": [], "near_mask": [], "near_scale": []}
    at = dict.fromkeys(TileStore.FIELDS, 0)
    times = {"solve_s": 0.0, "compress_s": 0.0, "sketched": 0, "formed_again": 0, "read_bytes": 0.0}

    def run(field, name, a, b):  # the next run of a field, joined to the last when it continues it
        last = runs[field][-1] if runs[field] else None
        if last is not None and last[0] == name and last[2] == a:
            runs[field][-1] = (name, last[1], b)
        else:
            runs[field].append((name, a, b))

    for g, li, w in zip(groups, index, whole):
        di = g["dense_index"][()].reshape(-1, 5)
        di[:, 4] += at["dense"]
        dense_index.append(di)
        ni = g["near_index"][()].reshape(-1, 3)
        if len(ni):  # (pair by pair: every tile's dense blocks are, or none are)
            near_index.append(ni + [at["near_q"], at["near_mask"], at["near_scale"]])
        for field in ("dense", "near_q", "near_mask", "near_scale"):
            n = int(g[field].shape[0])
            run(field, f"{g.name}/{field}", 0, n)
            at[field] += n
        keep = li[w]
        sizes = {"U": 3 * (keep[:, 1] - keep[:, 0]) * keep[:, 4], "V": 3 * (keep[:, 3] - keep[:, 2]) * keep[:, 4]}
        entry = np.empty((len(keep), 7), np.int64)
        entry[:, :5] = keep[:, :5]
        for col, field, src in ((5, "U", keep[:, 5]), (6, "V", keep[:, 6])):
            ends = np.cumsum(sizes[field])
            entry[:, col] = at[field] + ends - sizes[field]
            for a, b in zip(src, src + sizes[field]):
                run(field, f"{g.name}/{field}", int(a), int(b))
            at[field] += int(ends[-1]) if len(ends) else 0
        lowrank_index.append(entry)
        for k in times:
            times[k] += type(times[k])(g.attrs.get(k, 0))  # (a tile of an older run has no sketch or read counts)
    for r0, r1, c0, c1, k, (ua, ub), (va, vb) in merged:
        lowrank_index.append(np.array([[r0, r1, c0, c1, k, at["U"], at["V"]]], np.int64))
        run("U", out_U.name, ua, ub)
        run("V", out_V.name, va, vb)
        at["U"] += ub - ua
        at["V"] += vb - va
    near = Concatenated(store.path, dtype, runs["dense"])
    if near_index and near.dtype == np.float64:  # (format 1.7: the exact pairs in fixed point, 56 bytes where 72)
        near_name, near = "near_exact48", FixedPointPairs(near)
    else:  # (float32 values, --float32, stay as they are: fewer bytes than fixed point)
        near_name = "near_exact" if near_index else "dense"
    out = {"perm": tree.perm.astype(np.int64), "leaves": tree.leaves,
           "dense_index": np.concatenate(dense_index).astype(np.int64) if dense_index else np.zeros((0, 5), np.int64),
           "lowrank_index": np.concatenate(lowrank_index) if lowrank_index else np.zeros((0, 7), np.int64),
           # (pair by pair under another name than whole blocks: a reader of format 1.5 refuses it as missing
           # "dense" where it would misread it)
           near_name: near,
           **{k: Concatenated(store.path, lowrank_dtype, runs[k]) for k in ("U", "V")},
           "near_index": np.concatenate(near_index) if near_index else np.zeros((0, 3), np.int64),
           **{k: Concatenated(store.path, dt, runs[k])
              for k, dt in (("near_q", np.int16), ("near_mask", np.uint8), ("near_scale", np.float64))}}
    times.update({"merge_s": merge_s, "merged_blocks": len(merged),
                  "merged_pieces": int(sum(len(p) for p in blocks.values()))})
    if words:
        t1 = time.perf_counter()
        far, rounding = far_words(store, out["lowrank_index"], out.pop("U"), out.pop("V"), tol)
        out.update(far)
        times.update(rounding, round_s=time.perf_counter() - t1)
    return out, times


def far_words(store: "TileStore", lowrank_index: np.ndarray, U: "Concatenated", V: "Concatenated", tol: float):
    """The far field's factors in 16 bits (format 1.8): each block's U and V, read from the tile store a batch of
    blocks at a time (:data:`READ_BYTES` of them in float64), rounded within the share of ``tol`` the truncation
    left (:func:`truncation_tolerance`, :func:`pmask.runtime.compressed.encode_far`; a block that needs it at rank
    3k, its index updated) and appended to the store's ``far16`` group.  Returns the artifact's ``U16``, ``V16``
    (:class:`Concatenated` runs of that group), ``U_scale``, ``V_scale`` and the new ``lowrank_index`` (ranks and
    offsets), and the rounding's statistics."""
    from pmask.runtime.compressed import encode_far

    t = truncation_tolerance(tol)
    budget = (tol - t) / (1.0 + t)  # ‖B − ŨṼᵀ‖ ≤ t‖B‖ + rounding, ‖B‖ ≥ ‖UVᵀ‖ / (1 + t)
    li = np.asarray(lowrank_index, np.int64).reshape(-1, 7)
    mu, mv = 3 * (li[:, 1] - li[:, 0]) * li[:, 4], 3 * (li[:, 3] - li[:, 2]) * li[:, 4]
    if len(li) and not (np.array_equal(li[:, 5], np.cumsum(mu) - mu) and np.array_equal(li[:, 6], np.cumsum(mv) - mv)):
        raise AssertionError("the far field's factors are not in the index's order")  # (assemble's own layout)
    if "far16" in store.file:
        del store.file["far16"]
    g = store.file.create_group("far16")
    dsU, dsV = (g.create_dataset(k, shape=(0,), maxshape=(None,), dtype=np.int16, chunks=(2**16,)) for k in ("U", "V"))
    out = li.copy()
    su, sv, errs = [], [], []
    wide = 0
    step = max(1, READ_BYTES // 8)
    b = 0
    while b < len(li):
        e, size = b, 0
        while e < len(li) and (e == b or size + mu[e] + mv[e] <= step):
            size += int(mu[e] + mv[e])
            e += 1
        Ub = U[int(li[b, 5]):int(li[e - 1, 5] + mu[e - 1])]
        Vb = V[int(li[b, 6]):int(li[e - 1, 6] + mv[e - 1])]
        qus, qvs = [], []
        for q in range(b, e):
            k = int(li[q, 4])
            u0, v0 = int(li[q, 5] - li[b, 5]), int(li[q, 6] - li[b, 6])
            m, w = 3 * int(li[q, 1] - li[q, 0]), 3 * int(li[q, 3] - li[q, 2])  # (explicit: a block may be of rank 0)
            qu, s_u, qv, s_v, err = encode_far(Ub[u0:u0 + mu[q]].reshape(m, k), Vb[v0:v0 + mv[q]].reshape(w, k), budget)
            out[q, 4] = qu.shape[1]
            wide += qu.shape[1] > k
            qus.append(qu.ravel()), qvs.append(qv.ravel()), su.append(s_u), sv.append(s_v), errs.append(err)
        for ds, parts in ((dsU, qus), (dsV, qvs)):
            _append(ds, np.concatenate(parts) if parts else np.zeros(0, np.int16))
        del Ub, Vb, qus, qvs
        b = e
    nu, nv = 3 * (out[:, 1] - out[:, 0]) * out[:, 4], 3 * (out[:, 3] - out[:, 2]) * out[:, 4]
    out[:, 5], out[:, 6] = np.cumsum(nu) - nu, np.cumsum(nv) - nv
    store.file.flush()
    cat = lambda parts: np.concatenate(parts).astype(np.float32) if parts else np.zeros(0, np.float32)  # noqa: E731
    far = {"lowrank_index": out, "U_scale": cat(su), "V_scale": cat(sv),
           "U16": Concatenated(store.path, np.int16, [(dsU.name, 0, int(dsU.shape[0]))]),
           "V16": Concatenated(store.path, np.int16, [(dsV.name, 0, int(dsV.shape[0]))])}
    return far, {"far_rank3k_blocks": int(wide), "far_rounding_max": float(max(errs, default=0.0)),
                 "far_values": int(mu.sum() + mv.sum())}


# ------------------------------------------------------------------------------- the tile store
class TileStore:
    """Finished tiles in an HDF5 file of the run's work folder (one group per tile, written as it
    arrives; a group is complete once its ``done`` attribute is set), so that neither a lost worker
    nor a crashed client loses one."""

    FIELDS = ("dense_index", "dense", "lowrank_index", "U", "V", "near_index", "near_q", "near_mask", "near_scale")

    def __init__(self, path: Path, key: str):
        import h5py

        self.path = Path(path)
        self.file = h5py.File(self.path, "a")
        if self.file.attrs.get("key") != key:  # another factor or tolerance: nothing to reuse
            for g in list(self.file):
                del self.file[g]
            self.file.attrs["key"] = key
        for g in [g for g in self.file if not self.file[g].attrs.get("done")]:
            del self.file[g]  # written halfway when the client stopped

    def tiles(self) -> list[str]:
        """The finished tiles' groups (``tile-C``, C the panel's cluster)."""
        return [g for g in self.file if g.startswith("tile-")]

    def done(self) -> set[int]:
        return {int(g.split("-")[1]) for g in self.tiles()}

    def merged(self, dtype) -> tuple:
        """The ``merged`` group's U and V (empty, growing: :func:`assemble` appends each block it merges),
        made afresh (an assembly that stopped halfway left its own, which the run's start deletes too)."""
        if "merged" in self.file:
            del self.file["merged"]
        g = self.file.create_group("merged")
        return tuple(g.create_dataset(k, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(2**16,))
                     for k in ("U", "V"))

    def put(self, t: dict) -> None:
        g = self.file.create_group(f"tile-{t['column']}")
        for k in self.FIELDS:
            g.create_dataset(k, data=t[k])
        for k in ("solve_s", "compress_s", "pid", "sketched", "formed_again", "read_bytes", "pass_tiles"):
            g.attrs[k] = t[k]
        g.attrs["done"] = True
        self.file.flush()

    def close(self) -> None:
        self.file.close()


# ------------------------------------------------------------------------------- the cluster
def parse_memory(text) -> int:
    """A worker's memory limit in bytes ('4G', '512M', a number: :func:`pmask.precompute.greens.parse_bytes`)."""
    from pmask.precompute.greens import parse_bytes

    return parse_bytes(text, "--worker-memory")


def check_tolerance(tol) -> float:
    try:
        t = float(tol)
    except (TypeError, ValueError):
        t = float("nan")
    if not 0.0 < t < 1.0:
        raise InputError(f"--compress tolerance must lie in (0, 1) (relative error per far-field block; "
                         f"default {TOLERANCE:g}), got {tol!r}")
    return t


def connect(scheduler: str | None, workers: int | None, memory_limit: int | None, timeout: float = 10.0):
    """A dask.distributed Client: to ``scheduler`` (an address) or to a new LocalCluster of ``workers``
    single-threaded worker processes (default: one per core) with ``memory_limit`` bytes each
    (default: dask's share of this machine).  One line if the scheduler cannot be reached."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            refused(scheduler)  # nothing listening: said at once, where Client retries for ``timeout``
            with dask.config.set({"distributed.comm.timeouts.connect": f"{timeout}s"}):
                return Client(scheduler, timeout=f"{timeout}s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler!r} ({type(exc).__name__}: "
                             f"{str(exc).splitlines()[0] if str(exc) else 'no answer'}); start it with "
                             "`dask scheduler` and its workers with `dask worker ADDRESS`, or leave out "
                             "--scheduler to run on this machine") from None
    n = workers or os.cpu_count() or 1
    for name in ("distributed", "distributed.scheduler", "distributed.nanny", "distributed.worker"):
        logging.getLogger(name).setLevel(logging.WARNING)  # not pmask's INFO lines: a worker's start is no news
    # no dashboard: dashboard_address=None still binds the scheduler's HTTP routes to port 8787 ("Port 8787 is
    # already in use" beside another cluster); a free local port and dashboard=False start neither
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0",
                           scheduler_kwargs={"dashboard": False},
                           memory_limit=memory_limit if memory_limit else "auto", silence_logs=logging.ERROR)
    return Client(cluster)


def refused(scheduler: str, timeout: float = 1.0) -> None:
    """ConnectionRefusedError when nothing listens at a tcp:// scheduler address (a typo'd port, a scheduler
    not started): the host answers that at once, where dask's Client retries until its timeout (10 s by hand
    for tcp://127.0.0.1:9); ValueError for a port out of range.  Any other outcome (a connection, no answer
    within ``timeout``, another protocol, an address this does not parse) is left to the Client."""
    import socket
    from urllib.parse import urlsplit

    url = urlsplit(scheduler if "://" in scheduler else f"tcp://{scheduler}")
    host, port = url.hostname, url.port  # ValueError for a port that is no port (99999, "x"): said at once
    if url.scheme != "tcp" or not host or not port:
        return
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except ConnectionRefusedError as exc:
        raise ConnectionRefusedError(f"nothing listens at {host}:{port}") from exc
    except OSError:
        return


def check_scheduler(client, scheduler: str | None, done: int, total: int, store: Path,
                    wait: float | None = None) -> None:
    """One line, instead of a traceback, when the client has lost its scheduler (a killed `dask scheduler`,
    a dropped network) and it has not come back within ``wait`` seconds (:data:`SCHEDULER_WAIT`): how far the
    run got, and that a rerun resumes from what the work folder keeps (the finished tiles and W's store)."""
    until = time.monotonic() + (SCHEDULER_WAIT if wait is None else wait)
    while client.status != "running" and time.monotonic() < until:
        time.sleep(0.1)  # the client reconnects by itself when the scheduler is back soon
    if client.status != "running":
        raise ResourceError(f"lost the Dask scheduler ({scheduler or 'local cluster'}) after {done} of {total} tiles; "
                            f"the finished tiles and W's store are kept in {Path(store).parent}: run the same command "
                            "again to resume (with --scheduler of a running scheduler, or without it on this machine)")


def tile_bytes(held: float, n_contact: int, panel: int = PANEL, copies: int = 1, made: float = 0.0) -> float:
    """A worker's memory for one tile: the panel (3n x 3·panel doubles, ``copies`` of it), one slice of a product
    (at most :data:`READ_BYTES`, :meth:`SweepStore.sorted_columns`), ``held`` bytes (:func:`source_bytes`: what
    the panel's columns are computed from) and ``made`` (:func:`output_bytes`, the largest over the tiles; not
    known before the partition)."""
    columns = 8.0 * (3 * n_contact) * (3 * panel)
    return copies * columns + min(float(READ_BYTES), columns) + held + made


def output_bytes(tree: ClusterTree, column: int, blocks, chunk: float = READ_BYTES) -> float:
    """What a tile makes beside its panel (bytes): its dense blocks twice (each block, then the tile's array of
    them) and its largest far block four times (the block's copy, then :func:`low_rank`'s products BΩ, Q and QᵀB,
    each smaller than the block where it is compressed), and its sketches (:func:`sketch_bytes`); less the rows
    of the panel it does not form (:func:`tile_bytes` counts all 3n): those of no block it forms, but for the
    sketched blocks' samples.  ``chunk``: the largest chunk of W's blocks a tile reads (:func:`source_bytes`)."""
    c0, c1 = int(tree.start[column]), int(tree.stop[column])
    area = [(72.0 * tree.size(i) * (min(int(tree.stop[j]), c1) - max(int(tree.start[j]), c0)), far)
            for i, j, far in blocks]
    made = 2 * sum(a for a, far in area if not far) + 4 * max((a for a, far in area if far), default=0.0)
    formed, sampled = np.zeros(3 * len(tree.perm), bool), 0
    for i, j, far in blocks:
        if far and sketches(tree, i, j, c0, c1):
            sampled += SKETCH_SAMPLES
        else:
            formed[3 * int(tree.start[i]):3 * int(tree.stop[i])] = True
    unformed = max(float(np.sum(~formed)) - sampled, 0.0)
    return made + sketch_bytes(tree, column, blocks, chunk) - 8.0 * unformed * 3 * (c1 - c0)


def kept_bytes(tree: ClusterTree, column: int, blocks) -> float:
    """What a tile of a pass (:func:`tiles`) holds while another tile of the pass is worked on (bytes): its
    formed rows (D: the rows of the blocks it forms and its sketched blocks' samples, by its columns), its
    indices over the rows it asks (eight numbers a row), and for each of its groups Ω (twice), a mask over the
    asked rows, and per row of the group its range sketch and three indices (:class:`SketchGroup`).  Not its
    results: the route's passes write each tile as it is compressed (:func:`tiles` with a folder), so a tile's
    results are held only while it is the one worked on, which :func:`tile_bytes` counts (``made``); where the
    D and sketches of a pass's tiles all exist, at the end of its pass over W, none is compressed yet.
    (Counting each tile's results as well, and index arrays over all the asked rows for each group, as this did
    before, counted 18 of the 43 GiB of all the tiles at 51,519 vertices and cut them into 22 passes; the bench
    page's organ row gives the passes now.)"""
    c0, c1 = int(tree.start[column]), int(tree.stop[column])
    width = SKETCH_RANK + SKETCH_TESTS
    upto = max((int(tree.stop[i]) for i, _, _ in blocks), default=0)
    formed, sampled = np.zeros(3 * upto, bool), 0
    groups: dict[tuple[int, int], float] = {}
    for i, j, far in blocks:
        rows, cols = 3 * tree.size(i), 3 * (min(int(tree.stop[j]), c1) - max(int(tree.start[j]), c0))
        if far and sketches(tree, i, j, c0, c1):
            sampled += SKETCH_SAMPLES
            key = (int(tree.start[j]), int(tree.stop[j]))
            groups[key] = groups.get(key, 2.0 * cols * width + 3 * upto / 4) + rows * (width + 3)
        else:
            formed[3 * int(tree.start[i]):3 * int(tree.stop[i])] = True
    d_rows = float(np.sum(formed)) + sampled
    return 8.0 * (d_rows * 3 * (c1 - c0) + 8 * 3 * upto + sum(groups.values()))


def pass_bytes(tree: ClusterTree, columns: list[int], plans: list, held: float, n_contact: int, panel: int,
               widest: int) -> float:
    """A worker's memory for a pass of tiles ``columns`` (:func:`tiles`): every tile's :func:`kept_bytes` and
    its rows of the supernode block being read (``widest``: the widest supernode's columns), and the largest
    tile's own work as one tile alone counts it (:func:`tile_bytes`: its panel, a chunk, its outputs)."""
    return _pass_total([_pass_part(tree, c, b, held, n_contact, panel, widest) for c, b in zip(columns, plans)])


def pass_budget(limits: list[int | None], threads: list[int]) -> float:
    """What a pass may hold (bytes, by :func:`pass_bytes`): :data:`PASS_SHARE` of the smallest memory limit per
    thread among the workers that have one (:data:`UNLIMITED_PASS_BYTES` where none has), at most
    :data:`PASS_BYTES` where that is set."""
    shares = [PASS_SHARE * m / max(t, 1) for m, t in zip(limits, threads) if m]
    budget = min(shares) if shares else float(UNLIMITED_PASS_BYTES)
    return budget if PASS_BYTES is None else min(budget, float(PASS_BYTES))


def _pass_total(parts) -> float:
    return max((one for one, _ in parts), default=0.0) + sum(kept for _, kept in parts)


def _pass_part(tree, column, blocks, held, n_contact, panel, widest) -> tuple[float, float]:
    return (tile_bytes(held, n_contact, panel, 1, output_bytes(tree, column, blocks, held)),
            kept_bytes(tree, column, blocks) + 8.0 * 3 * tree.size(column) * widest)


def tile_work(tree: ClusterTree, column: int, blocks) -> float:
    """A tile's share of a pass's products (a proxy, in numbers a supernode column multiplies): its formed rows
    times its columns and its sketched blocks' rows times the sketch's width.  Measured by hand at 20,427
    vertices, a tile alone took ~0.9 s (its read of W) plus a time in proportion to this (within ±25 %)."""
    c0, c1 = int(tree.start[column]), int(tree.stop[column])
    upto = max((int(tree.stop[i]) for i, _, _ in blocks), default=0)
    formed, sketched = np.zeros(3 * upto, bool), 0
    for i, j, far in blocks:
        if far and sketches(tree, i, j, c0, c1):
            sketched += 3 * tree.size(i) + SKETCH_SAMPLES  # (its samples are formed rows)
        else:
            formed[3 * int(tree.start[i]):3 * int(tree.stop[i])] = True
    return float(np.sum(formed)) * 3 * (c1 - c0) + sketched * (SKETCH_RANK + SKETCH_TESTS)


#: passes per worker thread the tiles are cut into where memory allows fewer (:func:`passes`), the largest handed out
#: first.  Each pass reads most of W (its sketched rows are most of 3n), and there are at least this many passes a
#: worker thread, so W's reads grow with the workers: one a thread reads W about once per thread and once more, at
#: the cost of the balance that three gave, whose last passes evened out the workers' loads (the bench page's
#: passes_ab compares the two in one run: W's reads and the tiles' times).  Where memory sets more passes than the
#: threads (51,519 vertices on 2 local workers) it makes no difference
PASSES_PER_THREAD = 1


def passes(tree: ClusterTree, columns: list[int], plans: dict, budget: float, held: float, n_contact: int,
           panel: int, widest: int, threads: int, estimates: dict | None = None) -> list[list[int]]:
    """The tiles ``columns`` (in position order) cut into passes (:func:`tiles`): runs of neighbouring panels
    (their columns' paths share the most of W), each about an equal share of the work (:func:`tile_work`,
    :data:`PASSES_PER_THREAD` passes per worker thread) and within ``budget`` (:func:`pass_bytes`; a tile alone
    even above it: :func:`check_worker_memory` refuses that).  A pass ends at the tile that would take it more
    than half that tile's work past its share.  ``estimates``: :func:`tile_estimates` of these tiles, when the
    caller has them."""
    est = estimates or tile_estimates(tree, columns, plans, held, n_contact, panel, widest)
    share = sum(est[c][0] for c in columns) / max(1, PASSES_PER_THREAD * max(threads, 1))
    out, run, one, kept, done = [], [], 0.0, 0.0, 0.0
    for c in columns:
        w, (o, k) = est[c]
        if run and (done + w / 2 > share or max(one, o) + kept + k > budget):
            out.append(run)
            run, one, kept, done = [], 0.0, 0.0, 0.0
        run.append(c)
        one, kept, done = max(one, o), kept + k, done + w
    return out + ([run] if run else [])


def tile_estimates(tree: ClusterTree, columns: list[int], plans: dict, held: float, n_contact: int, panel: int,
                   widest: int) -> dict[int, tuple[float, tuple[float, float]]]:
    """Each tile's :func:`tile_work` and its two parts of a pass's memory (alone, and kept while the others are
    worked on: :func:`pass_bytes`), worked out once: the client cuts the passes, checks them and ranks them
    from these."""
    return {c: (tile_work(tree, c, plans[c]), _pass_part(tree, c, plans[c], held, n_contact, panel, widest))
            for c in columns}


def sketch_bytes(tree: ClusterTree, column: int, blocks, chunk: float = READ_BYTES) -> float:
    """What a tile's sketches take (bytes, :class:`SketchGroup`): for each group Ω and its copy scaled by the
    areas, its masks over the asked rows (a byte a row: one, and a copy in W's order), and per row of the group its
    range sketch Y and four indices (its position; Y's rows sorted, where each is, and their sort); a chunk's
    rows of a group copied for their product (at most ``chunk``); and the largest block's work
    (:func:`from_sketches`: its Y, its SVD, the test's product; X and its SVD)."""
    c0, c1 = int(tree.start[column]), int(tree.stop[column])
    width, total, one = SKETCH_RANK + SKETCH_TESTS, 0.0, 0.0
    groups: dict[tuple[int, int], list] = {}
    for i, j, far in blocks:
        if far and sketches(tree, i, j, c0, c1):
            groups.setdefault((int(tree.start[j]), int(tree.stop[j])), []).append(3 * tree.size(i))
    for (j0, j1), rows in groups.items():
        cols, n_sk = 3 * (min(j1, c1) - max(j0, c0)), float(sum(rows))
        total += 2 * cols * width + 3 * len(tree.perm) / 4 + n_sk * (width + 4)
        one = max(one, max(4 * m * width + 4 * SKETCH_RANK * cols for m in rows))
    return 8.0 * (total + one) + (float(chunk) if groups else 0.0)


def source_bytes(source: SweepStore) -> float:
    """A worker's memory for the columns' source: one chunk of W's blocks, and with a load (P2) the panel's
    rows of W_B's block beside it (at most as large)."""
    return float((2 if source.load else 1) * min(8 * source.largest, READ_BYTES))


def check_worker_memory(limits: list[int | None], need: float, threads: list[int] | None = None) -> None:
    """Refuse, before the tiles start, workers whose memory limit is below one tile per thread (a worker
    runs as many tiles at once as it has threads: `dask worker --nthreads 4 --memory-limit 1G` would run
    four 400 MiB tiles in 1 GiB, be restarted by its nanny and lose them)."""
    threads = threads or [1] * len(limits)
    small = [(m, t) for m, t in zip(limits, threads) if m and m < need * max(t, 1)]
    if small:
        m, t = min(small)
        per = f"{t} threads, so {t} tiles at once" if t > 1 else "one tile at a time"
        raise ResourceError(f"{len(small)} of {len(limits)} Dask workers have a memory limit ({m / 2**20:.0f} MiB) "
                            f"below what they would run ({per}, {need / 2**20:.0f} MiB each: the factor's or W's "
                            "share, a panel of Ξ and the work arrays); give them more (--worker-memory), fewer "
                            "threads (dask worker --nthreads 1), or use fewer, larger workers")


PHASE_MARGIN = 1.15  # the sweep's model (sweep_bytes) lands within 5 % of tracemalloc's peak on the tests' kidney,
# the assembly's (assembly_bytes) above it (an upper bound); the rest is the allocator's and the interpreter's share


def check_phase_memory(phase: str, need: float, advice: str) -> None:
    """Refuse, before it starts, a phase of the compressed route whose peak (with :data:`PHASE_MARGIN`)
    exceeds what this machine has available now (what is held already, the factor among it, is not
    available): one line naming the phase, its need and what to do."""
    from pmask.precompute.greens import available_memory

    avail = available_memory()
    if avail is not None and PHASE_MARGIN * need > avail:
        raise ResourceError(f"the compressed route's {phase} needs ~{need / 2**30:.2f} GiB at its peak, more than "
                            f"the {avail / 2**30:.2f} GiB this machine has available now; {advice}")


def assembly_bytes(tree: ClusterTree, store: "TileStore", lowrank_dtype=np.float64) -> int:
    """What :func:`assemble` holds at its peak (bytes), from the finished tiles' indices (nothing else read): the
    largest block's merge in float64 four times its pieces (the pieces, their stacked U, its Q and the merged
    factors; a merged block goes to the tile store as it is made) and the indices; the near field, the tiles'
    whole blocks and the merged ones stay in the tile store (:class:`Concatenated`), and the writer adds
    :data:`WRITE_BYTES`; after the merges, the 16-bit rounding (:func:`far_words`) holds a batch of
    :data:`READ_BYTES` of factors in float64 and its words (``lowrank_dtype`` int16: the only dtype of the far
    field's that changes what is held)."""
    blocks = factors = 0
    merging: dict = {}  # (r0, r1, J) -> its pieces' numbers
    for name in store.tiles():
        g = store.file[name]
        li = g["lowrank_index"][()].reshape(-1, 8)
        size = 3 * ((li[:, 1] - li[:, 0]) + (li[:, 3] - li[:, 2])) * li[:, 4]
        factors += int(size.sum())
        part = ~((li[:, 2] == tree.start[li[:, 7]]) & (li[:, 3] == tree.stop[li[:, 7]]))
        for e in np.flatnonzero(part):
            key = (int(li[e, 0]), int(li[e, 1]), int(li[e, 7]))
            merging[key] = merging.get(key, 0) + int(size[e])
        blocks += len(li) + int(g["dense_index"].shape[0])
    rounding = 2 * min(8 * factors, READ_BYTES) if np.dtype(lowrank_dtype) == np.int16 else 0  # (float64, words)
    return max(4 * 8 * max(merging.values(), default=0), rounding) + 8 * 8 * blocks


#: what the writer holds while it stores a compressed Ξ read from the tile store (:class:`Concatenated`): a block
#: of rows as read, as cast and as hashed (:data:`pmask.runtime.artifact.READ_BLOCK_BYTES` each)
WRITE_BYTES = 3 * READ_BLOCK_BYTES


def factor_bytes(factor) -> int:
    """Bytes a worker holds for the solves: the factor's arrays."""
    return int(sum(np.asarray(v).nbytes for v in factor.L.values()))


def factor_phase_bytes(factor: float) -> float:
    """The factor's worker at its peak (bytes), from the factor's size: the factorisation's transients
    (the stiffness, CHOLMOD's workspace and the factor's arrays: 1.5x the factor; measured 9.86 GiB for P2's
    6.4 GiB factor at 20,427 contact vertices, whose estimate is 7.3 GiB), or the factor beside W's sweep
    (:data:`SWEEP_BUDGET` at most, the factor's size where that is less), whichever is larger: they are not
    held at once."""
    return max(1.5 * factor, factor + min(SWEEP_BUDGET, factor))


def factor_workers(info: list[dict], need: float) -> list[str] | None:
    """The Dask workers (addresses, from ``scheduler_info``) whose memory limit holds the factor's phase
    (``need`` bytes; none asked: any worker, None), the task placed on one of them; refused in one line when
    none does, before anything is factorised (a worker past its limit is restarted by its nanny and the
    factorisation lost)."""
    if not need:
        return None
    fit = [w["id"] for w in info if not w.get("memory_limit") or w["memory_limit"] >= need]
    if not fit:
        largest = max(int(w.get("memory_limit") or 0) for w in info) if info else 0
        raise ResourceError(f"the factor's worker needs ~{need / 2**30:.1f} GiB at its peak (the factorisation, then "
                            f"W's sweep), more than any Dask worker's memory limit (the largest "
                            f"{largest / 2**30:.1f} GiB): run fewer local workers (--workers 1 gives one all of "
                            "this machine's share), give them more (--worker-memory), or use a cluster with a "
                            "larger worker")
    return fit


def _sweep_on_worker(client, source, path: Path, key: str, scheduler: str | None, store: Path, done: int,
                     total: int, workers: list[str] | None = None) -> dict:
    """:func:`factor_and_sweep` as a task on ``client``'s cluster; a refusal or a user's error raised there is
    raised here as it was (one line); a worker lost meanwhile is one line too (what is kept, what to do)."""
    from concurrent.futures import CancelledError

    from distributed import KilledWorker

    fut = None
    try:  # the job (its mesh) or the factor sent as data, not in the task graph (dask warns of a large graph)
        fut = client.submit(factor_and_sweep, client.scatter(source, hash=False, workers=workers), str(path), key,
                            key=f"pmask-sweep-{key[:16]}", pure=False, workers=workers, allow_other_workers=False)
        return fut.result()
    except (KilledWorker, CancelledError, OSError) as exc:
        check_scheduler(client, scheduler, done, total, store)  # one line when the scheduler is gone
        if isinstance(exc, OSError):
            raise
        # the worker died under the task (KilledWorker after dask's retries) or took the scattered job with it
        raise ResourceError("the Dask worker that factorised and swept W was lost (killed, or past its memory limit: "
                            "the factor and the sweep's batch must fit in one worker's --worker-memory); run "
                            "again with more memory per worker or fewer workers (--workers)") from None
    finally:
        if fut is not None:
            fut.release()


def _shares_work_folder(w_path: str, folder: str) -> bool:
    """Whether this worker reads W's store and writes to the passes' folder (the run's work folder)."""
    return os.path.exists(w_path) and os.access(folder, os.W_OK)


def compressed_greens(factor, points: np.ndarray, r_max: float, *, tol: float = TOLERANCE, store: Path,
                      key: str, scheduler: str | None = None, workers: int | None = None,
                      memory_limit: int | None = None, panel: int | None = None, client=None, dtype=np.float64,
                      on_tile=None, dense=None) -> tuple[dict, dict]:
    """Ξ compressed (the artifact's ``greens/hmatrix`` arrays) and statistics, from ``factor`` for the
    contact vertices at ``points``; the tiles run as Dask tasks (module docstring).  ``store``: the tile
    store's path, reused when ``key`` (factor and parameters) matches; ``client``: an open Client to use
    instead of connecting; ``on_tile(tile)``: called with each finished tile (tests, progress).  ``dense()``: the
    dense Ξ, where it fits on this machine (the pipeline's choice, ``compress_from_dense`` in
    :mod:`pmask.pipeline.stages`), called when tiles are left to compute: they ask it for their rows and sketches
    (:class:`DenseSource`) in this process, with no Dask and no W, the same blocks to round-off.  The near field
    and the factors come back as :class:`Concatenated` runs of the tile store, read when the writer stores them
    (so ``store`` must stay until then)."""
    from distributed import as_completed

    tol = check_tolerance(tol)
    store = Path(store)
    panel = panel or panel_size(len(points))
    tree = cluster_tree(points)
    cols = panels(tree, panel)
    job = isinstance(factor, FactorJob)
    symmetric = factor.element == "P1" if job else is_symmetric(factor)
    plan = {c: [b for b in partition(tree, c, r_max) if not symmetric or tree.start[b[0]] <= tree.start[b[1]]]
            for c in cols}  # symmetric: the blocks on and above the diagonal (the reader transposes the rest)
    ts = TileStore(store, f"{key}|{TILE_LAYOUT}|symmetric={symmetric}")
    todo = [c for c in cols if c not in ts.done()]
    stats = {"tiles": len(cols), "tiles_reused": len(cols) - len(todo), "leaf": LEAF, "eta": ETA, "panel": panel,
             "tolerance": tol, "scheduler": scheduler or "local", "symmetric": symmetric}
    t0 = time.perf_counter()
    own = client is None
    w_path = store.with_name(f"W-{store.stem}.bin")
    passed = store.with_name(f"{store.stem}-passes")  # the passes' tiles on their way to the tile store
    source = factor
    report = None  # what factor_and_sweep reported
    try:
        try:
            if todo and dense is not None:  # the dense Ξ at hand: its tiles one after the other here, no W
                xi = DenseSource(dense())
                near = (np.asarray(points, float)[tree.perm], float(r_max))
                stats.update({"route": "dense Xi", "workers": 0, "scheduler": None})
                for c in todo:
                    t = tiles(xi, tree, [c], [plan[c]], tol, near, True)[0]
                    ts.put(t)
                    if on_tile is not None:
                        on_tile(t)
                    del t
                del xi  # (the dense Ξ goes before the assembly)
                log.info("compressed Ξ from the dense Ξ: %d tiles, %.1f s", len(todo), time.perf_counter() - t0)
            elif todo:
                client = client or connect(scheduler, workers, memory_limit)
                info = list(client.scheduler_info()["workers"].values())
                limits = [w.get("memory_limit") for w in info]

                def check_tiles(held, copies):  # refuse workers too small for their tiles, before they start
                    made = max((output_bytes(tree, c, plan[c], held) for c in todo), default=0.0)  # (held ≥ a chunk)
                    stats["tile_bytes"] = tile_bytes(held, len(points), panel, copies, made)
                    check_worker_memory(limits, stats["tile_bytes"], [int(w.get("nthreads") or 1) for w in info])

                check_tiles(float(READ_BYTES), 1)  # W's chunk is at most this (its size is known once swept)
                t1 = time.perf_counter()
                reused = sweep_reusable(w_path, key)
                where = factor_workers(info, factor.need) if job and not reused else None
                report = _sweep_on_worker(client, factor, w_path, key, scheduler, store, len(cols) - len(todo),
                                          len(cols), where)
                source = SweepStore(w_path)  # W once, on a worker; the tiles read it (module docstring)
                if not reused:
                    stats["sweep_peak_bytes"] = int(source.index["peak_bytes"])
                swept = report["timings"].get("sweep", time.perf_counter() - t1)  # (not the factorisation)
                stats.update({"route": "W store", "sweep_s": swept, "W_reused": reused,
                              "W_bytes": int(w_path.stat().st_size), "sweep_flops": float(source.index["flops"]),
                              "gram_flops": float(source.index["gram_flops"]),
                              "sweep_batches": int(source.index.get("batches", 1)),
                              "sweep_pid": report["pid"], "sweep_host": report["host"],
                              "sweep_blas_threads": report["blas_threads"]})
                log.info("factor and W's sweep on a worker (%s, pid %d, %d BLAS threads): %.1f s",
                         report["host"], report["pid"], report["blas_threads"], report["seconds"])
                check_tiles(source_bytes(source), 1)
                stats["workers"] = len(limits)
                passed.mkdir(exist_ok=True)  # each pass's tiles, a file each, until the client has stored them
                for old in passed.glob("tile-*.npz"):  # a stopped run's (its tiles not stored: run again)
                    old.unlink()
                seen = client.run(_shares_work_folder, str(source.path), str(passed))
                if not all(seen.values()):
                    raise InputError(f"{sum(not v for v in seen.values())} of {len(seen)} Dask workers cannot read "
                                     f"{source.path} (W's store for the tiles) or write to {passed}: with --scheduler "
                                     "the artifact's work folder (.work next to -o) must be on a filesystem every "
                                     "worker mounts")
                threads = [int(w.get("nthreads") or 1) for w in info]
                held, widest = source_bytes(source), int(source.index["ncol"].max(initial=0))
                budget = pass_budget(limits, threads)
                est = tile_estimates(tree, todo, plan, held, len(points), panel, widest)
                groups = passes(tree, todo, plan, budget, held, len(points), panel, widest, sum(threads), est)
                stats["passes"] = len(groups)
                stats["pass_bytes"] = max(_pass_total([est[c][1] for c in g]) for g in groups)
                check_worker_memory(limits, stats["pass_bytes"], threads)
                attempts = {g[0]: 0 for g in groups}
                done = len(cols) - len(todo)
                fac = near = None
                while groups:
                    check_scheduler(client, scheduler, done, len(cols), store)
                    if fac is None or fac.status != "finished":
                        fac = client.scatter(source, broadcast=True, hash=False)
                    if near is None or near.status != "finished":  # (a lost worker may take it with it)
                        near = client.scatter((np.asarray(points, float)[tree.perm], float(r_max)), broadcast=True,
                                              hash=False)
                    size = {g[0]: sum(est[c][0] for c in g) for g in groups}
                    rank = {f: r for r, f in enumerate(sorted(size, key=size.get))}  # the largest pass first
                    futures = {client.submit(tiles, fac, tree, g, [plan[c] for c in g], tol, near, True, passed,
                                             key=f"pmask-tiles-{'.'.join(map(str, g))}-{attempts[g[0]]}",
                                             pure=False, priority=rank[g[0]]): g for g in groups}
                    lost = []
                    for fut in as_completed(futures):
                        g = futures[fut]
                        try:
                            made = fut.result()
                        except Exception as exc:  # a lost worker took every copy of the inputs, or the task failed
                            check_scheduler(client, scheduler, done, len(cols), store)
                            attempts[g[0]] += 1
                            if attempts[g[0]] >= TILE_ATTEMPTS or isinstance(exc, (MemoryError, InputError)):
                                raise
                            log.warning("the pass of tiles %s failed on its worker (%s: %s); running it again",
                                        ", ".join(map(str, g)), type(exc).__name__, exc)
                            lost.append(g)
                            continue
                        fut.release()  # the result is in the store: a lost worker must not make dask recompute it
                        for written in made:  # one tile's arrays at a time in the client
                            t = read_tile(written)
                            ts.put(t)
                            Path(written["path"]).unlink()
                            done += 1
                            if done * 10 // len(cols) > (done - 1) * 10 // len(cols):
                                log.info("compressed Ξ: %d of %d tiles, %.0f s", done, len(cols),
                                         time.perf_counter() - t0)
                            if on_tile is not None:
                                on_tile(t)
                            t = None
                        del made
                    groups = lost
            for p in (w_path, SweepStore.index_path(w_path)):  # every tile is in the store: W is not needed again
                p.unlink(missing_ok=True)
            if passed.is_dir():
                for left in passed.glob("tile-*"):  # (none: each is removed once stored)
                    left.unlink()
                passed.rmdir()
        finally:  # the workers go before the assembly
            if own and client is not None:
                cluster = getattr(client, "cluster", None)
                client.close()
                if cluster is not None:
                    cluster.close()
        stats["assembly_bytes"] = assembly_bytes(tree, ts, far_dtype(tol, dtype))
        check_phase_memory("assembly", stats["assembly_bytes"] + WRITE_BYTES,
                           f"every tile is kept in {store}: run again where more memory is free (the tiles are "
                           "reused), or with a larger tolerance (--compress TOL)")
        out, times = assemble(tree, ts, tol, dtype, far_dtype(tol, dtype))
        if job:  # the factor's scale and stats as the worker reported them (every tile stored: its checkpoint's)
            report = report or factor.summary()
            factor.stats, factor.timings, factor.resumed = report["stats"], report["timings"], report["resumed"]
        scale = factor.scale if report is None else report["scale"]
        out["scale"] = scale[0::3].astype(np.float64) if symmetric else np.zeros(0)
    finally:
        ts.close()
    stats.update({"seconds": time.perf_counter() - t0, **times,
                  "dense_blocks": len(out["dense_index"]), "lowrank_blocks": len(out["lowrank_index"]),
                  "stored_bytes": int(sum(out[k].nbytes for k in ("dense", "near_exact", "near_exact48", "U", "V",
                                                                 "U16", "V16", "U_scale", "V_scale", "near_q",
                                                                 "near_mask", "near_scale") if k in out)),
                  "dense_bytes": int(8 * (3 * len(points)) ** 2),
                  "max_rank": int(out["lowrank_index"][:, 4].max()) if len(out["lowrank_index"]) else 0})
    stats["ratio"] = stats["dense_bytes"] / max(stats["stored_bytes"], 1)
    if stats.get("W_bytes"):  # how many times the tiles read W's store, all their passes together
        stats["W_reads"] = stats["read_bytes"] / stats["W_bytes"]
    log.info("compressed Ξ: %d tiles (%d reused), %d dense + %d low-rank blocks, %.1fx smaller than dense, %.1f s",
             stats["tiles"], stats["tiles_reused"], stats["dense_blocks"], stats["lowrank_blocks"], stats["ratio"],
             stats["seconds"])
    return out, stats
