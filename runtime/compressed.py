r"""Ξ in compressed form: the near field exact, the far field as low-rank blocks over a cluster tree.

Ξ of an organ at haptic resolution does not fit one machine as a dense array ((3n)² numbers: 1.1 GiB at
3,882 contact vertices, 29 GiB at 20,000).  Not every part of it is needed in the same form:

* the vertex stiffness :math:`K_i = (\sum_j \rho^i_j \Xi_{ij})^{-1}` (eq. 12) reads only the blocks
  within the mask radius, :math:`|x_i - x_j| \le r \le r_{max}`: the **near field**, stored exactly;
* the deformation (eq. 16) and the coupling of several contacts read blocks between distant vertices:
  the **far field**, smooth between well-separated parts of the surface and numerically of low rank.

The contact vertices are ordered by a cluster tree (recursive bisection of their positions; ``perm``
maps a position in that order to the contact index).  Ξ in that order is partitioned into rectangular
blocks over pairs of tree clusters (I, J) (a hierarchical matrix): a pair with no vertex of I within
``r_max`` of a vertex of J, whose bounding boxes are farther apart than the larger box's diagonal / η, is
*admissible* and stored as :math:`U V^T` with :math:`\|\Xi_{IJ} - U V^T\|_F \le \varepsilon \|\Xi_{IJ}\|_F`
(ε: the artifact's ``tolerance``, default 1e-4); every other block (all of the near field among them) is stored
densely, every pair within r_max as the dense route computes it to round-off (format 1.7: in 48-bit fixed point,
within 1.4e-14 of the pair's largest magnitude; format 1.6: the others in 16 bits, below).  Every block's rows
and columns are whole leaf clusters, so a block is found from two leaf indices (:meth:`CompressedXi.owner`).
Built by :mod:`pmask.precompute.compress`.

Layout in the artifact (``/greens/hmatrix``; positions are in cluster order, in vertices)::

    perm           (n,)     contact index of each position
    leaves         (L+1,)   first position of each leaf cluster, and n
    dense_index    (nd, 5)  r0, r1, c0, c1, offset: block rows 3 r0..3 r1, columns 3 c0..3 c1, values at
                            ``dense[offset:]`` (row-major; with ``near_index`` its exact pairs', below)
    dense          (·,)     the dense blocks' values
    lowrank_index  (nl, 7)  r0, r1, c0, c1, rank k, offset in U, offset in V
    U, V           (·,)     U (3(r1-r0), k) and V (3(c1-c0), k), row-major, block ≈ U Vᵀ (float32 when
                            the tolerance is 1e-5 or more: their rounding is then ≤ 1 % of it)
    U16, V16       (·,)     in their place in format 1.8 where the tolerance is 1e-4 or more: the same factors
                            as int16 multiples of one scale per column (:func:`encode_far`), the block truncated
                            to half the tolerance and rounded within the other half (a 1.7 reader refuses the file
                            as missing U); the reader decodes them to float32 (:class:`Far16`)
    U_scale, V_scale (·,)   with them, float32: each block's k column scales, block after block in the index's
                            order (:func:`far_scale_offsets`)
    scale          (n,)     optional; when not empty Ξ = G diag(a) with G symmetric, a = scale (contact order),
                            and only the blocks on and above the diagonal (r0 ≤ c0) are stored: the block
                            below is :math:`\Xi_{JI} = \mathrm{diag}(a_J)^{-1}\,\Xi_{IJ}^T\,\mathrm{diag}(a_I)`
    near_index     (nd, 3)  optional (format 1.6): the dense blocks are stored pair by pair, offsets of block b
                            in near_q (values), near_mask (bytes) and near_scale (values); see below
    near_exact48   (·,)     with near_index, in place of ``dense`` (format 1.7): the exact pairs in fixed point,
                            28 uint16 words a pair (:func:`pack_exact`: within 1.4e-14 of the pair's largest
                            magnitude); a 1.6 reader refuses the file as missing its near field
    near_exact     (·,)     in its place in format 1.6, and in 1.7 where the values are float32 (``--float32``):
                            the exact pairs' values (a format 1.5 reader, which would read them as whole
                            blocks, refuses the file as missing ``dense``)
    near_mask      (·,)     uint8: for each dense block, one bit per vertex pair (row-major over its m x w
                            pairs, ``numpy.packbits`` order, each block from a whole byte): set where the pair
                            is stored exactly
    near_q         (·,)     int16: the 3x3 blocks of the other pairs, in the same order, as multiples of ...
    near_scale     (·,)     ... one scale per column of the block (3w values)

With ``near_index`` a dense block is stored at the granularity of its vertex pairs (:func:`encode_near`): every
pair within r_max (what K_i read: eq. 12) as its nine values (``dense_index``'s offset counts them, pair after
pair: in ``near_exact48`` a pair's words start at offset / 9 × 28), the block's other pairs in 16 bits per
value, ``value = q * scale[column]`` with each column's scale its largest magnitude / 32767, kept only where the
block then stays within half the tolerance of its norm (``‖Ξ_IJ − Ξ̃_IJ‖_F ≤ ε/2 ‖Ξ_IJ‖_F``; else every pair of
the block is stored exactly).  A leaf block holds
pairs up to r_max plus two leaves' diagonals apart (the bench page's organ rows give both parts' bytes).  Without
it (format ≤ 1.5) a dense block is stored whole, row-major at ``dense[offset:]``.

A P1 artifact is stored that way (half the bytes: K_i's near field and the far field alike); the
partition is symmetric ((J, I) is a block whenever (I, J) is), so the pair of blocks is one stored block.
"""
from __future__ import annotations

import numpy as np

from pmask.errors import InputError
from pmask.runtime.artifact import HMATRIX as DATASETS  # the compressed form's datasets, as the artifact names them
from pmask.runtime.artifact import take_runs


