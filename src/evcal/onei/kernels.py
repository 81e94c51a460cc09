"""Compiled kernels of OnEI (:mod:`evcal.onei`): packed event counts, sliding sums of frame
intervals and the blocked per-pixel normal equations. Pure numpy + numba, no state here.

**Packed counts.** The events of the open frame interval are counted in one byte per pixel:
bits 0-2 the OFF count, bits 3-5 the ON count (each 0..7; the eighth event of a polarity
spills 7 into an int32 map), bits 6-7 the polarity of the pixel's latest event in the
interval (0 none, 1 ON, 2 OFF). A random event stream then touches one byte per event instead
of three scattered words (the int32 ON and OFF maps and the int8 last polarity).

**Blocked normal equations.** The 16 running cross products of
:class:`~evcal.solver.NormalEquations` (rows in its order) are kept as ``(n_blocks,
16 * BLOCK)`` float64: ``m[b].reshape(16, BLOCK)`` is the C-contiguous ``(16, n)`` system of
pixels ``b * BLOCK ...`` for :mod:`evcal.solver`'s kernels, small enough to stay in a core's
L2 cache between the update of a block and its solve. ``BLOCK * 8`` bytes is 256 more than a
multiple of 4096, so that a pixel's 16 rows fall in different cache sets (with
``BLOCK = 8192`` they would all alias and the updates run about 5x slower).

**Equations.** One equation of a pixel is ``(ON, OFF)`` counts between two frames, the
polarities ``(q_j, q_k)`` of its last events before them and its two raw frame values;
:func:`apply_blocks` adds ``sign`` times its cross products (:meth:`NormalEquations.add`'s
formulas, the same operations in the same order, so the sums are bit-identical to adding the
equations one by one), block by block.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import numba
import numpy as np

BLOCK = 8224  # pixels per block: 16 rows of 65,792 B (16 pages + 256 B)
COUNT_BITS = 3  # per polarity in the packed byte; COUNT_MAX = 7 events before a spill
COUNT_MAX = (1 << COUNT_BITS) - 1
LAST_SHIFT = 2 * COUNT_BITS

F = TypeVar("F", bound=Callable[..., Any])


def _jit(fn: F) -> F:
    """``numba.njit`` with OnEI's options, typed for mypy (the kernels keep their signatures)."""
    jitted: F = numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
    return jitted


def jit(**options: Any) -> Callable[[F], F]:
    """``numba.njit(cache=True, nogil=True, **options)``, typed for mypy (the kernels keep
    their signatures)."""

    def wrap(fn: F) -> F:
        jitted: F = numba.njit(cache=True, nogil=True, **options)(fn)
        return jitted

    return wrap


# ----------------------------------------------------------------------------------------
# packed event counts


@_jit
def fold_events(x: np.ndarray, y: np.ndarray, p: np.ndarray, width: int, code: np.ndarray,
                spill_on: np.ndarray, spill_off: np.ndarray) -> int:  # pragma: no cover
    """Count validated events into the packed map; returns how many counts spilled."""
    n_spill = 0
    for i in range(x.size):
        k = np.int64(y[i]) * width + np.int64(x[i])
        w = np.int32(code[k])
        on = np.int32(p[i] > 0)
        shift = COUNT_BITS * on
        if ((w >> shift) & COUNT_MAX) == COUNT_MAX:
            if on:
                spill_on[k] += COUNT_MAX
            else:
                spill_off[k] += COUNT_MAX
            w -= COUNT_MAX << shift
            n_spill += 1
        code[k] = ((w + (1 << shift)) & ((1 << LAST_SHIFT) - 1)) | ((2 - on) << LAST_SHIFT)
    return n_spill


