"""Pure numeric gait analysis: gap filling, resampling, Alg. 6, events and parameters.

This is the post-processing of ``../shared/reference/algorithms.md`` sections 3.6 and 5.
Every function is pure: numpy in, numpy (or frozen dataclasses) out, no I/O.

Conventions:

- time is axis 0 of every series; ``t`` is in seconds (float64, strictly increasing);
- NaN means missing; a row of a (F, D) series is missing when any of its values is NaN;
- positions are camera-space mm, heights are mm above the floor plane, angles are degrees;
- sample indices refer to the series a function was given (30 fps camera frames, or the
  100 Hz resampled series).

Gap filling (algorithms.md section 5, reading (b)): a missing stretch is replaced by one cubic
Bezier segment between the last sample before and the first sample after it, with the end
tangents estimated from the two samples on each side (one-sided differences; the chord slope
when a side has only one sample). The maximum gap is ``max_gap_s``: the time from the last
seen to the next seen sample. The default 0.3 s (up to 8 missing frames at 30 fps) covers the
arm-swing occlusions of the hip and thigh markers (about a third of a gait cycle at most); a
longer gap spans a large part of a swing, where a cubic cannot follow the foot, so it stays
missing.

Resampling: a non-uniform Catmull-Rom spline written as cubic Bezier segments,
``P1 = x_i + m_i h / 3`` and ``P2 = x_{i+1} - m_{i+1} h / 3`` with
``m_i = (x_{i+1} - x_{i-1}) / (t_{i+1} - t_{i-1})`` and ``h = t_{i+1} - t_i``. With uniform
frames this is exactly the recommended ``P1 = x_i + (x_{i+1} - x_{i-1}) / 6``. Evaluated at
``t_0 + k / rate``. Segments with a missing end stay missing.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

SIDES = ("L", "R")


# ---------------------------------------------------------------------------------------------
# gaps and resampling (algorithms.md section 5)


def missing_rows(x: np.ndarray) -> np.ndarray:
    """Rows of ``x`` (F,) or (F, D) that hold a NaN. Returns (F,) bool."""
    x = np.asarray(x, dtype=float)
    return ~np.isfinite(x) if x.ndim == 1 else ~np.all(np.isfinite(x), axis=1)


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of True in a 1-D bool array as inclusive (first, last) index pairs."""
    m = np.asarray(mask, dtype=bool)
    if m.size == 0:
        return []
    d = np.diff(np.concatenate(([0], m.view(np.int8), [0])))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1) - 1
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def runs_rows(mask: np.ndarray) -> list[list[tuple[int, int]]]:
    """:func:`runs` of every row of a 2-D bool array, in one set of numpy calls.

    mask : (R, N). Returns R lists of inclusive (first, last) pairs.
    """
    m = np.asarray(mask, dtype=bool)
    if m.shape[0] == 0:
        return []
    pad = np.zeros((m.shape[0], 1), dtype=np.int8)
    d = np.diff(np.concatenate((pad, m.view(np.int8), pad), axis=1), axis=1)
    # row-major order: by row, then by position, so starts and stops pair up
    row, starts = np.nonzero(d == 1)
    stops = np.nonzero(d == -1)[1] - 1
    bounds = np.searchsorted(row, np.arange(m.shape[0] + 1)).tolist()
    pairs = list(zip(starts.tolist(), stops.tolist(), strict=True))
    return [pairs[a:b] for a, b in itertools.pairwise(bounds)]


def _bezier(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, p3: np.ndarray, s: np.ndarray):
    s = s[:, None]
    u = 1.0 - s
    return u**3 * p0 + 3 * u**2 * s * p1 + 3 * u * s**2 * p2 + s**3 * p3


def fill_gaps(
    t: np.ndarray, x: np.ndarray, max_gap_s: float = 0.3
) -> tuple[np.ndarray, np.ndarray]:
    """Fill interior gaps with cubic Bezier segments (algorithms.md section 5, Rec. (b)).

    Parameters
    ----------
    t : (F,) seconds, increasing.
    x : (F,) or (F, D) series, NaN = missing (a row with any NaN is missing as a whole).
    max_gap_s : the longest fillable gap, measured from the last seen sample before it to the
        first seen sample after it. Gaps touching either end of the series are never filled.

    Returns
    -------
    filled : same shape as ``x``; filled rows hold the Bezier values.
    was_filled : (F,) bool, the rows that were filled.
    """
    x = np.asarray(x, dtype=float)
    flat = x.ndim == 1
    xs = x[:, None] if flat else x
    out, filled = fill_gaps_markers(t, xs[:, None, :], max_gap_s)
    return (out[:, 0, 0] if flat else out[:, 0]), filled[:, 0]


def fill_from_segment(
    t: np.ndarray,
    x: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    lateral: np.ndarray,
    max_gap_s: float = 0.3,
) -> np.ndarray:
    """Fill a marker's interior gaps from the segment it rides on (a rigid-body fill).

    Over a gap of ``x``, ``x`` keeps its coordinates in the segment's frame (u along the
    segment markers a -> b, v = lateral x u, w = u x v): they are interpolated linearly in
    time between the gap's two ends and mapped back through each frame's own segment. Each
    end's coordinates come from the nearest sample outside the gap, within ``max_gap_s`` of
    it, where ``x`` and the segment are both seen (the sample next to the gap, unless the
    segment is unseen there). Frames of the gap where the segment is unseen (or along
    ``lateral``), and gaps longer than ``max_gap_s`` (measured as :func:`fill_gaps` does),
    touching either end of the series or without such a sample at either end, are left as
    they are, for :func:`fill_gaps`.

    Why: :func:`fill_gaps` carries the marker's own velocity at the gap's ends into it. In
    terminal swing the ankle comes to rest within a few frames, so the Bezier over a
    seven-frame ankle gap overshot and the knee angle read 34 degrees where it was 13 (the
    simulated child's walk, btk_PiG_Motion3_FF left); the knee and tibia markers, seen
    through the gap, carry the shank's rotation.

    Parameters
    ----------
    t : (F,) s, increasing.
    x : (F, 3) the marker, mm, NaN = missing.
    a, b : (F, 3) two markers of the same segment (the knee and the tibia for the ankle).
    lateral : (3,) a direction across the segment (the sagittal plane's normal).
    max_gap_s : the longest gap filled.

    Returns
    -------
    (F, 3) ``x`` with those gaps filled.
    """
    t = np.asarray(t, dtype=float)
    out = np.array(x, dtype=float, copy=True)
    a = np.asarray(a, dtype=float)
    u = np.asarray(b, dtype=float) - a
    norm = np.linalg.norm(u, axis=1)
    u = u / np.where(norm > 0, norm, np.nan)[:, None]
    v = np.cross(np.asarray(lateral, dtype=float), u)
    vn = np.linalg.norm(v, axis=1)
    # a segment within ~1 degree of the lateral axis has no frame to speak of
    v = v / np.where(vn > 0.02, vn, np.nan)[:, None]
    basis = np.stack((u, v, np.cross(u, v)), axis=1)  # (F, 3, 3): rows u, v, w
    seen = np.isfinite(v).all(axis=1)
    miss = missing_rows(out)
    ref = seen & ~miss
    nt = len(t)
    for g0, g1 in runs(miss):
        lo, hi = g0 - 1, g1 + 1
        if lo < 0 or hi >= nt or not t[hi] - t[lo] <= max_gap_s + 1e-9:
            continue
        # a tibia marker unlabelled at the gap's edge need not forfeit the fill: the
        # ankle's place on the shank is the same a frame or two further out
        before = np.flatnonzero(ref[:g0] & (t[:g0] >= t[lo] - max_gap_s - 1e-9))
        after = g1 + 1 + np.flatnonzero(ref[g1 + 1 :] & (t[g1 + 1 :] <= t[hi] + max_gap_s + 1e-9))
        if before.size == 0 or after.size == 0:
            continue
        r0, r1 = int(before[-1]), int(after[0])
        ends = np.einsum("kij,kj->ki", basis[[r0, r1]], out[[r0, r1]] - a[[r0, r1]])
        k = np.arange(g0, g1 + 1)[seen[g0 : g1 + 1]]
        s = ((t[k] - t[r0]) / (t[r1] - t[r0]))[:, None]
        c = (1.0 - s) * ends[0] + s * ends[1]
        out[k] = a[k] + np.einsum("ki,kij->kj", c, basis[k])
    return out