#: the largest magnitude of the 16-bit near-field values (near_q): symmetric, so that −value is representable
Q_MAX = 32767
#: set bits in each byte value (a pair's rank among its block's exact pairs)
_ONES = np.array([bin(k).count("1") for k in range(256)], np.int64)
#: the exact pairs in fixed point (format 1.7, ``near_exact48``): a pair's nine values are integers m, ``|m| <= 2^46``,
#: times 2^(e − EXACT_BITS), 2^e the power of two above the pair's largest magnitude (:func:`pack_exact`)
EXACT_BITS = 46
#: words (uint16) a pair takes: three a value (its 48-bit two's complement, low word first) and the exponent e
PAIR_WORDS = 28
#: the exponents e a pair's 28th word may hold (:func:`pack_exact`: a float64's binary exponents, subnormals
#: included); the C core (greens.c) checks the same range
EXACT_EXPONENTS = (-1074, 1023)


def exponents_valid(e: np.ndarray) -> bool:
    """Whether every pair exponent ``e`` is one :func:`pack_exact` can write (:data:`EXACT_EXPONENTS`): anything
    else is a writer's bug or a corrupt file, refused by both loaders."""
    return not len(e) or (int(e.min()) >= EXACT_EXPONENTS[0] and int(e.max()) <= EXACT_EXPONENTS[1])


def pack_exact(values: np.ndarray) -> np.ndarray:
    r"""The exact pairs' values (9k,) in fixed point, :data:`PAIR_WORDS` uint16 words a pair (format 1.7): each
    pair's nine values rounded to multiples of :math:`2^{e-46}`, :math:`2^{e-1} \le \max|v| < 2^e`, so that every
    value is within :math:`2^{e-47} \le 2^{-46} \max|v|` (1.4e-14 of the pair's largest magnitude) of its float64
    value: below the round-off the solve leaves in them (issue #27 found an independent SuperLU solve of the same
    volume mesh 1e-13 from the near field; the tests hold it to 1e-12 of the dense route's), in 56 bytes where
    float64 takes 72.  A pair of zeros stays zero.  :func:`unpack_exact` gives the values back.  Values of
    magnitude 2^1023 or more (1e308: whose rounding up could overflow) are refused with NaN and inf."""
    P = np.asarray(values, np.float64).reshape(-1, 9)
    if not (np.abs(P) < 2.0 ** 1023).all():
        raise ValueError("the exact pairs hold NaN, inf or values beyond 2^1023")  # (our bug: Ξ's are ~1e-9 m/Pa)
    _, e = np.frexp(np.abs(P).max(axis=1))  # max = f 2^e, 0.5 <= f < 1 (e = 0 for a zero pair)
    m = np.rint(np.ldexp(P, (EXACT_BITS - e)[:, None])).astype(np.int64)  # |m| <= 2^46
    out = np.empty((len(P), PAIR_WORDS), np.uint16)
    for w in range(3):
        out[:, w:27:3] = (m >> (16 * w)) & 0xFFFF
    out[:, 27] = e.astype(np.int16).view(np.uint16)
    return out.ravel()


def unpack_exact(words) -> np.ndarray:
    """The values (k, 9) of k pairs' :data:`PAIR_WORDS` words (:func:`pack_exact`), bit for bit what it rounded
    them to (an integer below 2^48 times a power of two is a float64 exactly)."""
    W = np.asarray(words, np.uint16).reshape(-1, PAIR_WORDS)
    e = W[:, 27].view(np.int16).astype(np.int64)
    if not exponents_valid(e):
        raise InputError("the compressed Green's functions' exact pairs hold an exponent no float64 has; recompute "
                         "the artifact (pmask precompute --force)")
    # each value's three words and a fourth that extends its sign, read as one little-endian int64 (on any host:
    # the words are stored little-endian in the buffer)
    buf = np.empty((len(W), 9, 4), "<u2")
    buf[:, :, :3] = W[:, :27].reshape(-1, 9, 3)
    np.multiply(buf[:, :, 2] >> 15, 0xFFFF, out=buf[:, :, 3])
    m = buf.view("<i8").reshape(-1, 9).astype(np.float64)
    # times 2^(e − 46): a product by a power of two, exact (the result is a float64), where that power is a normal
    # float64 (a third the time of ldexp); ldexp for a pair below 2^-976, whose power would underflow
    deep = e - EXACT_BITS < -1022
    m *= np.ldexp(1.0, np.maximum(e - EXACT_BITS, -1022))[:, None]
    if deep.any():
        m[deep] = np.ldexp(buf[deep].view("<i8").reshape(-1, 9).astype(np.float64), (e[deep] - EXACT_BITS)[:, None])
    return m