@_jit
def close_interval(code: np.ndarray, spill_on: np.ndarray, spill_off: np.ndarray,
                   spilled: bool, last_p: np.ndarray, keep: bool, counts: np.ndarray,
                   win: np.ndarray, add_win: bool) -> Any:  # pragma: no cover
    """Close the open interval: ``(idx, on, off, n_events, dense)``, its int32 counts, sparse
    (``idx`` the sorted pixels that fired) or, when more than 2/3 of the pixels fired, dense
    (full maps, ``idx`` empty: less memory than sparse); empty unless ``keep``. The latest
    polarities are folded into ``last_p``, the packed map and spills zeroed; with ``keep``
    the counts are added to ``counts`` (and to the sliding sum ``win`` (2, n) when
    ``add_win``). Passes without data-dependent branches (the polarities are random:
    branches would mispredict)."""
    # (no helper functions taking arrays in these loops: numba keeps the reference counting
    # of arrays passed to an inlined helper, which costs ~20x the loop body)
    n = code.size
    if spilled:  # the spill maps become the counts
        for i in range(n):
            c = np.int32(code[i])
            spill_on[i] += (c >> COUNT_BITS) & COUNT_MAX
            spill_off[i] += c & COUNT_MAX
    nnz = 0
    total = 0
    if keep:
        for i in range(n):
            c = np.int32(code[i])
            on = spill_on[i] if spilled else (c >> COUNT_BITS) & COUNT_MAX
            off = spill_off[i] if spilled else c & COUNT_MAX
            nnz += (on + off) > 0
            total += on + off
            counts[i] += on + off
        if add_win:  # one loop per output array (see fill_slot)
            for w_c, s_c, sh in ((win[0], spill_on, COUNT_BITS), (win[1], spill_off, 0)):
                for i in range(n):
                    c = np.int32(code[i])
                    w_c[i] += s_c[i] if spilled else (c >> sh) & COUNT_MAX
    dense = 3 * nnz > 2 * n
    if dense:
        out_on = np.empty(n, np.int32)
        out_off = np.empty(n, np.int32)
        for out, s_c, sh in ((out_on, spill_on, COUNT_BITS), (out_off, spill_off, 0)):
            for i in range(n):
                c = np.int32(code[i])
                out[i] = s_c[i] if spilled else (c >> sh) & COUNT_MAX
        nnz = 0  # no sparse pixels
    else:  # one spare element: the compaction writes every pixel, moves past those that fired
        out_on = np.empty(nnz + 1, np.int32)
        out_off = np.empty(nnz + 1, np.int32)
    idx = np.empty(nnz + 1, np.int32)
    if keep and not dense:
        j = 0
        for i in range(n):
            c = np.int32(code[i])
            on = spill_on[i] if spilled else (c >> COUNT_BITS) & COUNT_MAX
            off = spill_off[i] if spilled else c & COUNT_MAX
            idx[j] = i
            out_on[j] = on
            out_off[j] = off
            j += (on + off) > 0
    for i in range(n):
        last = np.int32(code[i]) >> LAST_SHIFT
        lp = last_p[i]
        last_p[i] = lp if last == 0 else (1 if last == 1 else -1)
        code[i] = 0
    if spilled:
        spill_on[:] = 0
        spill_off[:] = 0
    if dense:
        return idx[:0], out_on, out_off, total, True
    return idx[:nnz], out_on[:nnz], out_off[:nnz], total, False


# ----------------------------------------------------------------------------------------
# sliding sums of frame intervals


@_jit
def scatter_interval(win: np.ndarray, idx: np.ndarray, on: np.ndarray, off: np.ndarray,
                     sign: int) -> None:  # pragma: no cover
    """``win (2, n) += sign * (on, off)`` at the pixels ``idx``."""
    for i in range(idx.size):
        k = idx[i]
        win[0, k] += sign * on[i]
        win[1, k] += sign * off[i]


@_jit
def add_dense(win: np.ndarray, on: np.ndarray, off: np.ndarray,
              sign: int) -> None:  # pragma: no cover
    """``win (2, n) += sign * (on, off)`` for a dense interval."""
    w0 = win[0]
    w1 = win[1]
    for i in range(on.size):
        w0[i] += sign * on[i]
    for i in range(on.size):
        w1[i] += sign * off[i]


@_jit
def drop_dense(counts: np.ndarray, wins: np.ndarray, sub: np.ndarray, on: np.ndarray,
               off: np.ndarray) -> None:  # pragma: no cover
    """:func:`drop_interval` for a dense interval."""
    for i in range(on.size):
        counts[i] -= on[i] + off[i]
    for w in range(2):
        if sub[w]:
            add_dense(wins[w], on, off, -1)


@_jit
def drop_interval(counts: np.ndarray, wins: np.ndarray, sub: np.ndarray, idx: np.ndarray,
                  on: np.ndarray, off: np.ndarray) -> None:  # pragma: no cover
    """An interval leaves the large buffer: ``counts -= on + off`` and, for each of the two
    sliding sums ``wins[w]`` (2, n) with ``sub[w]``, ``wins[w] -= (on, off)``, in one pass."""
    s0 = sub[0]
    s1 = sub[1]
    for i in range(idx.size):
        k = idx[i]
        a = on[i]
        b = off[i]
        counts[k] -= a + b
        if s0:
            wins[0, 0, k] -= a
            wins[0, 1, k] -= b
        if s1:
            wins[1, 0, k] -= a
            wins[1, 1, k] -= b


# ----------------------------------------------------------------------------------------
# equations, blocked normal equations