def fill_gaps_markers(
    t: np.ndarray, x: np.ndarray, max_gap_s: float = 0.3, first_gap: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fill_gaps` of M series at once: t (F,), x (F, M, D) -> filled (F, M, D) and
    was_filled (F, M). Only markers with a gap are visited; gaps starting before frame
    ``first_gap`` are left as they are (the caller has them)."""
    t = np.asarray(t, dtype=float)
    xs = np.asarray(x, dtype=float)
    out = xs.copy()
    miss = ~np.all(np.isfinite(xs), axis=2)  # (F, M)
    filled = np.zeros(miss.shape, dtype=bool)
    nt = len(t)
    cols = np.flatnonzero(miss.any(axis=0)).tolist()
    for k, gaps in zip(cols, runs_rows(miss[:, cols].T), strict=True):
        mk = miss[:, k]
        xk = xs[:, k]
        for a, b in gaps:
            lo, hi = a - 1, b + 1  # the seen samples around the gap
            if lo < 0 or hi >= nt or a < first_gap:
                continue
            h = t[hi] - t[lo]
            if not h <= max_gap_s + 1e-9:
                continue
            chord = (xk[hi] - xk[lo]) / h
            # one-sided tangents from the neighbouring seen sample, else the chord slope
            m0 = (
                (xk[lo] - xk[lo - 1]) / (t[lo] - t[lo - 1]) if lo >= 1 and not mk[lo - 1] else chord
            )
            m3 = (
                (xk[hi + 1] - xk[hi]) / (t[hi + 1] - t[hi])
                if hi + 1 < nt and not mk[hi + 1]
                else chord
            )
            p0, p3 = xk[lo], xk[hi]
            p1, p2 = p0 + m0 * h / 3.0, p3 - m3 * h / 3.0
            s = (t[a : b + 1] - t[lo]) / h
            out[a : b + 1, k] = _bezier(p0, p1, p2, p3, s)
            filled[a : b + 1, k] = True
    return out, filled


def resample(t: np.ndarray, x: np.ndarray, rate_hz: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """Resample a series onto ``t[0] + k / rate_hz`` with Catmull-Rom Bezier segments.

    Parameters
    ----------
    t : (F,) seconds, strictly increasing (the frame timestamps, not assumed uniform).
    x : (F,) or (F, D); NaN rows stay missing: an output sample is NaN when either end of
        its segment is missing.
    rate_hz : output rate.

    Returns
    -------
    tq : (Q,) output times, ``t[0] + k / rate_hz`` up to ``t[-1]``.
    xq : (Q,) or (Q, D).
    """
    x = np.asarray(x, dtype=float)
    flat = x.ndim == 1
    xs = x[:, None] if flat else x
    tq, xq = resample_markers(t, xs[:, None, :], rate_hz)
    return tq, (xq[:, 0, 0] if flat else xq[:, 0])


def resample_markers(
    t: np.ndarray, x: np.ndarray, rate_hz: float = 100.0, first: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`resample` of M series at once (one set of numpy calls instead of M).

    t : (F,) s; x : (F, M, D), a marker missing in a frame when any of its D values is NaN.
    first : evaluate the output samples from this one on only (the caller has the others).
    Returns tq (Q,) and xq (Q - first, M, D). Each marker gets exactly what :func:`resample`
    gives it alone: every operation is elementwise over the marker axis, and an output
    sample depends on the four frames around its segment only.
    """
    t = np.asarray(t, dtype=float)
    xs = np.asarray(x, dtype=float)
    n = len(t)
    if n == 0:
        return np.zeros(0), np.zeros((0, *xs.shape[1:]))
    nq = int(np.floor((t[-1] - t[0]) * rate_hz + 1e-6)) + 1
    tq = t[0] + np.arange(nq) / rate_hz
    if n == 1:
        return tq, np.repeat(xs, nq - first, axis=0)
    seg = np.clip(np.searchsorted(t, tq[first:], side="right") - 1, 0, n - 2)
    if len(seg) == 0:
        return tq, np.zeros((0, *xs.shape[1:]))
    # frames from one before the first segment on: the tangent of a frame needs its
    # neighbours, and no sample evaluated here uses the tangent of the frame j0 itself
    j0 = max(int(seg[0]) - 1, 0)
    t, xs, seg = t[j0:], xs[j0:], seg - j0
    n = len(t)
    miss = ~np.all(np.isfinite(xs), axis=2)  # (F, M)
    # tangents: central difference where both neighbours are seen, else one-sided
    m = np.full_like(xs, np.nan)
    ok = ~miss
    prev_ok = np.concatenate((np.zeros((1, ok.shape[1]), dtype=bool), ok[:-1])) & ok
    next_ok = np.concatenate((ok[1:], np.zeros((1, ok.shape[1]), dtype=bool))) & ok
    i = np.arange(n)
    ip, inx = np.maximum(i - 1, 0), np.minimum(i + 1, n - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        central = (xs[inx] - xs[ip]) / (t[inx] - t[ip])[:, None, None]
        forward = (xs[inx] - xs) / (t[inx] - t)[:, None, None]
        backward = (xs - xs[ip]) / (t - t[ip])[:, None, None]
    m[prev_ok & next_ok] = central[prev_ok & next_ok]
    m[next_ok & ~prev_ok] = forward[next_ok & ~prev_ok]
    m[prev_ok & ~next_ok] = backward[prev_ok & ~next_ok]
    m[ok & ~prev_ok & ~next_ok] = 0.0
    h = t[seg + 1] - t[seg]
    s = (tq[first:] - t[seg]) / h
    p0, p3 = xs[seg], xs[seg + 1]
    p1 = p0 + m[seg] * (h / 3.0)[:, None, None]
    p2 = p3 - m[seg + 1] * (h / 3.0)[:, None, None]
    s2 = s[:, None, None]
    u = 1.0 - s2
    xq = u**3 * p0 + 3 * u**2 * s2 * p1 + 3 * u * s2**2 * p2 + s2**3 * p3
    # exact hits on a seen sample keep it even when the next one is missing
    exact = np.isclose(s, 0.0, atol=1e-9)[:, None] & ~miss[seg]  # (Q, M)
    xq[exact] = p0[exact]
    bad = (miss[seg] | miss[seg + 1]) & ~exact
    xq[bad] = np.nan
    return tq, xq


@dataclass(frozen=True)
class Resampled:
    """Markers gap-filled and resampled (:func:`fill_resample_markers`), kept with their
    input so that the series can be extended when frames are added.

    t : (F,) s; x : (F, M, D) input; filled : (F, M, D); was_filled : (F, M) bool;
    tq : (Q,); xq : (Q, M, D).
    """

    t: np.ndarray
    x: np.ndarray
    filled: np.ndarray
    was_filled: np.ndarray
    tq: np.ndarray
    xq: np.ndarray
    max_gap_s: float
    rate_hz: float


def _first_difference(a: np.ndarray, b: np.ndarray) -> int:
    """The first index along axis 0 where ``a`` and ``b[:len(a)]`` differ bit for bit
    (``len(a)`` if none; NaN equals NaN)."""
    n = min(len(a), len(b))
    da = np.ascontiguousarray(a[:n]).view(np.uint8).reshape(n, -1)
    db = np.ascontiguousarray(b[:n]).view(np.uint8).reshape(n, -1)
    diff = np.flatnonzero((da != db).any(axis=1))
    return int(diff[0]) if diff.size else n


def _stable_frames(t: np.ndarray, x: np.ndarray, max_gap_s: float, prev: Resampled) -> int:
    """How many leading frames of (t, x) fill exactly as ``prev`` filled them.

    Per marker: up to its first frame that differs from ``prev`` (d), except a gap that
    reaches within two frames of d, which starts the changed part, unless it was left
    unfilled before and is still unfillable (a marker out of view at the end stays so).
    """
    n0 = len(prev.t)
    d_t = _first_difference(prev.t, t)
    # per marker, the first frame that differs from prev (bit for bit)
    changed = (
        np.ascontiguousarray(prev.x).view(np.uint8).reshape(n0, x.shape[1], -1)
        != np.ascontiguousarray(x[:n0]).view(np.uint8).reshape(n0, x.shape[1], -1)
    ).any(axis=2)
    first = np.where(changed.any(axis=0), changed.argmax(axis=0), n0)
    d = np.minimum(first, d_t).tolist()
    # the gaps near the changed frames decide; look at a window before them first (a long
    # trial has many gaps), and at everything if a gap that matters runs out of the window
    lo = max(min(d) - 64, 0)
    found = _stable_in(t, x, max_gap_s, prev, d, lo)
    return found if found is not None else _stable_in(t, x, max_gap_s, prev, d, 0)  # type: ignore[return-value]


def _stable_in(
    t: np.ndarray, x: np.ndarray, max_gap_s: float, prev: Resampled, d: list[int], lo: int
) -> int | None:
    """:func:`_stable_frames` from the gaps after frame ``lo``; None when a gap that
    matters begins before ``lo`` (its start is then unknown here)."""
    nt = len(t)
    n0 = len(prev.t)
    stable = min(d)
    miss = ~np.all(np.isfinite(x[lo:]), axis=2)  # (F - lo, M)
    cols = np.flatnonzero(miss.any(axis=0)).tolist()
    gaps_of = {
        k: [(a + lo, b + lo) for a, b in gaps]
        for k, gaps in zip(cols, runs_rows(miss[:, cols].T), strict=True)
    }

    def cut(a: int, k: int) -> bool:  # the gap may begin before the window
        return a == lo and lo > 0 and bool(miss[0, k])

    for k, dk in enumerate(d):
        for a, b in gaps_of.get(k, ()):
            if b + 2 < dk:
                continue
            if a >= stable:
                break
            if cut(a, k):
                return None
            g0, g1 = a - 1, b + 1
            fillable = g0 >= 0 and g1 < nt and t[g1] - t[g0] <= max_gap_s + 1e-9
            if fillable or prev.was_filled[a : min(b + 1, n0), k].any():
                stable = min(stable, a)
                break
    # the tail is filled from ``stable`` on: no fillable gap of any marker may straddle it
    moved = True
    while moved:
        moved = False
        if stable < lo:
            return None
        for k in np.flatnonzero(miss[stable - lo] if stable < nt else ()).tolist():
            for a, b in gaps_of[k]:
                if a < stable <= b:
                    if cut(a, k):
                        return None
                    g0, g1 = a - 1, b + 1
                    if g0 >= 0 and g1 < nt and t[g1] - t[g0] <= max_gap_s + 1e-9:
                        stable, moved = a, True
                    break
    return stable


def fill_resample_markers(
    t: np.ndarray,
    x: np.ndarray,
    max_gap_s: float = 0.3,
    rate_hz: float = 100.0,
    prev: Resampled | None = None,
) -> Resampled:
    """:func:`fill_gaps_markers` then :func:`resample_markers`, reusing ``prev`` where the
    result cannot differ: the same values as computing from scratch, bit for bit.

    A filled gap depends on the frames from two before to one after it, a resampled sample
    on the frames from one before to two after its segment. When the frames of ``prev`` are
    a prefix of (t, x) up to frame d (a growing trial), every gap ending two frames before
    d keeps its filling, and every output sample whose segment ends three frames before the
    first changed filled frame keeps its value; only the rest is computed.

    t : (F,) s; x : (F, M, D), NaN = missing. Returns a :class:`Resampled`.
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    stable = 0  # frames whose filled values are those of prev
    if (
        prev is not None
        and prev.x.shape[1:] == x.shape[1:]
        and (prev.max_gap_s, prev.rate_hz) == (max_gap_s, rate_hz)
        and len(prev.t) <= len(t)
        and len(t) >= 2
    ):
        stable = _stable_frames(t, x, max_gap_s, prev)
    if stable < 3 or prev is None:
        filled, was = fill_gaps_markers(t, x, max_gap_s)
        tq, xq = resample_markers(t, filled, rate_hz)
        return Resampled(t, x, filled, was, tq, xq, max_gap_s, rate_hz)
    start = max(stable - 2, 0)  # gaps from ``stable`` on see two frames before them
    tail, was = fill_gaps_markers(t[start:], x[start:], max_gap_s, first_gap=stable - start)
    filled = np.concatenate((prev.filled[:stable], tail[stable - start :]))
    was = np.concatenate((prev.was_filled[:stable], was[stable - start :]))
    tq_all = t[0] + np.arange(int(np.floor((t[-1] - t[0]) * rate_hz + 1e-6)) + 1) / rate_hz
    keep = int(np.searchsorted(tq_all, t[stable - 2], side="left"))
    keep = min(keep, len(prev.xq))
    tq, xq_tail = resample_markers(t, filled, rate_hz, first=keep)
    xq = np.concatenate((prev.xq[:keep], xq_tail))
    return Resampled(t, x, filled, was, tq, xq, max_gap_s, rate_hz)


def _window_sums(
    t: np.ndarray, x: np.ndarray, window_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sums over the seen samples within ``window_s`` / 2 of each time, from prefix sums
    (O(N)): count n, sum t, sum x, sum t^2, sum t*x, with t counted from t[0].

    t : (N,) s, increasing; x : (N,) or (N, M) (M series on the same times, each summed on
    its own, as the same prefix sums down axis 0) with NaN = missing. Returns the five sums,
    shaped as x, and the centred times ``tc`` (N,) or (N, 1).
    """
    ok = np.isfinite(x)
    tc = (t - t[0]).reshape(-1, *([1] * (x.ndim - 1)))
    w = ok.astype(float)
    xv = np.where(ok, x, 0.0)
    tw = np.where(ok, tc, 0.0)

    def csum(a: np.ndarray) -> np.ndarray:
        return np.concatenate((np.zeros((1, *a.shape[1:])), np.cumsum(a, axis=0)))

    lo = np.searchsorted(t, t - window_s / 2 - 1e-9, side="left")
    hi = np.searchsorted(t, t + window_s / 2 + 1e-9, side="right")
    sums = [csum(a) for a in (w, tw, xv, tw * tc, tw * xv)]
    n0, st, sx, stt, stx = (c[hi] - c[lo] for c in sums)
    return n0, st, sx, stt, stx, tc


def local_linear(
    t: np.ndarray, x: np.ndarray, window_s: float, at_missing: bool = False
) -> np.ndarray:
    """A least-squares line through the seen samples within ``window_s`` / 2 of each time,
    evaluated there (a NaN-aware, first-order Savitzky-Golay smoother on timestamps).

    t : (N,) s; x : (N,), or (N, M) for M series on the same times (each fitted on its
    own), with NaN = missing. Returns x's shape, NaN where fewer than 3 samples or a missing
    input sample (a gap is not filled here, unless ``at_missing``: then the line is
    evaluated at missing samples too).
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    ok = np.isfinite(x)
    if len(t) == 0:
        return np.zeros(x.shape)
    n0, st, sx, stt, stx, tc = _window_sums(t, x, window_s)
    den = n0 * stt - st * st
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.where(den > 1e-12, (n0 * stx - st * sx) / den, 0.0)
        mean_t, mean_x = st / n0, sx / n0
        out = mean_x + slope * (tc - mean_t)
    out[(n0 < 3) | (~ok & (not at_missing))] = np.nan
    return out


def extend_back(
    frame_index: np.ndarray,
    pixel: np.ndarray,
    position: np.ndarray,
    spare_pixel: Sequence[np.ndarray],
    spare_position: Sequence[np.ndarray],
    markers: Sequence[int],
    in_pass: np.ndarray,
    max_frames: int = 10,
    gate_px: float = 6.0,
    sep_px: float = 8.0,
    depth_mm: float = 60.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marker tracks extended back in time onto blobs the labeller left unnamed.

    A labeller working frame by frame often names a far heel only once it has landed: in
    its swing the heel's blob was there but ambiguous, and Alg. 6 then sees no descent to
    time the heel strike on. Once a run of labels exists, the blob it came from is the one
    that continues it backwards. From the first two samples of each run of ``markers``
    (consecutive frames), the track is followed back one frame at a time: the predicted
    pixel continues the last image velocity, and the unnamed blob nearest it is taken when

    - it lies within ``gate_px`` plus half the image speed of the prediction;
    - no other unnamed blob, and no other marker's own prediction (its last pixel plus its
      velocity), lies within ``max(2 d, d + sep_px)`` of it (d: its distance), so a foot's
      markers cannot trade places;
    - no named marker of that frame is nearer the prediction;
    - its depth lies within ``depth_mm`` of the track's last depth;
    - the frame lies in a walking pass (``in_pass``; the labeller knows the direction).

    It stops at the first frame that fails, after ``max_frames`` frames, or at a dropped
    frame. The runs extended are those of the labels given (not of samples added).
    Departure: the paper labels frame by frame only.

    Parameters
    ----------
    frame_index : (F,) camera frame numbers, increasing.
    pixel, position : (F, 20, 2) px and (F, 20, 3) mm of the named markers, NaN = missing.
    spare_pixel, spare_position : F arrays (M_f, 2) px and (M_f, 3) mm of the blobs left
        unnamed in each frame (the position as the marker would be published there).
    markers : marker indices to extend. in_pass : (F,) bool.

    Returns
    -------
    (pixel, position, added): copies with the samples added, and (F, 20) bool marking them.
    """
    pixel = np.array(pixel, dtype=float)
    position = np.array(position, dtype=float)
    fi = np.asarray(frame_index, dtype=np.int64)
    n = len(fi)
    named = np.isfinite(pixel).all(axis=2)
    seen = named.copy()  # named, or added here
    if n < 3 or max_frames <= 0:
        return pixel, position, seen & ~named
    follows = np.zeros(n, dtype=bool)  # frame i is the one right after frame i - 1
    follows[1:] = np.diff(fi) == 1
    taken: list[set[int]] = [set() for _ in range(n)]
    for k in markers:
        # a run's first two labels; a run extended back stops at the next run's end, so the
        # anchors do not change as tracks grow
        first = named[1:-1, k] & named[2:, k] & follows[2:] & ~named[:-2, k]
        for f in np.flatnonzero(first)[::-1] + 1:
            cur = int(f)
            for _ in range(max_frames):
                g = cur - 1
                if g < 0 or not follows[cur] or not in_pass[g] or seen[g, k]:
                    break
                v = pixel[cur, k] - pixel[cur + 1, k]
                pred = pixel[cur, k] + v
                cand = np.asarray(spare_pixel[g], dtype=float).reshape(-1, 2)
                free = np.array([i for i in range(len(cand)) if i not in taken[g]], dtype=int)
                if not free.size:
                    break
                d = np.hypot(*(cand[free] - pred).T)
                order = np.argsort(d, kind="stable")
                d0 = float(d[order[0]])
                if d0 > gate_px + 0.5 * float(np.hypot(*v)):
                    break
                clear = max(2.0 * max(d0, 1.0), d0 + sep_px)
                if len(order) > 1 and d[order[1]] < clear:
                    break
                pick = cand[free[order[0]]]
                if seen[g].any() and np.hypot(*(pixel[g, seen[g]] - pred).T).min() < d0:
                    break
                others = [j for j in np.flatnonzero(seen[cur]) if j != k]
                if others:
                    vj = np.where(
                        seen[cur + 1, others][:, None],
                        pixel[cur, others] - pixel[cur + 1, others],
                        0.0,
                    )
                    if np.hypot(*(pixel[cur, others] + vj - pick).T).min() < clear:
                        break
                p = np.asarray(spare_position[g], dtype=float).reshape(-1, 3)[free[order[0]]]
                # the last depth, not its velocity: walking across the view a heel's depth
                # hardly moves, and the difference of two silhouette depths is mostly noise
                if not (np.isfinite(p).all() and abs(p[2] - position[cur, k, 2]) <= depth_mm):
                    break
                pixel[g, k], position[g, k] = pick, p
                seen[g, k] = True
                taken[g].add(int(free[order[0]]))
                cur = g
    return pixel, position, seen & ~named


def reject_outliers(pos: np.ndarray, max_dev_mm: float = 40.0, half: int = 2) -> np.ndarray:
    """Mark as missing the samples that jump away from their neighbours (a Hampel filter).

    A wrongly labelled marker in one or two frames (another marker's blob given this name)
    sits far from the median of its neighbours, while smooth motion stays close. Neighbours
    are taken in symmetric pairs (o = 1..``half`` frames before and after, both seen), so the
    median does not lag a moving marker; farther than ``max_dev_mm`` from it the sample
    becomes NaN, for the gap filler. A sample without a seen pair is kept.
    ``max_dev_mm <= 0`` returns the input.

    pos : (F, M, 3) mm, NaN = missing. Returns (F, M, 3).
    """
    pos = np.asarray(pos, dtype=float)
    out = pos.copy()
    n = len(pos)
    if max_dev_mm <= 0 or n < 3:
        return out
    pad = np.full((half, *pos.shape[1:]), np.nan)
    padded = np.concatenate([pad, pos, pad])
    # the median of the neighbours taken in symmetric pairs (o frames before and after, both
    # seen): it sits on a smoothly moving marker, and one wrong neighbour cannot drag it
    parts = []
    for o in range(1, half + 1):
        before = padded[half - o : half - o + n]
        after = padded[half + o : half + o + n]
        pair = np.isfinite(before).all(axis=-1) & np.isfinite(after).all(axis=-1)
        parts += [
            np.where(pair[..., None], before, np.nan),
            np.where(pair[..., None], after, np.nan),
        ]
    neigh = np.stack(parts, axis=-1)  # (F, M, 3, 2 half)
    enough = np.isfinite(neigh[..., 0, :]).any(axis=-1)
    med = nanmedian_last(neigh)
    dev = np.linalg.norm(pos - med, axis=-1)
    bad = enough & np.isfinite(dev) & (dev > max_dev_mm)
    out[bad] = np.nan
    return out


OUTLIER_REF_FPS = 30.0  # the frame rate the outlier bounds are given for


def outlier_bound(max_dev_mm: float, fps: float) -> float:
    """A :func:`reject_outliers` bound given at 30 fps, for a camera running at ``fps``.

    Smooth motion departs from the median of its neighbours by about its acceleration times
    the frame interval squared, so below 30 fps the bound grows with (30 / fps)^2 (four times
    at 15 fps, where a swinging ankle's real samples would otherwise be dropped); above 30
    fps it stays as given. ``max_dev_mm <= 0`` (off) is returned unchanged.
    """
    if max_dev_mm <= 0 or not fps > 0:
        return max_dev_mm
    return max_dev_mm * max(1.0, (OUTLIER_REF_FPS / fps) ** 2)


def nanmedian_last(x: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN, NaN where all are NaN; (..., K) -> (...).

    The same values as ``np.nanmedian(x, axis=-1)`` (mean of the two middle values, as
    ``(low + high) / 2``), without its per-call cost on many short rows or its warning.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:  # one row (a contact's heel positions): fewer numpy calls
        v = np.sort(x[~np.isnan(x)]).tolist()
        n = len(v)
        if n == 0:
            return np.array(np.nan)
        return np.array(v[n // 2] if n % 2 else (v[n // 2 - 1] + v[n // 2]) / 2.0)
    srt = np.sort(x, axis=-1)  # NaN sorts last
    count = (~np.isnan(x)).sum(axis=-1, keepdims=True)
    high = count // 2
    low = np.where(count % 2 == 1, high, high - 1)
    idx = np.concatenate((np.maximum(low, 0), high), axis=-1)
    pair = np.take_along_axis(srt, np.minimum(idx, x.shape[-1] - 1), axis=-1)
    with np.errstate(invalid="ignore"):
        med = (pair[..., 0] + pair[..., 1]) / 2.0
    return np.where(count[..., 0] > 0, med, np.nan)


def percentile_linear(x: np.ndarray, q: Sequence[float]) -> list[float]:
    """``np.percentile(x, q)`` (the default "linear" method) of a 1-D array of finite values.

    The same arithmetic as numpy (virtual index ``(n - 1) q / 100``, its ``_lerp``), on one
    sort: numpy's generic quantile machinery costs far more than the sort on a walking pass.
    x : (N,), N >= 1, finite. Returns one float per entry of ``q``.
    """
    xs = np.sort(np.asarray(x, dtype=float)).tolist()
    n = len(xs)
    out = []
    for qq in q:
        v = (n - 1) * (float(qq) / 100)
        if v >= n - 1:
            out.append(xs[-1])
            continue
        i = math.floor(v)
        a, b, g = xs[i], xs[i + 1], v - i
        d = b - a
        out.append(b - d * (1 - g) if g >= 0.5 else a + d * g)
    return out


def segment_outliers(a: np.ndarray, b: np.ndarray, tol: float = 0.15) -> np.ndarray:
    """Samples where the distance |a - b| of two markers on one rigid segment departs from
    its median over the series by more than ``tol`` (relative). (F, 3) x2 -> (F,) bool."""
    d = np.linalg.norm(np.asarray(a, dtype=float) - np.asarray(b, dtype=float), axis=-1)
    ok = np.isfinite(d)
    if ok.sum() < 3:
        return np.zeros(len(d), dtype=bool)
    ref = float(nanmedian_last(d[ok]))  # np.median of these finite values, cheaper
    return ok & (np.abs(d - ref) > tol * ref)


def chain_outliers(
    hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray, tol: float = 0.15
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The wrong sample of a leg's HIP-KNE-ANK chain, from its two segment lengths.

    In a frame where all three markers are seen, a thigh length that departs from its
    median over the series by more than ``tol`` (relative) while the shank's does not names
    the hip; a shank alone names the ankle; both name the knee, which they share. A frame
    with one or two of the markers is not judged (a pair cannot say which of its two is
    wrong). hip, knee, ankle : (F, 3) mm, NaN = missing. Returns three (F,) bool masks
    (hip, knee, ankle): True = drop that sample.
    """
    thigh = segment_outliers(hip, knee, tol)
    shank = segment_outliers(knee, ankle, tol)
    seen = np.isfinite(np.stack([hip, knee, ankle])).all(axis=(0, 2))
    return seen & thigh & ~shank, seen & thigh & shank, seen & shank & ~thigh


def running_median(t: np.ndarray, z: np.ndarray, window_s: float) -> np.ndarray:
    """Median of the seen values within ``window_s`` / 2 of each sample, by index (a dropped
    frame widens the window a little). z : (F, M), NaN = missing. Returns (F, M), NaN where
    fewer than a quarter of the window is seen on either side of the sample (at the ends of
    the data, or of a marker's view, a one-sided median would follow whatever came last)."""
    z = np.asarray(z, dtype=float)
    n = len(t)
    if n < 2:
        return np.full(z.shape, np.nan)
    dt = float(np.median(np.diff(t)))
    half = max(2, round(0.5 * window_s / dt)) if dt > 0 else 2
    pad = np.full((half, *z.shape[1:]), np.nan)
    zp = np.concatenate([pad, z, pad])
    win = np.lib.stride_tricks.sliding_window_view(zp, 2 * half + 1, axis=0)  # (F, M, K)
    seen = ~np.isnan(win)
    need = half // 2
    both = (seen[..., :half].sum(axis=-1) >= need) & (seen[..., half + 1 :].sum(axis=-1) >= need)
    return np.where(both, nanmedian_last(win), np.nan)


def depth_outliers(t: np.ndarray, z: np.ndarray, window_s: float, tol_mm: float) -> np.ndarray:
    """Depths that leave their running median by more than ``tol_mm`` (a wrong layer).

    In a side view a marker's depth is the body's position across the walkway: it drifts
    slowly (a straight walk at an angle to the image plane, the trunk's sway of a few cm),
    while a depth taken from a limb in front of the marker, or from the floor, is off by
    tens of mm for a few frames. The median over ``window_s`` (:func:`running_median`)
    follows the drift and ignores runs shorter than half the window; where it is one-sided
    (the ends of a marker's view) nothing is judged.

    t : (F,) s; z : (F, M) depth mm, NaN = missing. Returns (F, M) bool, True = outlier.
    ``tol_mm <= 0`` or ``window_s <= 0``: nothing is an outlier.
    """
    z = np.asarray(z, dtype=float)
    if tol_mm <= 0 or window_s <= 0 or len(t) < 3:
        return np.zeros(z.shape, dtype=bool)
    med = running_median(t, z, window_s)
    with np.errstate(invalid="ignore"):
        return np.abs(z - med) > tol_mm


def smooth_depth(
    t: np.ndarray,
    pos: np.ndarray,
    window_s: float,
    outlier_mm: float = 0.0,
    outlier_window_s: float = 1.0,
    outlier_markers: Sequence[int] | None = None,
) -> np.ndarray:
    """Move each marker along its viewing ray to a smoothed depth (departure, see below).

    In a side view the depth (Z) of a marker changes slowly (it is the body's lateral axis)
    while the ToF depth noise of Alg. 3 is large; the pixel (u, v) is precise. Each position
    p = Z (x_n, y_n, 1) is therefore rescaled to ``Z_s / Z`` with Z_s the local-linear fit of
    Z over ``window_s``: the image-plane trajectory is untouched, only the depth along the
    ray is smoothed. With ``outlier_mm`` > 0, depths more than that from their running
    median over ``outlier_window_s`` (:func:`depth_outliers`) are left out of the fit and
    take the fitted depth of their neighbours instead of their own, keeping their pixel
    (the precise part), or are dropped where no neighbour is near enough (only the markers
    ``outlier_markers``, all when None). ``window_s <= 0`` returns the input.

    t : (F,) s; pos : (F, M, 3) camera mm, NaN = missing. Returns (F, M, 3).
    """
    pos = np.asarray(pos, dtype=float)
    if window_s <= 0 or len(t) < 3:
        return pos.copy()
    out = pos.copy()
    z = pos[:, :, 2]
    judged = np.arange(pos.shape[1]) if outlier_markers is None else np.asarray(outlier_markers)
    bad = np.zeros(z.shape, dtype=bool)
    if judged.size:  # each marker's running median is its own: only the judged are computed
        bad[:, judged] = depth_outliers(t, z[:, judged], outlier_window_s, outlier_mm)
    zs = local_linear(t, np.where(bad, np.nan, z), window_s, at_missing=True)  # (F, M)
    zs[~bad & ~np.isfinite(z)] = np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(np.isfinite(zs) & (z > 0), zs / z, 1.0)
    out *= scale[:, :, None]
    # in the middle of a longer wrong run no seen depth is near enough: the sample is
    # dropped for the gap filler (the running median in its place was worse: knee
    # RMSE 1.97 / 4.64 deg against 1.27 / 1.78 on the bundled walks)
    out[bad & ~np.isfinite(zs)] = np.nan
    return out


# ---------------------------------------------------------------------------------------------
# geometry


def knee_flexion(
    hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray, lateral: np.ndarray | None = None
) -> np.ndarray:
    """Knee flexion = 180 deg minus the angle HIP-KNE-ANK (algorithms.md section 5).

    Parameters
    ----------
    hip, knee, ankle : (..., 3) positions, mm.
    lateral : optional (3,) unit vector normal to the sagittal plane: the angle is then
        measured between the segments projected onto that plane (sagittal knee flexion).

    Returns
    -------
    (...) degrees; 0 = straight, positive = flexed; NaN where a marker is missing or two
    coincide.
    """
    a = np.asarray(hip, dtype=float) - np.asarray(knee, dtype=float)
    b = np.asarray(ankle, dtype=float) - np.asarray(knee, dtype=float)
    if lateral is not None:
        n = np.asarray(lateral, dtype=float)
        a = a - (a @ n)[..., None] * n
        b = b - (b @ n)[..., None] * n
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.sum(a * b, axis=-1) / (na * nb)
        # atan2 of |cross| and dot is accurate near straight legs, where arccos is not
        ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), c * na * nb))
    ang = np.where((na > 0) & (nb > 0), ang, np.nan)
    return 180.0 - ang


def plane_height(points: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Signed height above a plane ``(nx, ny, nz, d)`` (unit normal up): ``n . p + d``.

    points : (..., 3) mm. Returns (...) mm.
    """
    pl = np.asarray(plane, dtype=float)
    n = pl[:3] / np.linalg.norm(pl[:3])
    return np.asarray(points, dtype=float) @ n + pl[3] / np.linalg.norm(pl[:3])


def lateral_axis(plane: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Unit normal of the sagittal plane: floor normal x walking axis. (3,)"""
    n = np.asarray(plane[:3], dtype=float)
    lat = np.cross(n / np.linalg.norm(n), np.asarray(axis, dtype=float))
    return lat / np.linalg.norm(lat)


def walking_axis(start: np.ndarray, end: np.ndarray, plane: np.ndarray | None = None) -> np.ndarray:
    """Unit vector from the start to the end point, made parallel to the floor. (3,)"""
    u = np.asarray(end, dtype=float) - np.asarray(start, dtype=float)
    if plane is not None:
        n = np.asarray(plane[:3], dtype=float)
        n = n / np.linalg.norm(n)
        u = u - (u @ n) * n
    norm = np.linalg.norm(u)
    if not norm > 0:
        raise ValueError(f"walking start {start} and end {end} give no direction")
    return u / norm


def progression(points: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Coordinate along the walking axis: ``(p - origin) . axis``. (..., 3) -> (...) mm."""
    return (np.asarray(points, dtype=float) - np.asarray(origin, dtype=float)) @ np.asarray(axis)


def line_of_progression(
    t: np.ndarray,
    points: np.ndarray,
    plane: np.ndarray,
    ref: np.ndarray,
    min_span_s: float = 0.5,
) -> np.ndarray:
    """Direction the subject actually walked during one pass, parallel to the floor. (3,)

    Step and stride length are distances along the subject's line of progression (the
    clinical footprint definition), not along the walkway drawn at calibration: an axis off
    by theta turns the step width w between the heels into a step-length error of
    w sin(theta), alternating in sign between left and right steps. Each body marker's
    least-squares velocity over the pass (slope of its position against time) is taken; these
    are summed weighted by the samples each rests on, and the sum is projected onto the floor.
    A marker's own slope does not move when other markers enter or leave the view (a mean of
    the markers seen would jump), and whole strides of lateral sway average out.

    Parameters
    ----------
    t : (N,) s. points : (N, M, 3) mm, body markers (pelvis, trunk), NaN = missing.
    plane : (4,) floor plane ``(nx, ny, nz, d)``. ref : (3,) unit walking axis signed in the
        direction of this pass (gives the sign; returned when no direction can be measured).
    min_span_s : a marker counts only when seen (at least 3 samples) over this long.

    Returns
    -------
    (3,) unit vector in the floor plane, ``@ ref > 0``; ``ref`` itself when no marker counts
    or the measured motion runs against ``ref`` (not this pass's walk).
    """
    t = np.asarray(t, dtype=float)
    pts = np.asarray(points, dtype=float)
    ref = np.asarray(ref, dtype=float)
    n = np.asarray(plane[:3], dtype=float)
    n = n / np.linalg.norm(n)
    v = np.zeros(3)
    for k in range(pts.shape[1]):
        ok = np.isfinite(pts[:, k]).all(axis=1)
        if ok.sum() < 3 or t[ok][-1] - t[ok][0] < min_span_s:
            continue
        v += ok.sum() * ls_slope(t[ok], pts[ok, k])
    v = v - (v @ n) * n
    norm = float(np.linalg.norm(v))
    if not norm > 0 or not v @ ref > 0:
        return ref
    return v / norm


# ---------------------------------------------------------------------------------------------
# Alg. 6: inflection-point search (water-filling reading, algorithms.md section 3.6 Rec.)


@dataclass(frozen=True)
class FlatRange:
    """One flat range of a trajectory (a valley where the marker rests on the floor).

    ``left``/``right`` are inclusive sample indices. An end is ``locked`` when the water
    stopped spreading there (an inflection point eta); it is ``open`` when the range runs
    into the start or end of the data (or a missing stretch), so that end is no event.
    ``born`` is the normalised level at which the range first appeared.
    """

    left: int
    right: int
    left_locked: bool
    right_locked: bool
    left_open: bool
    right_open: bool
    born: float
    left_level: float = float("nan")
    right_level: float = float("nan")

    @property
    def length(self) -> int:
        return self.right - self.left + 1


@dataclass(frozen=True)
class InflectionResult:
    """Output of :func:`inflection_search`.

    ranges : the kept flat ranges, in time order.
    peaks : sample index of the highest point between consecutive kept ranges (rho).
    lo, hi : the heights mapped to 0 and 1 by the normalisation.
    """

    ranges: tuple[FlatRange, ...]
    peaks: tuple[int, ...]
    lo: float
    hi: float
    all_ranges: tuple[FlatRange, ...] = field(default=())


@dataclass(slots=True)
class _Range:  # mutable working copy inside inflection_search only
    left: int
    right: int
    born: float
    left_locked: bool = False
    right_locked: bool = False
    left_level: float = float("nan")
    right_level: float = float("nan")
    # bounds at the start of the current level; -1 for a range born at this level
    old_left: int = -1
    old_right: int = -1


def level_runs(y: np.ndarray, levels: np.ndarray) -> list[list[tuple[int, int]]]:
    """:func:`runs` of ``y <= level`` for every level at once (NaN is never below).

    y : (N,); levels : (L,). Returns L lists of inclusive (first, last) pairs. One 2-D pass
    instead of L small ones: the per-call cost of numpy dominates on a walking pass.
    """
    if len(y) == 0 or len(levels) == 0:
        return [[] for _ in levels]
    with np.errstate(invalid="ignore"):
        return runs_rows(y[None, :] <= levels[:, None])


def inflection_search(
    y: np.ndarray,
    gamma: float = 0.05,
    xi: float = 0.33,
    phi: float = 0.33,
    tau: int = 3,
    max_born: float = 0.25,
    min_swing: float = 0.5,
) -> InflectionResult:
    """Alg. 6 as water-filling: find the flat valleys of a height trajectory.

    Implements algorithms.md section 3.6 Rec. R0-R6. The heights are normalised to [0, 1]
    (R0; the 1st and 99th percentiles map to 0 and 1, so a single outlier cannot squash the
    scale). For each level k = gamma, 2 gamma, ..., 1 the samples at or below k form runs
    (R2). A run meeting no range starts one; a run over one or more ranges moves only their
    unlocked ends (R3); two ranges whose facing ends are both unlocked merge (the valley floor
    was split by noise). An end that grew by less than ``xi`` (left) or ``phi`` (right) of the
    range length from one level to the next is locked at its previous position (R4): the water
    has reached the steep wall. Ranges are kept (R5) when their inner ends are locked (an end
    at the data boundary is open, not locked), they are longer than ``tau`` samples and they
    were born at a level <= ``max_born`` (a valley that only appears high up, such as the
    toe's mid-swing clearance dip, is not a floor contact; this replaces the printed line-18
    test, which reduces to a tautology, see [A-6c]).

    Parameters
    ----------
    y : (N,) heights (any unit), NaN = missing (breaks ranges).
    gamma : level step on the normalised scale (Table I: 0.05).
    xi, phi : left and right growth-rate clip rates (Table I: 0.03; text: 0.33).
    tau : minimum range length in samples (Table I: 3).
    max_born : highest normalised level at which a kept range may appear.
    min_swing : consecutive kept ranges whose separating peak stays below this normalised
        level are merged (one contact split by the heel's slow rise, not two contacts).

    Returns
    -------
    InflectionResult with the kept ranges (eta = their locked ends) and peaks (rho).
    """
    y = np.asarray(y, dtype=float)
    fin = np.isfinite(y)
    if fin.sum() < 2:
        return InflectionResult((), (), float("nan"), float("nan"))
    lo, hi = percentile_linear(y[fin], (1.0, 99.0))
    if not hi - lo > 1e-9:
        return InflectionResult((), (), float(lo), float(hi))
    yn = np.where(fin, np.clip((y - lo) / (hi - lo), 0.0, 1.0), np.nan)
    nlev = int(np.ceil(1.0 / gamma - 1e-9))
    levels = np.minimum(gamma * np.arange(1, nlev + 1), 1.0)
    n = len(y)
    seen = fin.tolist()  # list lookups: the loops below index it per range end

    def is_open_left(i: int) -> bool:
        return i == 0 or not seen[i - 1]

    def is_open_right(i: int) -> bool:
        return i == n - 1 or not seen[i + 1]

    ranges: list[_Range] = []
    prev_level = 0.0
    all_runs = level_runs(yn, levels + 1e-12)  # R2 for every level (yn is NaN where unseen)
    for k, level_run in zip(levels.tolist(), all_runs, strict=True):
        new_list: list[_Range] = []
        # ranges stay in time order: runs are, and locking moves an end back inside its run
        for r in ranges:
            r.old_left, r.old_right = r.left, r.right
        j = 0
        nr = len(ranges)
        for s, e in level_run:
            while j < nr and ranges[j].right < s:
                new_list.append(ranges[j])
                j += 1
            j0 = j
            while j < nr and ranges[j].left <= e:
                j += 1
            if j == j0:
                new_list.append(_Range(s, e, float(k)))
                continue
            # merge neighbours whose facing ends are both unlocked
            merged: list[_Range] = [ranges[j0]]
            for r in ranges[j0 + 1 : j]:
                last = merged[-1]
                if not last.right_locked and not r.left_locked:
                    last.right, last.right_locked = r.right, r.right_locked
                    last.right_level = r.right_level
                    last.born = min(last.born, r.born)
                    last.old_right = r.old_right
                else:
                    merged.append(r)
            nm = len(merged)
            for i, r in enumerate(merged):
                if not r.left_locked:
                    r.left = s if i == 0 else merged[i - 1].right + 1
                if not r.right_locked:
                    r.right = e if i == nm - 1 else merged[i + 1].left - 1
                new_list.append(r)
        new_list.extend(ranges[j:])
        for r in new_list:
            ol, orr = r.old_left, r.old_right
            if ol < 0:
                continue
            length = orr - ol + 1
            # R4: the growth rate, not the slope (a flat floor floods fast, a wall slowly)
            if not r.left_locked and not is_open_left(ol) and (ol - r.left) / length < xi:
                r.left, r.left_locked, r.left_level = ol, True, prev_level
            if not r.right_locked and not is_open_right(orr) and (r.right - orr) / length < phi:
                r.right, r.right_locked, r.right_level = orr, True, prev_level
        ranges = new_list
        prev_level = float(k)

    ranges.sort(key=lambda r: r.left)
    frozen = [
        FlatRange(
            r.left,
            r.right,
            r.left_locked,
            r.right_locked,
            is_open_left(r.left),
            is_open_right(r.right),
            r.born,
            r.left_level,
            r.right_level,
        )
        for r in ranges
    ]
    kept = []
    for r in frozen:
        left_ok = r.left_locked or r.left_open
        right_ok = r.right_locked or r.right_open
        if not (left_ok and right_ok) or (r.left_open and r.right_open):
            continue
        if r.length <= tau or r.born > max_born + 1e-9:
            continue
        kept.append(r)
    # two contacts of one foot have a swing between them: ranges separated only by a low
    # bump (the heel's slow rise split one valley at a lock) are one contact
    merged: list[FlatRange] = []
    for r in kept:
        if merged and r.left - merged[-1].right <= 5:
            a = merged[-1]
            gap = yn[a.right + 1 : r.left]
            top = float(np.max(gap)) if gap.size else 0.0  # NaN (missing) never merges
            if top < min_swing:
                merged[-1] = FlatRange(
                    a.left,
                    r.right,
                    a.left_locked,
                    r.right_locked,
                    a.left_open,
                    r.right_open,
                    min(a.born, r.born),
                    a.left_level,
                    r.right_level,
                )
                continue
        merged.append(r)
    kept = merged
    peaks = []
    yl = yn.tolist()  # a few short slices: plain Python beats numpy's per-call cost
    for a, b in itertools.pairwise(kept):
        seg = yl[a.right + 1 : b.left]
        seen_values = [v for v in seg if v == v]  # NaN != NaN
        if seen_values:
            # the first highest sample, as np.nanargmax
            peaks.append(a.right + 1 + seg.index(max(seen_values)))
    return InflectionResult(tuple(kept), tuple(peaks), float(lo), float(hi), tuple(frozen))


# ---------------------------------------------------------------------------------------------
# events and spatio-temporal parameters (algorithms.md section 5)


@dataclass(frozen=True)
class Contact:
    """One stance of one foot, from Alg. 6 on its heel and toe heights.

    Times in seconds; NaN where that end of the stance was not observed. ``heel_pos`` is the
    median progression of the heel while planted (mm along the walking direction): over its
    flat range where the heel lies within ``rise_frac`` of its lowest point, from where it
    came down to that level to its rise, Fig. 6's stable window.
    """

    side: str
    heel_strike: float
    heel_rise: float
    toe_off: float
    heel_pos: float
    start: float
    stop: float
    # Where the toe's speed-up to this toe off began, when the toe's flat range locked with
    # the toe already moving (a clearance dip as low as the stance, or a filled gap); NaN
    # otherwise. drop_events_in_gaps judges the toe off by the samples seen since then.
    toe_off_from: float = float("nan")


def _speed(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """|dx/dt| by central differences, NaN where undefined. (N,) -> (N,)"""
    if len(t) < 2:
        return np.full(len(t), np.nan)
    return np.abs(np.gradient(x, t))


def swing_speed(seen: float, walk_speed: float, swing_floor: float) -> float:
    """A foot's swing speed (mm/s) for its event thresholds: the 90th percentile of the
    speeds seen (``seen``), raised to ``swing_floor`` times the walking speed where that is
    known (:func:`foot_contacts`); NaN when neither is."""
    floor = swing_floor * walk_speed if swing_floor > 0 else np.nan
    return float(np.fmax(seen, floor))  # fmax: a NaN side gives the other


def walking_speed(t: np.ndarray, prog: np.ndarray) -> float:
    """The mean walking speed of a pass (mm/s): the magnitude of the least-squares slope of
    the body's progression ``prog`` (N,) over time ``t`` (N,) s, NaN = not seen. NaN when
    fewer than three samples are seen or they span no time."""
    t = np.asarray(t, dtype=float)
    prog = np.asarray(prog, dtype=float)
    ok = np.isfinite(t) & np.isfinite(prog)
    return abs(float(ls_slope(t[ok], prog[ok]))) if ok.sum() >= 3 else float("nan")


def ls_slope(t: np.ndarray, x: np.ndarray) -> np.ndarray | float:
    """Least-squares slope of ``x`` (N,) or (N, D) against time ``t`` (N,) s, all seen: a
    float, or (D,). NaN where ``t`` has no spread."""
    tk = t - t.mean()
    den = float(tk @ tk)
    if not den > 0:
        return np.full(np.shape(x)[1:], np.nan) if np.ndim(x) > 1 else float("nan")
    return (tk @ (x - x.mean(axis=0))) / den


def foot_contacts(
    t: np.ndarray,
    heel_h: np.ndarray,
    toe_h: np.ndarray,
    heel_prog: np.ndarray,
    toe_prog: np.ndarray,
    side: str,
    gamma: float = 0.05,
    xi: float = 0.33,
    phi: float = 0.33,
    tau: int = 3,
    max_born: float = 0.25,
    refine: str = "velocity",
    hs_speed_frac: float = 0.1,
    to_speed_frac: float = 0.3,
    to_late_s: float = 0.1,
    min_contact_s: float = 0.15,
    rise_frac: float = 0.05,
    arrive_speed_frac: float = 0.5,
    walk_speed: float = float("nan"),
    swing_floor: float = 1.8,
) -> list[Contact]:
    """Stances of one foot from Alg. 6 on its heel and toe heights.

    Heel strike = left end of the heel's flat range; toe off = right end of the toe's flat
    range that overlaps it (algorithms.md section 5, Rec. [A-P3]). Cross-check: a toe range
    is paired with the heel range it overlaps and its right end must fall before the next heel
    strike of that foot; otherwise the toe off is unknown (NaN), never guessed.

    With ``refine="velocity"`` (default) each event is then refined inside the bracket Alg. 6
    gives. Measured on the 26 bundled real trials, the locked ends lead the labelled events
    by about 100 ms (heel) and 70 ms (toe): a heel marker decelerates gradually into the floor
    and a toe marker lifts while the forefoot rolls, so "flat" begins after the water has
    locked and ends before the foot leaves. The refinement uses the foot's speed along the
    walking direction (the zero-velocity rule of Ghoussayni et al., Gait Posture 2004, with a
    threshold relative to the foot's own swing speed so slow and pathological gait scale):
    heel strike = first sample from the heel lock minus 0.3 s (not before the previous swing
    peak) at which the heel's speed falls to ``hs_speed_frac`` of its swing speed; toe off =
    first sample after the toe lock at which the toe's speed exceeds ``to_speed_frac`` of it.
    ``refine="none"`` returns the locked ends as printed.

    Parameters
    ----------
    t : (N,) s; heel_h, toe_h : (N,) mm above the floor (NaN = missing);
    heel_prog, toe_prog : (N,) positions along the walking direction, mm.
    side : "L" or "R". gamma, xi, phi, tau, max_born : see :func:`inflection_search`.
    refine : "velocity" or "none". hs_speed_frac, to_speed_frac : speed thresholds, as
        fractions of the foot's swing speed (90th percentile of its speed).
    to_late_s : ``refine="velocity"`` only. A toe already faster than ``to_speed_frac``
        when its flat range locked, and for more than this before the lock, left the floor
        before it: the toe off is where that speed-up began. The range can run on into the
        swing when the toe's lift-off was unseen for a few frames and its clearance stays
        low (btk_PiG_Motion3_FF seed 1: a right toe off 0.29 s late, swing 0.15 s against
        0.44 s); the lock normally lies a sample or two into the lift-off, where the run's
        start would be early. 0 = always the lock.
    min_contact_s : a heel strike whose flat range runs into the end of the data (the foot
        leaves the view) must be followed by at least this much observed contact.
    rise_frac : heel rise = the heel above its lowest point in the range by this fraction
        of its normalised height range (used by the phases only).
    arrive_speed_frac : ``refine="velocity"`` only. A heel strike needs the heel seen moving
        (faster than the ``hs_speed_frac`` rest speed) before it comes to rest, else it was
        already down when the data or the pass began: no event. A flat range that begins
        where the heel comes into view (open left end: Alg. 6 saw no descent to lock on) has
        a heel strike when the heel is seen moving faster than this fraction of its swing
        speed, then coming to rest: the strike itself was observed.
    walk_speed, swing_floor : the pass's walking speed (mm/s, NaN = unknown) and the least
        multiple of it that the swing speed may be. A foot moves forward only in its swing,
        which lasts at most about half the cycle even in hemiparetic gait, so its swing
        speed is at least about twice the walking speed: on the simulator's true markers
        the 90th percentile is 2.6-3.5 times it, 2.0-2.5 on the hemiparetic leg. Where
        the labels leave most of a swing unseen (the far foot), the percentile of the
        samples seen falls to about the walking speed, and the rest and toe speed-up
        thresholds with it: heel strikes came 34-62 ms late and toe offs early. The
        thresholds use the reference raised to ``swing_floor`` times ``walk_speed``; the
        tests that the heel was seen moving keep the reference of the samples seen.

    Returns
    -------
    Contacts in time order (one per heel flat range).
    """
    t = np.asarray(t, dtype=float)
    heel_h = np.asarray(heel_h, dtype=float)
    toe_h = np.asarray(toe_h, dtype=float)
    hr = inflection_search(heel_h, gamma, xi, phi, tau, max_born)
    # no merging for the toe: its mid-swing clearance dip comes close to the floor, right
    # after the stance range, and must stay a separate (unpaired) range
    tr = (
        inflection_search(toe_h, gamma, xi, phi, tau, max_born, min_swing=0.0)
        if np.isfinite(toe_h).sum() > 1
        else InflectionResult((), (), float("nan"), float("nan"))
    )
    vh = _speed(t, np.asarray(heel_prog, dtype=float))
    vt = _speed(t, np.asarray(toe_prog, dtype=float))
    seen = percentile_linear(vh[~np.isnan(vh)], (90,))[0] if np.isfinite(vh).any() else np.nan
    ref = swing_speed(seen, walk_speed, swing_floor)
    use_vel = refine == "velocity" and np.isfinite(ref) and ref > 0
    out: list[Contact] = []
    hranges = list(hr.ranges)
    n = len(t)
    for i, r in enumerate(hranges):
        hs_i = r.left if r.left_locked else -1
        if use_vel and (hs_i >= 0 or r.left_open):
            first = r.left  # open: the foot walks into view in its swing
            if r.left_locked:
                first = int(np.searchsorted(t, t[r.left] - 0.3))
                if i > 0:
                    first = max(first, hranges[i - 1].right + 1)
                # the swing peak between the previous range and this one, found by where it
                # lies: a gap with no sample has no peak, so peaks and gaps need not pair up
                prev_right = hranges[i - 1].right if i > 0 else n
                between = [k for k in hr.peaks if prev_right < k < r.left]
                if between:
                    first = max(first, between[-1])
            # the strike is seen only if the heel is seen moving first (else it was already
            # down when the data or the pass began): then the first sample where its speed
            # is down (NaN never is); never coming to rest inside its flat range means no
            # heel strike, not a guess. Alg. 6 locks while the heel is still moving (it
            # lands about 0.1 s later): a lock with the heel already at rest is no landing.
            # Without a lock (open end) the heel must be seen in its swing.
            moving = (hs_speed_frac if r.left_locked else arrive_speed_frac) * seen
            until = r.left + 1 if r.left_locked else r.right
            with np.errstate(invalid="ignore"):
                fast = np.flatnonzero(vh[first:until] > moving)
                a = first + int(fast[0]) if fast.size else r.right
                rest = np.flatnonzero(vh[a : r.right] <= hs_speed_frac * ref)
            hs_i = a + int(rest[0]) if rest.size else -1
        if hs_i >= 0 and r.right_open and t[r.right] - t[hs_i] < min_contact_s:
            # seen for too short a time before the data ends (leaving the view): no event
            hs_i = -1
        hs = float(t[hs_i]) if hs_i >= 0 else float("nan")
        # heel rise: the heel leaves its lowest level by rise_frac of its swing height (the
        # locked end of the range lies higher up the wall: it brackets, it does not time)
        rise = float("nan")
        planted = r.right  # last sample of the heel's stable window (Fig. 6)
        landed = r.left  # and its first
        if np.isfinite(hr.hi - hr.lo):
            seg = heel_h[r.left : r.right + 1]
            if np.isfinite(seg).any():
                k0 = int(np.nanargmin(seg))
                high = seg > seg[k0] + rise_frac * (hr.hi - hr.lo)
                above = np.flatnonzero(high[k0:])
                planted = r.left + k0 + int(above[0]) if above.size else r.right
                if r.right_locked:
                    rise = float(t[planted])
                # from where the heel came down to that level: a range can begin on the
                # swing's wall (an open end where the heel came into view rising, merged
                # with the next valley), and the median over the swing was no footprint
                before = np.flatnonzero(high[:k0])
                landed = r.left + (int(before[-1]) + 1 if before.size else 0)
        next_left = hranges[i + 1].left if i + 1 < len(hranges) else n
        to = to_from = float("nan")
        for q in tr.ranges:
            if q.right < r.left or q.left > r.right or not q.right_locked:
                continue
            began = -1  # where the toe's speed-up to this toe off began, if already fast
            if not (r.left <= q.right < next_left and q.right >= r.right - 1):
                continue
            j = q.right
            if use_vel:
                # the first sample from the lock on where the toe speed is up (or the limit)
                stop = min(next_left - 1, n - 1)
                with np.errstate(invalid="ignore"):
                    rest = np.flatnonzero(vt[j:stop] > to_speed_frac * ref)
                    fast = vt[q.left : j + 1] > to_speed_frac * ref
                if fast[-1]:
                    slow = np.flatnonzero(~fast)
                    began = q.left + (int(slow[-1]) + 1 if slow.size else 0)
                j = j + int(rest[0]) if rest.size else max(j, stop)
                if not vt[j] > to_speed_frac * ref:
                    continue  # the toe never left inside this stride: no toe off
                if j > q.right and not np.isfinite(vt[j - 1]):
                    # the toe sped up while unseen (its range was locked before a gap too
                    # long to fill): the first sample after the gap is not the toe off
                    continue
            to, to_from = float(t[j]), float(t[began]) if began >= 0 else float("nan")
            if began >= 0 and to_late_s > 0 and t[q.right] - to_from > to_late_s:
                to = to_from  # the toe was in flight well before the lock
        # the heel stands still from its strike to its rise, then rolls forward with the foot
        pos = np.asarray(heel_prog[landed : planted + 1], dtype=float)
        pos_med = float(nanmedian_last(pos)) if np.isfinite(pos).any() else float("nan")
        out.append(
            Contact(side, hs, rise, to, pos_med, float(t[r.left]), float(t[r.right]), to_from)
        )
    return out


def _in_gap(
    t: np.ndarray, seen: np.ndarray, when: float, max_s: float, since: float | None = None
) -> bool:
    """Whether ``when`` (or any time from ``since`` to ``when``) falls in a run of unseen
    samples spanning more than ``max_s``, or beyond the first or last sample seen."""
    ts = t[seen]
    start = when if since is None else since
    lo = max(int(np.searchsorted(ts, start, side="right")) - 1, 0)
    part = ts[lo : int(np.searchsorted(ts, when, side="left")) + 1]
    if not part.size or part[0] > start or part[-1] < when:
        return True
    return bool((np.diff(part) > max_s).any())


def drop_events_in_gaps(
    contacts: Sequence[Contact],
    t: np.ndarray,
    heel_seen: np.ndarray,
    toe_seen: np.ndarray,
    max_s: float,
) -> list[Contact]:
    """Contacts whose heel strike (toe off) falls in a gap of the heel (toe) longer than
    ``max_s`` lose that event (NaN): a gap filled by a curve only guesses when the foot
    landed or left. ``max_s`` <= 0: no change.

    t : (N,) s, the frame times; heel_seen, toe_seen : (N,) bool, the marker labelled then.
    """
    if max_s <= 0:
        return list(contacts)
    out = []
    for c in contacts:
        if _finite(c.heel_strike) and _in_gap(t, heel_seen, c.heel_strike, max_s):
            c = replace(c, heel_strike=float("nan"))
        since = c.toe_off_from if _finite(c.toe_off_from) else None
        if _finite(c.toe_off) and _in_gap(t, toe_seen, c.toe_off, max_s, since):
            c = replace(c, toe_off=float("nan"))
        out.append(c)
    return out


def drop_shared_footprints(
    contacts: dict[str, list[Contact]],
    min_sep_mm: float = 60.0,
    t: np.ndarray | None = None,
    heel_prog: dict[str, np.ndarray] | None = None,
) -> dict[str, list[Contact]]:
    """Contacts without the ones that land on the other foot's footprint (departure).

    Two feet cannot stand on one spot at the same time: a stance whose heel strikes within
    ``min_sep_mm`` (along the walking direction) of where the other foot's heel struck,
    while that foot still stands, is a heel label on the wrong foot, not a contact; left
    in, it gives a false heel strike and a step of a few mm followed by one of about a
    stride. The later of the two is dropped (the other was there first). Heel positions
    at a strike come from ``heel_prog`` at that time, else the stance's median
    (``Contact.heel_pos``), as in :func:`spatiotemporal`. ``min_sep_mm`` <= 0: no change.

    contacts : {"L": [...], "R": [...]} one pass. t : (N,) s; heel_prog : {"L": (N,),
    "R": (N,)} mm, optional.
    """
    out = {s: list(contacts.get(s, [])) for s in SIDES}
    if min_sep_mm <= 0:
        return out

    def at_strike(c: Contact) -> float:
        return _heel_at(t, heel_prog, c.side, c.heel_strike, c.heel_pos)

    for side in SIDES:
        other = "R" if side == "L" else "L"
        out[side] = [
            c
            for c in out[side]
            if not any(
                _finite(c.heel_strike)
                and o.start < c.heel_strike <= o.stop
                and abs(at_strike(c) - at_strike(o)) < min_sep_mm
                for o in contacts.get(other, [])
            )
        ]
    return out


def events_from_contacts(contacts: Sequence[Contact]) -> list[dict]:
    """Gait events as results.md records ``{"side", "kind", "time_s"}``, sorted by time."""
    ev = []
    for c in contacts:
        if np.isfinite(c.heel_strike):
            ev.append({"side": c.side, "kind": "heel_strike", "time_s": round(c.heel_strike, 4)})
        if np.isfinite(c.toe_off):
            ev.append({"side": c.side, "kind": "toe_off", "time_s": round(c.toe_off, 4)})
    ev.sort(key=lambda e: (e["time_s"], e["side"], e["kind"]))
    return ev


def _finite(v: float) -> bool:
    return v is not None and bool(np.isfinite(v))


def _at(t: np.ndarray, x: np.ndarray, when: float) -> float:
    """x at time ``when`` by linear interpolation; NaN if a neighbouring sample is missing."""
    i = int(np.searchsorted(t, when))
    if i <= 0 or i >= len(t):
        return float(x[0]) if i == 0 and len(t) and t[0] == when else float("nan")
    a, b = x[i - 1], x[i]
    if not (np.isfinite(a) and np.isfinite(b)):
        return float("nan")
    w = (when - t[i - 1]) / (t[i] - t[i - 1])
    return float(a + w * (b - a))


def _heel_at(
    t: np.ndarray | None,
    heel_prog: dict[str, np.ndarray] | None,
    side: str,
    when: float,
    fallback: float,
) -> float:
    """The heel's position along the walk at ``when`` from ``heel_prog``, else ``fallback``
    (no trajectories, or the heel unseen then)."""
    if t is None or heel_prog is None or side not in heel_prog or not _finite(when):
        return fallback
    v = _at(t, heel_prog[side], when)
    return v if np.isfinite(v) else fallback


def spatiotemporal(
    contacts: dict[str, list[Contact]],
    direction: float = 1.0,
    t: np.ndarray | None = None,
    heel_prog: dict[str, np.ndarray] | None = None,
) -> dict[str, dict[str, list[float]] | float]:
    """Step and stride length, stance and swing per side, cadence and speed.

    Definitions of ``../shared/spec/results.md``:

    - step length (assigned to the leading foot at its heel strike): distance along the
      walking direction between the two heels at that heel strike, each heel taken where it
      struck the floor (the trailing heel at its own, previous strike: by now it is rolling
      forward). This is the clinical footprint definition and the paper's Fig. 6 (the gap
      between the stable positions of the left and right heels);
    - stride length: between the positions of the same heel at successive heel strikes;
    - stance: heel strike to toe off of the same foot; swing: toe off to the next heel strike;
    - cadence: steps per minute from all heel strikes of both feet, a missed strike counted
      by the feet's alternation (:func:`steps_between_strikes`); speed: total stride length
      over total stride time.

    Heel positions at a strike come from ``heel_prog`` (interpolated at the strike time);
    where a heel is unseen at that moment (or no trajectories are given) the median position
    over its Alg. 6 flat range stands in (algorithms.md section 5: Fig. 6's stable windows).

    Parameters
    ----------
    contacts : {"L": [...], "R": [...]} stances in time order (one walking pass).
    direction : +1 or -1, the sign of progression along the walking axis in this pass.
    t : (N,) s and heel_prog : {"L": (N,), "R": (N,)} mm, optional heel trajectories.

    Returns
    -------
    {"L": {...lists...}, "R": {...}, "cadence_steps_per_min": float, "speed_m_s": float};
    NaN where a figure cannot be measured. Private keys: ``_records``, one record per heel
    strike with the figures that belong to it (times included, for matching); stride totals.
    """

    out: dict = {}
    stride_len_total = 0.0
    stride_time_total = 0.0
    records: list[dict[str, Any]] = []
    for side in SIDES:
        other = "R" if side == "L" else "L"
        mine = contacts.get(side, [])
        theirs = contacts.get(other, [])
        step, stride, stance, swing = [], [], [], []
        other_hs = [o.heel_strike for o in theirs if _finite(o.heel_strike)]
        for i, c in enumerate(mine):
            if not _finite(c.heel_strike):
                continue
            rec: dict[str, Any] = {"side": side, "heel_strike_s": round(c.heel_strike, 4)}
            # the trailing foot's strike must fall after this foot's previous strike: with the
            # contralateral strike between them missed, the one before it would make a step
            # of a step plus a stride
            own_prev = max(
                (m.heel_strike for m in mine[:i] if _finite(m.heel_strike)), default=-np.inf
            )
            prior = [
                o
                for o in theirs
                if o.start < c.heel_strike
                and _finite(o.heel_pos)
                and o.stop >= c.start - 0.5
                and (o.heel_strike if _finite(o.heel_strike) else o.start) > own_prev
            ]
            if prior:
                here = _heel_at(t, heel_prog, side, c.heel_strike, c.heel_pos)
                o = prior[-1]
                # the trailing heel where it struck (its footprint), not where it has rolled to
                there = (
                    _heel_at(t, heel_prog, other, o.heel_strike, o.heel_pos)
                    if _finite(o.heel_strike)
                    else (o.heel_pos)
                )
                d = direction * (here - there)
                if _finite(d) and d > 0:
                    step.append(round(float(d), 2))
                    rec["step_length_mm"] = step[-1]
            if _finite(c.toe_off) and c.toe_off > c.heel_strike:
                stance.append(round(c.toe_off - c.heel_strike, 4))
                rec["toe_off_s"] = round(c.toe_off, 4)
                rec["stance_s"] = stance[-1]
            nxt = mine[i + 1] if i + 1 < len(mine) else None
            # a stride holds exactly one contralateral strike; more means a missed contact
            between = (
                sum(1 for x in other_hs if c.heel_strike < x < nxt.heel_strike)
                if nxt is not None and _finite(nxt.heel_strike)
                else -1
            )
            if nxt is not None and _finite(nxt.heel_strike) and between <= 1:
                rec["next_heel_strike_s"] = round(nxt.heel_strike, 4)
                a = _heel_at(t, heel_prog, side, c.heel_strike, c.heel_pos)
                b = _heel_at(t, heel_prog, side, nxt.heel_strike, nxt.heel_pos)
                sl = direction * (b - a)
                if _finite(sl) and sl > 0:
                    stride.append(round(float(sl), 2))
                    rec["stride_length_mm"] = stride[-1]
                    stride_len_total += sl
                    stride_time_total += nxt.heel_strike - c.heel_strike
                if _finite(c.toe_off) and c.heel_strike < c.toe_off < nxt.heel_strike:
                    swing.append(round(nxt.heel_strike - c.toe_off, 4))
                    rec["swing_s"] = swing[-1]
            records.append(rec)
        out[side] = {
            "step_length_mm": step,
            "stride_length_mm": stride,
            "stance_s": stance,
            "swing_s": swing,
        }
    steps, seconds = steps_between_strikes([contacts])
    out["cadence_steps_per_min"] = round(60.0 * steps / seconds, 3) if seconds > 0 else float("nan")
    out["speed_m_s"] = (
        round(stride_len_total / stride_time_total / 1000.0, 4)
        if stride_time_total > 0
        else float("nan")
    )
    out["_records"] = sorted(records, key=lambda r: r["heel_strike_s"])
    out["_stride_len_total"] = stride_len_total
    out["_stride_time_total"] = stride_time_total
    return out


def steps_between_strikes(
    passes: Sequence[Mapping[str, Sequence[Contact]]],
) -> tuple[float, float]:
    """Steps taken and seconds elapsed between heel strikes, within each pass (cadence).

    Strikes of opposite feet are an odd number of steps apart, strikes of the same foot an
    even number: one and two when no strike between them was missed. Counting every interval
    as one step, as a plain mean of the intervals does, makes the cadence too low wherever a
    strike was missed (one missed in three intervals: 90 steps/min instead of 120). So each
    interval gets the count of its parity nearest its length over the mean step time T, at
    least one step between opposite feet. T is first the seconds over the least counts of
    the parities (one step between opposite feet, two between the same foot), then, once
    more, the seconds over the steps so counted, shared by the passes given. Hence:

    - strikes missed in a row count too; a single step counts as three only when it lasts
      more than twice T, beyond the step-time asymmetry of hemiparetic gait (the mean, not
      the median, so that a long and a short step alternating weigh alike);
    - two strikes of the same foot less than T apart are one strike seen twice, or a false
      one, and add no step;
    - T is first a mean over the least counts, not over the steps between opposite feet
      alone: where most strikes were missed, those may span three steps each, and T from
      them alone made real strides "seen twice". The price: a lone interval of two strides
      in a pass of few strikes may count as one stride.

    Parameters
    ----------
    passes : per walking pass, {"L": [...], "R": [...]} its stances (any order). The time
        between passes (a turn) is never counted.

    Returns
    -------
    (steps, seconds); (0, 0) without two heel strikes in one pass.
    """
    pairs = [
        (b[0] - a[0], a[1] == b[1])
        for contacts in passes
        for a, b in itertools.pairwise(
            sorted(
                (c.heel_strike, side)
                for side in SIDES
                for c in contacts.get(side, [])
                if _finite(c.heel_strike)
            )
        )
    ]
    dt = np.array([d for d, _ in pairs], dtype=float)
    same = np.array([s for _, s in pairs], dtype=bool)
    if not dt.sum() > 0:
        return 0.0, 0.0
    n = np.where(same, 2.0, 1.0)  # the least counts
    for _ in range(2):
        r = dt / (dt.sum() / n.sum())
        n = np.where(
            same, 2.0 * np.round(r / 2.0), np.maximum(1.0, 2.0 * np.round((r - 1.0) / 2.0) + 1.0)
        )
    return float(n.sum()), float(dt.sum())


def pool_spatiotemporal(
    contacts_per_pass: Sequence[dict[str, list[Contact]]],
    st_per_pass: Sequence[dict[str, Any]],
) -> dict[str, Any]:
    """Spatio-temporal parameters of several passes pooled into one set.

    The per-side lists are concatenated in pass order. Cadence pools the steps and seconds
    between each pass's heel strikes (:func:`steps_between_strikes`); speed pools stride
    lengths over stride times. A turn between passes therefore never counts as walking.

    Parameters
    ----------
    contacts_per_pass : per pass, the stances per side (progression signed forward).
    st_per_pass : per pass, the output of :func:`spatiotemporal`.
    """
    out: dict[str, Any] = {}
    for side in SIDES:
        out[side] = {
            k: [x for st in st_per_pass for x in st[side][k]]
            for k in ("step_length_mm", "stride_length_mm", "stance_s", "swing_s")
        }
    steps, seconds = steps_between_strikes(contacts_per_pass)
    length = sum(st.get("_stride_len_total", 0.0) for st in st_per_pass)
    duration = sum(st.get("_stride_time_total", 0.0) for st in st_per_pass)
    out["cadence_steps_per_min"] = round(60.0 * steps / seconds, 3) if seconds > 0 else float("nan")
    out["speed_m_s"] = round(length / duration / 1000.0, 4) if duration > 0 else float("nan")
    return out


PHASES = (
    "initial_contact",
    "loading_response",
    "mid_stance",
    "terminal_stance",
    "pre_swing",
    "initial_swing",
    "mid_swing",
    "terminal_swing",
)


def gait_phases(
    contacts: dict[str, list[Contact]],
    t: np.ndarray,
    heel_prog: dict[str, np.ndarray],
    shank_tilt: dict[str, np.ndarray],
) -> dict[str, list[dict[str, float]]]:
    """The eight gait phases of each complete cycle (algorithms.md section 5, [A-P4]).

    A cycle runs from a heel strike to the next heel strike of the same foot. Phase starts
    (seconds) follow the standard event boundaries: initial contact = heel strike (a point);
    loading response until contralateral toe off; mid stance until heel rise (the right end of
    the heel's flat range); terminal stance until contralateral heel strike; pre-swing until
    ipsilateral toe off; initial swing until the feet are adjacent (the swinging heel passes
    the other heel along the walking direction); mid swing until the shank is vertical
    (``shank_tilt``, positive while the knee is ahead of the ankle, falls to zero after the
    feet are adjacent); terminal swing until the next heel strike.

    Parameters
    ----------
    contacts : stances per side (one pass). t : (N,) s.
    heel_prog : per side (N,) heel progression, mm, signed so that walking is increasing.
    shank_tilt : per side (N,) knee-minus-ankle progression, mm (positive = knee ahead).

    Returns
    -------
    {"L": [cycle, ...], "R": [...]}; a cycle maps each phase name to its start time and has
    ``"end"``. Cycles with a missing boundary are left out.
    """
    out: dict[str, list[dict[str, float]]] = {}
    for side in SIDES:
        other = "R" if side == "L" else "L"
        cyc = []
        mine = contacts.get(side, [])
        theirs = contacts.get(other, [])
        for c, nxt in itertools.pairwise(mine):
            hs, end = c.heel_strike, nxt.heel_strike
            if not (_finite(hs) and _finite(end) and _finite(c.toe_off) and _finite(c.heel_rise)):
                continue
            c_to = [o.toe_off for o in theirs if _finite(o.toe_off) and hs < o.toe_off < c.toe_off]
            c_hs = [
                o.heel_strike
                for o in theirs
                if _finite(o.heel_strike) and hs < o.heel_strike < c.toe_off
            ]
            if not c_to or not c_hs:
                continue
            sw = (t > c.toe_off) & (t < end)
            rel = heel_prog[side] - heel_prog[other]
            adj = np.flatnonzero(sw & (rel >= 0))
            tilt = shank_tilt[side]
            # early swing: knee ahead of the ankle; the shank is vertical when that ends
            vert = np.flatnonzero(sw & (tilt <= 0))
            if adj.size == 0 or vert.size == 0:
                continue
            feet_adjacent = float(t[adj[0]])
            later = vert[vert >= adj[0]]
            tibia_vertical = float(t[later[0]]) if later.size else float("nan")
            if not _finite(tibia_vertical):
                continue
            bounds = [
                hs,
                hs,
                c_to[0],
                min(max(c.heel_rise, c_to[0]), c_hs[0]),
                c_hs[0],
                c.toe_off,
                feet_adjacent,
                tibia_vertical,
            ]
            cycle = {name: round(float(b), 4) for name, b in zip(PHASES, bounds, strict=True)}
            cycle["end"] = round(float(end), 4)
            cyc.append(cycle)
        out[side] = cyc
    return out


# ---------------------------------------------------------------------------------------------
# passes


@dataclass(frozen=True)
class Pass:
    """One walk in one direction: sample range [start, stop) and the sign of progression."""

    start: int
    stop: int
    direction: int


def split_passes(
    t: np.ndarray,
    prog: np.ndarray,
    min_speed_mm_s: float = 150.0,
    window_s: float = 0.5,
    min_duration_s: float = 0.6,
) -> list[Pass]:
    """Split a walk into passes by the direction of progression.

    The body's progression (e.g. the median of the pelvis markers along the walking axis)
    is differentiated over ``window_s`` (a least-squares slope over a centred window, so the
    within-stride speed oscillation does not flip the sign); samples moving slower than
    ``min_speed_mm_s`` (standing, turning) belong to no pass. Runs of one sign shorter than
    ``min_duration_s`` are dropped.

    Parameters
    ----------
    t : (N,) s. prog : (N,) mm, NaN = body not seen.

    Returns
    -------
    Passes in time order.
    """
    t = np.asarray(t, dtype=float)
    prog = np.asarray(prog, dtype=float)
    n = len(t)
    if n < 3:
        return []
    # least-squares slope over a centred time window, from prefix sums (O(N))
    n0, st, sx, stt, stx, _ = _window_sums(t, prog, window_s)
    den = n0 * stt - st * st
    with np.errstate(invalid="ignore", divide="ignore"):
        v = (n0 * stx - st * sx) / den
        spread = np.sqrt(np.maximum(stt / np.maximum(n0, 1) - (st / np.maximum(n0, 1)) ** 2, 0))
    # enough seen samples spread over enough of the window (a slope needs a baseline)
    v[(n0 < 3) | ~(den > 0) | (spread < window_s / 12)] = np.nan
    sign = np.zeros(n, dtype=int)
    sign[v > min_speed_mm_s] = 1
    sign[v < -min_speed_mm_s] = -1
    out = []
    for d in (1, -1):
        for a, b in runs(sign == d):
            if t[b] - t[a] >= min_duration_s:
                out.append(Pass(a, b + 1, d))
    out.sort(key=lambda p: p.start)
    return out


def extend_to_exit(
    t: np.ndarray,
    passes: Sequence[Pass],
    trunk_seen: np.ndarray,
    feet_seen: np.ndarray,
    tail_s: float = 0.25,
) -> list[Pass]:
    """Each pass carried on while its trunk has left the image and a foot is still seen.

    Walking out of the field of view, the trunk leaves first and the trailing foot stays in
    view for the rest of its stance and its toe off. The body progression then comes from
    that planted foot alone (:func:`split_passes` is given the median of every marker seen
    when the trunk is not), reads as standing, and the pass ended before the toe off (a
    walker at 0.4 m/s: the trailing foot in view 0.6 s after the shoulder left, its toe off
    0.25 s after the pass's end). A pass whose trunk is last seen at most ``tail_s`` after
    its end (half the slope window of :func:`split_passes`: the slope there already averages
    in the samples that follow) continues over the samples with the trunk unseen and a foot
    seen, up to the next pass's start. A pass whose trunk stays in view (a subject who stops
    or turns in the image) is not extended.

    Parameters
    ----------
    t : (N,) s; passes : from :func:`split_passes`, in time order.
    trunk_seen, feet_seen : (N,) bool, a trunk (shoulder, pelvis, hip) and a foot (heel,
        toe) marker seen at each sample.

    Returns
    -------
    The passes, each with its ``stop`` moved (or not).
    """
    out = []
    for i, ps in enumerate(passes):
        lim = passes[i + 1].start if i + 1 < len(passes) else len(t)
        k = ps.stop
        while k < lim and trunk_seen[k] and feet_seen[k] and t[k] - t[ps.stop - 1] <= tail_s:
            k += 1
        gone = k
        while k < lim and not trunk_seen[k] and feet_seen[k]:
            k += 1
        out.append(replace(ps, stop=k) if k > gone else ps)
    return out