def encode_near(B: np.ndarray, exact: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A dense block B (3m, 3w) in the pair-granular layout (module docstring): the pairs where ``exact`` (m, w) is
    set as float64 values, the others as int16 multiples of one scale per column of B, unless that leaves B
    farther than ``tol``/2 of its norm from its values (Frobenius), when every pair is stored exactly.  Returns
    (exact values (9k,), q (9(mw − k),) int16, scale (3w,), mask bytes (⌈mw/8⌉,) uint8)."""
    m, w = B.shape[0] // 3, B.shape[1] // 3
    P = np.asarray(B, np.float64).reshape(m, 3, w, 3).transpose(0, 2, 1, 3).reshape(m * w, 3, 3)
    keep = np.asarray(exact, bool).ravel().copy()
    scale = np.zeros((w, 3))
    q = np.zeros((0, 3, 3), np.int16)
    if not keep.all():
        R, cols = P[~keep], np.flatnonzero(~keep) % w
        np.maximum.at(scale, cols, np.abs(R).max(axis=1))  # each column's largest magnitude among these pairs
        scale /= Q_MAX
        s = np.broadcast_to(scale[cols][:, None, :], R.shape)
        qf = np.rint(np.divide(R, s, out=np.zeros_like(R), where=s > 0))
        if np.linalg.norm(R - qf * s) <= 0.5 * tol * np.linalg.norm(P):
            q = qf.astype(np.int16)
        else:  # (a tolerance below what 16 bits hold: the block stays exact)
            keep[:], scale[:] = True, 0.0
    return P[keep].ravel(), q.ravel(), scale.ravel(), np.packbits(keep)


def _rounded(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A (m, k) as int16 multiples of one float32 scale per column (its largest magnitude / :data:`Q_MAX`)."""
    s = (np.abs(A).max(axis=0) / Q_MAX).astype(np.float32) if A.size else np.zeros(A.shape[1], np.float32)
    q = np.rint(np.divide(A, s, out=np.zeros(A.shape), where=s > 0))
    return np.clip(q, -Q_MAX, Q_MAX).astype(np.int16), s


def _product_norm(A: np.ndarray, B: np.ndarray) -> float:
    r""":math:`\|A B^T\|_F` from the two Gram matrices, :math:`\sum (A^TA) \circ (B^TB)`: O((m + n) k²), not m n."""
    return float(np.sqrt(max(np.sum((A.T @ A) * (B.T @ B)), 0.0)))


def encode_far(U: np.ndarray, V: np.ndarray, budget: float):
    r"""A far block's factors U (m, k), V (n, k) in 16 bits (format 1.8): each column as int16 multiples of one
    float32 scale, its largest magnitude / :data:`Q_MAX`.  The rounding's error,
    :math:`\|UV^T - \tilde U\tilde V^T\|_F = \|(U - \tilde U)V^T + \tilde U (V - \tilde V)^T\|_F`, is computed
    (from k x k Gram matrices) and must be within ``budget`` of :math:`\|UV^T\|_F`; on a kidney's far blocks it
    is 2.7e-5 at the median and 4.4e-5 at most (P2, 4,338 vertices, by hand), so the tiles truncate to half the
    tolerance and this rounding takes the other half (:func:`pmask.precompute.compress.truncation_tolerance`).  A
    block whose rounding exceeds it (a column of a few large entries) is stored at rank 3k,
    :math:`[\tilde U\;\widetilde{\Delta U}\;\tilde U]\,[\tilde V\;\tilde V\;\widetilde{\Delta V}]^T` with
    :math:`\Delta U = U - \tilde U`, whose error is the residuals' rounding and :math:`\Delta U\,\Delta V^T`,
    ~1e-9 of the block.  Returns (Uq (m, k'), U's scales (k',), Vq (n, k'), V's scales (k',), the relative
    error), k' = k or 3k; :class:`Far16` gives the factors back."""
    U, V = np.asarray(U, np.float64), np.asarray(V, np.float64)
    norm = _product_norm(U, V)
    (qu, su), (qv, sv) = _rounded(U), _rounded(V)
    Ut, Vt = qu * su.astype(np.float64), qv * sv.astype(np.float64)
    dU, dV = U - Ut, V - Vt
    err = _product_norm(np.hstack([dU, Ut]), np.hstack([V, dV]))
    if err <= budget * norm:
        return qu, su, qv, sv, err / norm if norm else 0.0
    (qdu, sdu), (qdv, sdv) = _rounded(dU), _rounded(dV)
    dUt, dVt = qdu * sdu.astype(np.float64), qdv * sdv.astype(np.float64)
    err = _product_norm(np.hstack([dU - dUt, Ut, dU]), np.hstack([Vt, dV - dVt, dV]))
    return (np.hstack([qu, qdu, qu]), np.concatenate([su, sdu, su]), np.hstack([qv, qv, qdv]),
            np.concatenate([sv, sv, sdv]), err / norm if norm else 0.0)


def far_scale_offsets(lowrank_index: np.ndarray) -> np.ndarray:
    """Where each low-rank block's column scales start in ``U_scale`` and ``V_scale`` (format 1.8): the blocks'
    ranks, one after the other in the index's order."""
    k = np.asarray(lowrank_index, np.int64).reshape(-1, 7)[:, 4]
    return np.concatenate([[0], np.cumsum(k)])[:-1]


def far_words_of(decoded: np.ndarray, scale: np.ndarray, lowrank_index: np.ndarray, which: int) -> np.ndarray:
    """A 16-bit factor's words (format 1.8) from its float32 values as :class:`Far16` decodes them, ``which`` 5
    for U, 6 for V: each value divided by its column's scale (:class:`Far16` of words one: every value's scale) and
    rounded, exact (a decoded value is a word, of magnitude at most :data:`Q_MAX`, times a scale, rounded to 24
    bits: the quotient is within 2⁻⁹ of the word); decoded again by :class:`Far16` and compared, bit for bit (a
    difference is a bug here, not a user's file)."""
    s = Far16(np.ones(len(decoded), np.int16), scale, lowrank_index, which)[:]
    words = np.rint(np.divide(decoded, s, out=np.zeros(len(decoded)), where=s > 0)).astype(np.int16)
    again = Far16(words, scale, lowrank_index, which)[:]
    if not np.array_equal(again.view(np.uint32), np.asarray(decoded, np.float32).view(np.uint32)):
        raise RuntimeError("a 16-bit factor's words do not decode to its values (a bug in pmask)")
    return words


class SlicedArray:
    """A flat array read in contiguous slices, ``a[i:j]`` (:meth:`_slice`), never whole unless asked
    (``np.asarray``): the tile store's runs as the writer reads them (:class:`pmask.precompute.compress.Concatenated`),
    the exact pairs packed as they are read (:class:`pmask.precompute.compress.FixedPointPairs`), a 16-bit factor
    decoded (:class:`Far16`)."""

    #: what the refusal of a strided or fancy index names
    what = "a sliced array"

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key) -> np.ndarray:
        if not isinstance(key, slice) or key.step not in (None, 1):
            raise TypeError(f"{self.what} is read in contiguous slices")
        start, stop, _ = key.indices(len(self))
        return self._slice(start, max(start, stop))

    def _slice(self, start: int, stop: int) -> np.ndarray:
        raise NotImplementedError

    def __array__(self, dtype=None, copy=None):
        whole = self[0:len(self)]
        return whole if dtype is None else whole.astype(dtype)