@_jit
def fill_slot(win: np.ndarray, lp_j: np.ndarray, lp_k: np.ndarray, img_j: np.ndarray,
              img_k: np.ndarray, sums: np.ndarray, qa: np.ndarray,
              raw: np.ndarray) -> None:  # pragma: no cover
    """Queue one equation of two 8-bit frames: the pixel counts ``win`` (2, n) into ``sums``,
    ``(q_k - q_j, |q_k| - |q_j|)`` into ``qa`` (2, n) and the frame values into ``raw``
    (2, n) (a value the frames' table maps to NaN, one not usable, gives the equation weight
    0 in :func:`apply_blocks`). Copies and differences: vectorised."""
    # one loop per output array: with more, the checks that the arrays do not overlap
    # exceed what the compiler vectorises
    sums[0] = win[0]
    sums[1] = win[1]
    q = qa[0]
    a = qa[1]
    for i in range(q.size):
        q[i] = lp_k[i] - lp_j[i]
    for i in range(q.size):
        a[i] = abs(lp_k[i]) - abs(lp_j[i])
    raw[0] = img_j
    raw[1] = img_k


@_jit
def _apply1(mb: np.ndarray, nb: int, on: np.ndarray, off: np.ndarray, q: np.ndarray,
            a: np.ndarray, dl: np.ndarray, sign: float) -> None:  # pragma: no cover
    """Add ``sign`` times one queued equation (maps starting at the block's first pixel) to
    the ``nb`` pixels of block ``mb``: :meth:`NormalEquations.add`'s products, added in the
    same order (bit-identical sums). Weight 0 where the equation has no events or its ``dl``
    is NaN (a clipped frame value); selects, no branches, so that the pixel loop
    vectorises."""
    B = BLOCK
    for i in range(nb):
        c_on = on[i]
        c_off = off[i]
        ok = ((c_on + c_off) > 0) & (dl[i] == dl[i])
        ws = sign if ok else 0.0
        d = dl[i] if ok else 0.0
        p = np.float64(c_on - c_off)
        e = np.float64(c_on + c_off)
        qq = np.float64(q[i])
        aa = np.float64(a[i])
        wp = ws * p
        we = ws * e
        wq = ws * qq
        wa = ws * aa
        mb[i] += wp * p
        mb[B + i] += wp * e
        mb[2 * B + i] += wp * qq
        mb[3 * B + i] += wp * aa
        mb[4 * B + i] += we * e
        mb[5 * B + i] += we * qq
        mb[6 * B + i] += we * aa
        mb[7 * B + i] += wq * qq
        mb[8 * B + i] += wq * aa
        mb[9 * B + i] += wa * aa
        mb[10 * B + i] += wp * d
        mb[11 * B + i] += we * d
        mb[12 * B + i] += wq * d
        mb[13 * B + i] += wa * d
        mb[14 * B + i] += ws * d * d
        mb[15 * B + i] += ws


@_jit
def _apply2(mb: np.ndarray, nb: int, on1: np.ndarray, off1: np.ndarray, q1: np.ndarray,
            a1: np.ndarray, dl1: np.ndarray, sign1: float, on2: np.ndarray, off2: np.ndarray,
            q2: np.ndarray, a2: np.ndarray, dl2: np.ndarray,
            sign2: float) -> None:  # pragma: no cover
    """:func:`_apply1` of two equations in one pass over the block: ``m = (m + x1) + x2``,
    the same operations in the same order as two passes (bit-identical), with half the loads
    and stores of the block's sums."""
    B = BLOCK
    for i in range(nb):
        c1 = on1[i]
        o1 = off1[i]
        ok1 = ((c1 + o1) > 0) & (dl1[i] == dl1[i])
        ws1 = sign1 if ok1 else 0.0
        d1 = dl1[i] if ok1 else 0.0
        p1 = np.float64(c1 - o1)
        e1 = np.float64(c1 + o1)
        qq1 = np.float64(q1[i])
        aa1 = np.float64(a1[i])
        wp1 = ws1 * p1
        we1 = ws1 * e1
        wq1 = ws1 * qq1
        wa1 = ws1 * aa1
        c2 = on2[i]
        o2 = off2[i]
        ok2 = ((c2 + o2) > 0) & (dl2[i] == dl2[i])
        ws2 = sign2 if ok2 else 0.0
        d2 = dl2[i] if ok2 else 0.0
        p2 = np.float64(c2 - o2)
        e2 = np.float64(c2 + o2)
        qq2 = np.float64(q2[i])
        aa2 = np.float64(a2[i])
        wp2 = ws2 * p2
        we2 = ws2 * e2
        wq2 = ws2 * qq2
        wa2 = ws2 * aa2
        mb[i] = (mb[i] + wp1 * p1) + wp2 * p2
        mb[B + i] = (mb[B + i] + wp1 * e1) + wp2 * e2
        mb[2 * B + i] = (mb[2 * B + i] + wp1 * qq1) + wp2 * qq2
        mb[3 * B + i] = (mb[3 * B + i] + wp1 * aa1) + wp2 * aa2
        mb[4 * B + i] = (mb[4 * B + i] + we1 * e1) + we2 * e2
        mb[5 * B + i] = (mb[5 * B + i] + we1 * qq1) + we2 * qq2
        mb[6 * B + i] = (mb[6 * B + i] + we1 * aa1) + we2 * aa2
        mb[7 * B + i] = (mb[7 * B + i] + wq1 * qq1) + wq2 * qq2
        mb[8 * B + i] = (mb[8 * B + i] + wq1 * aa1) + wq2 * aa2
        mb[9 * B + i] = (mb[9 * B + i] + wa1 * aa1) + wa2 * aa2
        mb[10 * B + i] = (mb[10 * B + i] + wp1 * d1) + wp2 * d2
        mb[11 * B + i] = (mb[11 * B + i] + we1 * d1) + we2 * d2
        mb[12 * B + i] = (mb[12 * B + i] + wq1 * d1) + wq2 * d2
        mb[13 * B + i] = (mb[13 * B + i] + wa1 * d1) + wa2 * d2
        mb[14 * B + i] = (mb[14 * B + i] + ws1 * d1 * d1) + ws2 * d2 * d2
        mb[15 * B + i] = (mb[15 * B + i] + ws1) + ws2


@_jit
def _slot_dl(raw: np.ndarray, dl: np.ndarray, kinds: np.ndarray, lut: np.ndarray, k: int,
             s: int, nb: int, buf: np.ndarray) -> None:  # pragma: no cover
    """Slot ``k``'s ``dL`` of the ``nb`` pixels from ``s`` into ``buf``."""
    if kinds[k]:
        r_j = raw[k, 0]
        r_k = raw[k, 1]
        for ii in range(nb):
            buf[ii] = lut[r_k[s + ii]] - lut[r_j[s + ii]]
    else:
        d = dl[k]
        for ii in range(nb):
            buf[ii] = d[s + ii]


@_jit
def apply_blocks(m: np.ndarray, n: int, b_start: int, b_stop: int, sums: np.ndarray,
                 qa: np.ndarray, raw: np.ndarray, dl: np.ndarray, kinds: np.ndarray,
                 lut: np.ndarray, slots: np.ndarray, signs: np.ndarray,
                 buf: np.ndarray) -> None:  # pragma: no cover
    """Add the queued equations ``slots`` (with ``signs``, in order) to blocks ``b_start ..
    b_stop`` of the blocked normal equations ``m`` of ``n`` pixels, block by block (a block
    stays in cache while its equations are added). A slot's ``dL`` is ``lut[raw[1]] -
    lut[raw[0]]`` (``kinds`` True: 8-bit frames, ``lut`` NaN at the values not usable;
    computed per block into ``buf``, a table look-up does not vectorise) or ``dl`` (other
    frames, 0 where not usable, and so their counts). Equations go two at a time
    (:func:`_apply2`, ``buf`` holds two blocks' ``dL``), the same sums as one by one."""
    for b in range(b_start, b_stop):
        s = b * BLOCK
        nb = min(BLOCK, n - s)
        mb = m[b]
        r = 0
        while r < slots.size:
            k = slots[r]
            _slot_dl(raw, dl, kinds, lut, k, s, nb, buf[0])
            if r + 1 < slots.size:
                k2 = slots[r + 1]
                _slot_dl(raw, dl, kinds, lut, k2, s, nb, buf[1])
                _apply2(mb, nb, sums[k, 0, s:], sums[k, 1, s:], qa[k, 0, s:], qa[k, 1, s:],
                        buf[0], signs[r], sums[k2, 0, s:], sums[k2, 1, s:], qa[k2, 0, s:],
                        qa[k2, 1, s:], buf[1], signs[r + 1])
                r += 2
            else:
                _apply1(mb, nb, sums[k, 0, s:], sums[k, 1, s:], qa[k, 0, s:], qa[k, 1, s:],
                        buf[0], signs[r])
                r += 1


@_jit
def append_masked(mask: np.ndarray, a: np.ndarray, b: np.ndarray, nb: int, out_a: np.ndarray,
                  out_b: np.ndarray, pos: int) -> int:  # pragma: no cover
    """Append ``a[:nb][mask]`` and ``b[:nb][mask]`` at ``out[pos:]``; returns the new end."""
    for i in range(nb):
        if mask[i]:
            out_a[pos] = a[i]
            out_b[pos] = b[i]
            pos += 1
    return pos