class Far16(SlicedArray):
    """A 16-bit factor (format 1.8, :func:`encode_far`) left in the file (:class:`pmask.runtime.artifact.FileArray`)
    and read as float32 a slice at a time: ``f[a:b]`` reads those words and multiplies each by its column's scale.
    A slice may span blocks (``f[:]`` decodes it all, block after block)."""

    def __init__(self, words, scale, lowrank_index: np.ndarray, which: int):
        li = np.asarray(lowrank_index, np.int64).reshape(-1, 7)
        rows = 3 * (li[:, 1] - li[:, 0]) if which == 5 else 3 * (li[:, 3] - li[:, 2])
        order = np.argsort(li[:, which], kind="stable")
        self.words, self.scale = words, np.asarray(scale, np.float32)
        self.start, self.k = li[order, which], li[order, 4]
        self.size, self.so = rows[order] * self.k, far_scale_offsets(li)[order]
        self.shape, self.dtype = (len(words),), np.dtype(np.float32)
        self.nbytes = int(getattr(words, "nbytes", 2 * len(words))) + self.scale.nbytes  # (as stored)

    what = "a 16-bit factor"

    def _slice(self, a: int, b: int) -> np.ndarray:
        if b <= a:
            return np.zeros(0, np.float32)
        q = np.asarray(self.words[a:b])
        out = np.empty(b - a, np.float32)
        blk = int(np.searchsorted(self.start, a, side="right")) - 1
        at = a
        while at < b:
            s0, k = int(self.start[blk]), int(self.k[blk])
            stop = min(b, s0 + int(self.size[blk]))
            if stop <= at:  # (a block of rank 0)
                blk += 1
                continue
            sc = self.scale[self.so[blk]:self.so[blk] + k]
            if at == s0 and stop == s0 + int(self.size[blk]):  # (a whole block: its rows times the scales)
                out[at - a:stop - a] = (q[at - a:stop - a].reshape(-1, k) * sc).ravel()
            else:
                out[at - a:stop - a] = q[at - a:stop - a] * sc[(np.arange(at, stop) - s0) % k]
            at, blk = stop, blk + 1
        return out


class CompressedXi:
    """Ξ (3n x 3n) as near-field dense blocks and far-field low-rank blocks (module docstring).

    The runtime's access layer for Ξ: :meth:`blocks` (3x3 blocks of vertex pairs: eq. 12's sums and the
    coupling of contacts), :meth:`matvec` (Ξ x: the deformation of eq. 16), :meth:`to_dense` (tests)."""

    def __init__(self, perm, leaves, dense_index, dense, lowrank_index, U=None, V=None, *, tolerance: float,
                 scale=None, near_index=None, near_mask=None, near_q=None, near_scale=None, U16=None, V16=None,
                 U_scale=None, V_scale=None):
        self.perm = np.asarray(perm, np.int64)
        n = len(self.perm)
        self.n = n
        self.shape = (3 * n, 3 * n)
        self.tolerance = float(tolerance)
        self.leaves = np.asarray(leaves, np.int64)
        self.dense_index = np.asarray(dense_index, np.int64).reshape(-1, 5)
        self.lowrank_index = np.asarray(lowrank_index, np.int64).reshape(-1, 7)
        if U is None or V is None:  # (format 1.8: the factors in 16 bits, with their scales)
            U, V = U16, V16
        if U is None or V is None:
            raise InputError("the compressed Green's functions' far field is missing; recompute the artifact "
                             "(pmask precompute --force)")
        self.far_nbytes = int(U.nbytes + V.nbytes)  # (as stored: format 1.8's 16-bit words and their scales)
        self.far_scales = None  # format 1.8: U's and V's column scales (float32), which a table carries (1.5)
        if np.dtype(U.dtype) == np.int16 or np.dtype(V.dtype) == np.int16:  # format 1.8: in 16 bits (encode_far)
            U, V = self._far16(U, V, U_scale, V_scale)
        self.dense, self.U, self.V = dense, U, V
        self.fixed = np.dtype(dense.dtype) == np.uint16  # format 1.7: the exact pairs in fixed point (pack_exact)
        self._exact_values = len(dense) // PAIR_WORDS * 9 if self.fixed else len(dense)  # (values, not words)
        values = np.dtype(np.float64) if self.fixed else dense.dtype
        self.dtype = np.result_type(values, U.dtype) if len(U) else values
        self.position = np.empty(n, np.int64)
        self.position[self.perm] = np.arange(n)
        self.symmetric = scale is not None and len(scale) > 0
        if self.symmetric and len(scale) != n:
            raise InputError("the compressed Green's functions' scale does not match their vertices; recompute the "
                             "artifact (pmask precompute --force)")
        self.scale = np.asarray(scale, float) if self.symmetric else None  # a, contact order
        self._dof_scale = np.repeat(self.scale[self.perm], 3) if self.symmetric else None  # a per dof, cluster order
        # the leaf cluster of each position, and the blocks over each leaf row (the block that owns a pair)
        self.leaf_of = np.repeat(np.arange(len(self.leaves) - 1), np.diff(self.leaves))
        self._nd = len(self.dense_index)
        self._key, self._block, self._flip = self._leaf_rows()
        self.packed = near_index is not None and len(near_index) > 0  # format 1.6: the near field pair by pair
        if self.packed:
            self.near_index = np.asarray(near_index, np.int64).reshape(-1, 3)
            self.near_mask = np.asarray(near_mask, np.uint8)
            self.near_scale = np.asarray(near_scale, np.float64)
            self.near_q = near_q  # (may be read on demand, as the exact values)
            self._check_packed()
        else:
            self.near_index = np.zeros((0, 3), np.int64)
            self.near_mask = np.zeros(0, np.uint8)
            self.near_scale = np.zeros(0)
            self.near_q = np.zeros(0, np.int16)

    def _far16(self, U, V, U_scale, V_scale):
        """Format 1.8's 16-bit factors as float32: decoded at once where read into memory, a slice at a time where
        left in the file (:class:`Far16`); their scales checked against the index first (one line if not)."""
        li = self.lowrank_index
        k = int(li[:, 4].sum())
        ends = [3 * (li[:, 1] - li[:, 0]) * li[:, 4], 3 * (li[:, 3] - li[:, 2]) * li[:, 4]]
        ok = (np.dtype(U.dtype) == np.dtype(V.dtype) == np.int16 and U_scale is not None and V_scale is not None
              and len(U_scale) == len(V_scale) == k
              and all(not len(li) or (li[:, c].min() >= 0 and np.max(li[:, c] + e) <= len(a))
                      for c, e, a in ((5, ends[0], U), (6, ends[1], V))))
        if not ok:
            raise InputError("the compressed Green's functions' 16-bit far field does not match its index or scales; "
                             "recompute the artifact (pmask precompute --force)")
        self.far_scales = (np.asarray(U_scale, np.float32), np.asarray(V_scale, np.float32))
        self.far_nbytes += int(self.far_scales[0].nbytes + self.far_scales[1].nbytes)
        if isinstance(U, np.ndarray):
            return (Far16(U, U_scale, li, 5)[:], Far16(V, V_scale, li, 6)[:])
        return Far16(U, U_scale, li, 5), Far16(V, V_scale, li, 6)

    def _check_packed(self) -> None:
        """The pair-granular near field's offsets and counts against the arrays they index (one line if not), and
        the bits set before each byte of the mask (a pair's rank among its block's exact pairs)."""
        di, ni = self.dense_index, self.near_index
        pairs = (di[:, 1] - di[:, 0]) * (di[:, 3] - di[:, 2])
        nbytes = -(-pairs // 8)
        ones = _ONES[self.near_mask]
        dt = np.int32 if ones.sum() < 2**31 else np.int64
        self._ones_before = np.concatenate([[0], np.cumsum(ones, dtype=dt)])
        whole_pairs = not self.fixed or len(self.dense) % PAIR_WORDS == 0
        ok = whole_pairs and len(ni) == len(di) and (not len(ni) or (
            ni.min() >= 0 and di[:, 4].min() >= 0 and np.all(ni[:, 1] + nbytes <= len(self.near_mask))))
        if ok and len(ni):
            k = self._ones_before[ni[:, 1] + nbytes] - self._ones_before[ni[:, 1]]  # exact pairs of each block
            ok = (np.all(di[:, 4] + 9 * k <= self._exact_values)
                  and np.all(ni[:, 0] + 9 * (pairs - k) <= len(self.near_q))
                  and np.all(ni[:, 2] + 3 * (di[:, 3] - di[:, 2]) <= len(self.near_scale)))
        if not ok:
            raise InputError("the compressed Green's functions' near field does not match its index; recompute the "
                             "artifact (pmask precompute --force)")

    def _leaf_rows(self):
        """The stored blocks over each leaf row, as sorted keys ``row * L + first leaf column`` (L leaves), the
        block, and whether the row reads it transposed (symmetric: the pair is below the diagonal).  Each row's
        blocks must tile its columns exactly once.  An H-matrix's blocks cover a row a bounded number of times
        per tree level, so this holds O(n log n) entries, where a leaf x leaf table held L² (350 MB at 200,000
        vertices)."""
        nl = len(self.leaves) - 1
        box = np.vstack([self.dense_index[:, :4], self.lowrank_index[:, :4]])
        if not self.n or not len(box):
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, bool)
        if box.min() < 0 or box[:, [1, 3]].max() > self.n or np.any(box[:, [1, 3]] <= box[:, [0, 2]]):
            raise InputError("the compressed Green's functions' blocks lie outside their vertices; recompute the "
                             "artifact (pmask precompute --force)")
        lr0, lr1 = self.leaf_of[box[:, 0]], self.leaf_of[box[:, 1] - 1] + 1  # leaf ranges of each block
        lc0, lc1 = self.leaf_of[box[:, 2]], self.leaf_of[box[:, 3] - 1] + 1
        b = np.arange(len(box))
        flip = np.zeros(len(box), bool)
        if self.symmetric:  # the block below the diagonal, read from the stored one above it
            m = box[:, 0] != box[:, 2]
            lr0, lr1, lc0, lc1 = (np.concatenate([x, y[m]])
                                  for x, y in ((lr0, lc0), (lr1, lc1), (lc0, lr0), (lc1, lr1)))
            b, flip = np.concatenate([b, b[m]]), np.concatenate([flip, np.ones(m.sum(), bool)])
        span = lr1 - lr0
        row = np.repeat(lr0 - np.cumsum(span) + span, span) + np.arange(span.sum())  # each block's leaf rows
        each = np.repeat(np.arange(len(b)), span)
        key = row * nl + lc0[each]
        order = np.argsort(key, kind="stable")
        key, each, row = key[order], each[order], row[order]
        first = np.r_[True, row[1:] != row[:-1]]
        last = np.r_[first[1:], True]
        tiled = (len(np.unique(row)) == nl and np.all(lc0[each][first] == 0) and np.all(lc1[each][last] == nl)
                 and np.array_equal(lc0[each][~first], lc1[each][~last]))
        if not tiled:
            raise InputError("the compressed Green's functions do not cover every pair of vertices once; recompute "
                             "the artifact (pmask precompute --force)")
        return key, b[each], flip[each]

    def owner(self, p, q) -> tuple[np.ndarray, np.ndarray]:
        """The stored block holding each pair of positions (p, q) (cluster order), and whether it holds the pair
        transposed (symmetric: below the diagonal)."""
        nl = len(self.leaves) - 1
        k = np.searchsorted(self._key, self.leaf_of[p] * nl + self.leaf_of[q], side="right") - 1
        return self._block[k], self._flip[k]

    @property
    def nbytes(self) -> int:
        """Bytes of the stored values (what the compression ratio compares with (3n)² dense numbers)."""
        return int(self.near_nbytes + self.far_nbytes)

    @property
    def near_nbytes(self) -> int:
        """Bytes of the dense blocks (the exact pairs, and, format 1.6, the others' 16-bit values, their scales and
        the mask that tells them apart)."""
        return int(self.dense.nbytes + self.near_q.nbytes + self.near_mask.nbytes + self.near_scale.nbytes)

    def dense_block(self, b: int) -> np.ndarray:
        """Dense block ``b`` of :attr:`dense_index` as its (3m, 3w) array (cluster order)."""
        r0, r1, c0, c1, off = (int(x) for x in self.dense_index[b])
        m, w = r1 - r0, c1 - c0
        if not self.packed:
            return np.asarray(self.dense[off:off + 9 * m * w], np.float64).reshape(3 * m, 3 * w)
        qo, mo, so = (int(x) for x in self.near_index[b])
        keep = np.unpackbits(self.near_mask[mo:mo + -(-m * w // 8)], count=m * w).astype(bool)
        k = int(keep.sum())
        P = np.empty((m * w, 3, 3))
        P[keep] = self.exact_values(off, off + 9 * k).reshape(k, 3, 3)
        scale = self.near_scale[so:so + 3 * w].reshape(w, 3)
        P[~keep] = (np.asarray(self.near_q[qo:qo + 9 * (m * w - k)], np.float64).reshape(-1, 3, 3)
                    * scale[np.flatnonzero(~keep) % w][:, None, :])
        return P.reshape(m, w, 3, 3).transpose(0, 2, 1, 3).reshape(3 * m, 3 * w)

    def compression_ratio(self, itemsize: int = 8) -> float:
        """Dense Ξ's bytes over this form's stored values."""
        return (3 * self.n) ** 2 * itemsize / max(self.nbytes, 1)

    def near_fraction(self) -> float:
        """Share of Ξ's entries in dense (near-field) blocks."""
        d = self.dense_index
        twice = 1 + (self.symmetric & (d[:, 0] != d[:, 2]))  # a stored block above the diagonal stands for two
        return float(np.sum(twice * (d[:, 1] - d[:, 0]) * (d[:, 3] - d[:, 2]))) / max(self.n ** 2, 1)

    def blocks(self, i, j) -> np.ndarray:
        r"""Ξ_ij (pairs, 3, 3) for contact indices ``i`` and ``j`` (arrays of the same length): exact where the
        pair lies in a dense block (every pair within r_max), U_i V_jᵀ (3x3 rows of the factors) elsewhere;
        a pair below a symmetric form's diagonal from the stored one, :math:`\Xi_{ij} = (a_j/a_i)\,\Xi_{ji}^T`."""
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        p, q = self.position[i], self.position[j]
        b, t = self.owner(p, q)
        if t.any():
            out = self._stored(np.where(t, q, p), np.where(t, p, q), b)
            out[t] = out[t].transpose(0, 2, 1) * (self.scale[j[t]] / self.scale[i[t]])[:, None, None]
            return out
        return self._stored(p, q, b)

    def _stored(self, p, q, b) -> np.ndarray:
        """The 3x3 blocks of positions (p, q) from the stored blocks ``b`` that hold them."""
        out = np.empty((len(p), 3, 3))
        three = np.arange(3)
        dense = b < self._nd
        if dense.any() and self.packed:
            out[dense] = self._pairs(p[dense], q[dense], b[dense])
        elif dense.any():
            r0, _, c0, c1, off = self.dense_index[b[dense]].T
            width = 3 * (c1 - c0)
            rows = 3 * (p[dense] - r0)[:, None] + three  # (k, 3)
            cols = 3 * (q[dense] - c0)[:, None] + three
            idx = off[:, None, None] + rows[:, :, None] * width[:, None, None] + cols[:, None, :]
            out[dense] = self.dense[idx]
        far = np.flatnonzero(~dense)
        if len(far):
            lb = b[far] - self._nd
            order = np.argsort(lb, kind="stable")
            lb, far = lb[order], far[order]
            cut = np.flatnonzero(np.diff(lb)) + 1
            for grp in np.split(np.arange(len(far)), cut):
                r0, r1, c0, c1, k, uo, vo = self.lowrank_index[lb[grp[0]]]
                U = self.U[uo:uo + 3 * (r1 - r0) * k].reshape(3 * (r1 - r0), k)
                V = self.V[vo:vo + 3 * (c1 - c0) * k].reshape(3 * (c1 - c0), k)
                Ur = U[3 * (p[far[grp]] - r0)[:, None] + three].astype(np.float64)  # (g, 3, k); float32 factors
                Vr = V[3 * (q[far[grp]] - c0)[:, None] + three].astype(np.float64)  # are summed in float64
                out[far[grp]] = np.einsum("grk,gck->grc", Ur, Vr)
        return out

    def exact_values(self, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """The exact pairs' values ``lo:hi`` (float64; offsets of whole pairs, multiples of nine, when stored in
        fixed point: :func:`unpack_exact`)."""
        hi = self._exact_values if hi is None else hi
        if not self.fixed:
            return np.asarray(self.dense[lo:hi], np.float64)
        return unpack_exact(self.dense[lo // 9 * PAIR_WORDS:hi // 9 * PAIR_WORDS]).ravel()

    def _exact_runs(self, starts) -> np.ndarray:
        """The nine exact values from each offset ``starts`` into :attr:`dense` (pairs, 9), gathered as whole rows
        (:func:`pmask.runtime.artifact.take_runs`); a near field read on demand finds the blocks to read from the
        runs' ends (:meth:`pmask.runtime.artifact.BlocksOnDemand.runs`).  Every K_i's masked sum at 20,427 vertices
        with 10 mm masks: 3.1 s against 4.5 s gathering value by value, bitwise the same (by hand).  In fixed
        point (format 1.7) a pair's :data:`PAIR_WORDS` words are gathered and unpacked."""
        if self.fixed:
            starts = np.asarray(starts, np.int64) // 9 * PAIR_WORDS
            runs = getattr(self.dense, "runs", None)
            if runs is not None:
                return unpack_exact(runs(starts, PAIR_WORDS))
            return unpack_exact(take_runs(self.dense, starts, PAIR_WORDS) if isinstance(self.dense, np.ndarray)
                                else self.dense[starts[:, None] + np.arange(PAIR_WORDS)])
        runs = getattr(self.dense, "runs", None)
        if runs is not None:
            return runs(starts, 9)
        return take_runs(self.dense, np.asarray(starts, np.int64), 9) if isinstance(self.dense, np.ndarray) \
            else self.dense[np.asarray(starts)[:, None] + np.arange(9)]

    def _pairs(self, p, q, b) -> np.ndarray:
        """The 3x3 blocks of positions (p, q) from the pair-granular dense blocks ``b`` that hold them: pair t of
        its block is exact where its bit is set, the (bits set before it)-th exact pair, else the (t − that)-th of
        the 16-bit ones."""
        r0, _, c0, c1, off = self.dense_index[b].T
        qo, mo, so = self.near_index[b].T
        t = (p - r0) * (c1 - c0) + (q - c0)  # the pair within its block
        g = 8 * mo + t  # its bit
        byte = self.near_mask[g >> 3].astype(np.int64)
        bit = g & 7
        before = self._ones_before[g >> 3] - self._ones_before[mo] + _ONES[byte >> (8 - bit)]  # exact pairs before t
        exact = ((byte >> (7 - bit)) & 1).astype(bool)
        nine = np.arange(9)
        if exact.all():  # (a mask's pairs, all within r_max: no selection, no scatter)
            return np.asarray(self._exact_runs(off + 9 * before), np.float64).reshape(-1, 3, 3)
        out = np.empty((len(p), 9))
        if exact.any():
            out[exact] = self._exact_runs((off + 9 * before)[exact])
        if not exact.all():
            o = ~exact
            s = self.near_scale[(so + 3 * (q - c0))[o, None] + np.arange(3)]  # the pair's three columns' scales
            out[o] = (self.near_q[(qo + 9 * (t - before))[o, None] + nine].astype(np.float64).reshape(-1, 3, 3)
                      * s[:, None, :]).reshape(-1, 9)
        return out.reshape(-1, 3, 3)

    def matvec(self, x) -> np.ndarray:
        """Ξ x for x (3n,) or (3n, m) in contact order; blocks whose columns x leaves zero are skipped (a
        deformation's load sits on a few vertices)."""
        x = np.asarray(x, float)
        vec = x.ndim == 1
        X = x.reshape(self.n, 3, -1)[self.perm].reshape(3 * self.n, -1)  # cluster order
        Y = np.zeros_like(X)
        nz = np.concatenate([[0], np.cumsum(np.any(X.reshape(self.n, -1) != 0, axis=1))])
        loaded = lambda a, b: (nz[b] - nz[a]) > 0  # noqa: E731  (positions a..b carry load)
        di, li = self.dense_index, self.lowrank_index
        for b in np.flatnonzero(loaded(di[:, 2], di[:, 3])):
            r0, r1, c0, c1, _ = di[b]
            Y[3 * r0:3 * r1] += self.dense_block(b) @ X[3 * c0:3 * c1]
        for r0, r1, c0, c1, k, uo, vo in li[loaded(li[:, 2], li[:, 3])]:
            m, w = 3 * (r1 - r0), 3 * (c1 - c0)
            U = self.U[uo:uo + m * k].reshape(m, k)
            V = self.V[vo:vo + w * k].reshape(w, k)
            Y[3 * r0:3 * r1] += U @ (V.T @ X[3 * c0:3 * c1])
        if self.symmetric:  # the blocks below the diagonal: Ξ_JI x_I = diag(a_J)⁻¹ Ξ_IJᵀ diag(a_I) x_I
            a = self._dof_scale[:, None]
            for b in np.flatnonzero((di[:, 0] != di[:, 2]) & loaded(di[:, 0], di[:, 1])):
                r0, r1, c0, c1, _ = di[b]
                B = self.dense_block(b)
                Y[3 * c0:3 * c1] += (B.T @ (a[3 * r0:3 * r1] * X[3 * r0:3 * r1])) / a[3 * c0:3 * c1]
            for r0, r1, c0, c1, k, uo, vo in li[(li[:, 0] != li[:, 2]) & loaded(li[:, 0], li[:, 1])]:
                m, w = 3 * (r1 - r0), 3 * (c1 - c0)
                U = self.U[uo:uo + m * k].reshape(m, k)
                V = self.V[vo:vo + w * k].reshape(w, k)
                Y[3 * c0:3 * c1] += (V @ (U.T @ (a[3 * r0:3 * r1] * X[3 * r0:3 * r1]))) / a[3 * c0:3 * c1]
        out = np.empty_like(Y)
        out.reshape(self.n, 3, -1)[self.perm] = Y.reshape(self.n, 3, -1)
        return out.ravel() if vec else out

    def to_dense(self) -> np.ndarray:
        """The (3n, 3n) array in contact order (for tests and small models)."""
        D = np.zeros(self.shape)
        a = self._dof_scale
        blocks = [(*self.dense_index[b, :4], self.dense_block(b)) for b in range(self._nd)]
        blocks += [(r0, r1, c0, c1, self.U[uo:uo + 3 * (r1 - r0) * k].reshape(-1, k).astype(np.float64)
                    @ self.V[vo:vo + 3 * (c1 - c0) * k].reshape(-1, k).T)
                   for r0, r1, c0, c1, k, uo, vo in self.lowrank_index]
        for r0, r1, c0, c1, B in blocks:
            D[3 * r0:3 * r1, 3 * c0:3 * c1] = B
            if self.symmetric and r0 != c0:
                D[3 * c0:3 * c1, 3 * r0:3 * r1] = B.T * a[3 * r0:3 * r1][None, :] / a[3 * c0:3 * c1][:, None]
        dofs = (3 * self.perm[:, None] + np.arange(3)).ravel()
        out = np.empty_like(D)
        out[np.ix_(dofs, dofs)] = D
        return out

    @classmethod
    def from_datasets(cls, data: dict, tolerance: float) -> "CompressedXi":
        """From the artifact's datasets (:data:`DATASETS`, keyed by their full names)."""
        g = {k.rsplit("/", 1)[1]: data.get(k) for k in DATASETS}
        pairs = g["near_exact48"] if g["near_exact48"] is not None else g["near_exact"]  # (1.7, or 1.6)
        near = g["dense"] if g["dense"] is not None else pairs  # (whole blocks, or pair by pair)
        if near is None or (pairs is not None) != (g["near_index"] is not None):
            raise InputError("the compressed Green's functions' near field is missing or does not match its index; "
                             "recompute the artifact (pmask precompute --force)")
        return cls(g["perm"], g["leaves"], g["dense_index"], near, g["lowrank_index"], g["U"], g["V"],
                   tolerance=tolerance, scale=g["scale"], near_index=g["near_index"], near_mask=g["near_mask"],
                   near_q=g["near_q"], near_scale=g["near_scale"], U16=g["U16"], V16=g["V16"], U_scale=g["U_scale"],
                   V_scale=g["V_scale"])


#: ζ_m(i) blocks a :class:`MaskedXi` keeps (9 floats each; a few contacts use tens)
ZETA_BLOCK_CACHE = 65536


class MaskedXi:
    r"""Ξ seen through the core masks without the ζ table (as large as Ξ): what coupled contacts and the display
    read from a compressed Ξ (either form works; a dense one has its ζ table instead).

    ``mask_row(c)``: (columns, weights) of the mask centred at contact vertex c (contact indices), empty where it
    has none.  :meth:`block` is ζ_m(i) = Σ_j ρ^m_j Ξ_ij (eq. 13) from Ξ's blocks of mask m's columns at row i (the
    exact near field, or the far field's low-rank factors: work of the mask's size times the rank, whatever n),
    kept in a bounded cache, since contacts stay on the same vertices for many ticks; :meth:`deformation_of` is
    eq. 16 as one product Ξ x."""

    def __init__(self, Xi, mask_row, cache: int = ZETA_BLOCK_CACHE):
        self.Xi, self.mask_row, self.cache = Xi, mask_row, int(cache)
        self._blocks = {}

    def block(self, m: int, i: int) -> list:
        """ζ_m(i)ᵀ for contact vertices m (the force's) and i (the displaced one), three lists of three (the block
        function of :func:`pmask.runtime.stiffness.zeta_compliance`); zero where m has no mask (a zero row of the ζ
        table too)."""
        key = (m, i)
        blk = self._blocks.get(key)
        if blk is None:
            cols, w = self.mask_row(m)
            Z = np.einsum("j,jrc->rc", w, xi_blocks(self.Xi, np.full(len(cols), i), cols)) if len(cols) \
                else np.zeros((3, 3))
            blk = Z.T.tolist()
            if len(self._blocks) >= self.cache:
                self._blocks.clear()
            self._blocks[key] = blk
        return blk

    def deformation_of(self, mesh_T, contact_row, loads) -> np.ndarray:
        """eq. 16 summed over point loads ``[(mesh triangle, barycentrics, force), ...]``: one product Ξ x, x the
        loads spread over each loaded vertex's mask, which touches only the blocks of the loaded columns.  The
        displacement (len(contact_row), 3) of every mesh vertex, zero where ``contact_row`` is -1."""
        x = np.zeros((self.Xi.n, 3))
        for t, b, f in loads:
            for vertex, phi in zip(mesh_T[t], b):
                c = contact_row[vertex]
                if phi != 0.0 and c >= 0:
                    cols, w = self.mask_row(c)
                    x[cols] += (phi * np.asarray(w))[:, None] * np.asarray(f, float)
        v_contact = self.Xi.matvec(x.ravel()).reshape(-1, 3)
        contact_row = np.asarray(contact_row)
        v = np.zeros((len(contact_row), 3))
        has = contact_row >= 0
        v[has] = v_contact[contact_row[has]]
        return v


def xi_blocks(Xi, i, j) -> np.ndarray:
    """Ξ_ij (pairs, 3, 3) from either form: a dense (3n, 3n) array or :class:`CompressedXi`."""
    if isinstance(Xi, CompressedXi):
        return Xi.blocks(i, j)
    n = Xi.shape[1] // 3
    X4 = Xi.reshape(Xi.shape[0] // 3, 3, n, 3)
    return X4[np.asarray(i), :, np.asarray(j), :]  # (float32 stays float32: the mask weights' product upcasts)
