"""Compiled (numba) kernels of detect's Alg. 1-2 and locate's Alg. 3 hot loops.

The numpy versions in ``stages/detect.py`` and ``stages/locate.py`` stay the reference (the
stages' ``jit`` parameter, on by default, picks these). Every kernel reproduces its
reference's result bit for bit: the same pixels, the same floating-point operations in the
same order, sums in the order ``np.bincount`` takes them and the R8 sum in numpy's
pairwise order (:func:`_pairwise_sum`); the labelling numbers components as OpenCV does
(:func:`label`). Two exceptions: R9's ray norm (:func:`marker_points`), summed in the
order this numpy's einsum uses, which may depend on numpy's SIMD build (positions agree to
1e-9 mm at worst), and the occluder direction of :func:`complete_occluded`, summed in
window order where the reference sums in depth order (centroids agree to 1e-9 px).
What numba saves is numpy's per-call overhead on the small arrays of one frame (a few
hundred calls of a few microseconds each): a kernel loops over the pixels or blobs
instead. Kernels use plain element loops: slice assignments, ``np.argsort`` and
array arithmetic each add seconds of compile time.

Array conventions: images (row, col) = (v, u); pixels (u, v) = (column, row); IR amplitude
and depth (mm, 0 = invalid) are uint16; NaN = not recovered; blobs along axis 0.

Compilation is lazy (first call of a kernel, not import) and cached on disk
(``cache=True``, in ``stages/__pycache__`` or ``NUMBA_CACHE_DIR``), so processes after the
first load machine code instead of compiling it. This module is imported only inside the
detect and locate functions that run a kernel (clean calls detect's), never at import of
the stages, so processes that run none of them do not pay numba's import.
"""

from __future__ import annotations

import math

import numpy as np

from gaitflow.errors import ConfigError

try:
    from numba import njit
except ImportError as exc:  # a hard dependency: no silent fallback to the slow path
    raise ConfigError(
        f"numba is required by the detect and locate stages (pip install 'numba>=0.60'): {exc}"
    ) from exc

# numpy's pairwise summation: runs up to this long are summed with 8 accumulators.
_PW_BLOCKSIZE = 128


# --------------------------------------------------------------------------------------
# detect: block maximum (region of interest) and Alg. 2 statistics


@njit(cache=True, nogil=True, error_model="numpy")
def block_max(ir: np.ndarray, block: int) -> np.ndarray:
    """Maximum over each ``block`` x ``block`` tile, as ``detect.block_max``.

    (H, W) uint16 -> (ceil(H/b), ceil(W/b)); tiles past the edge count the missing pixels as
    0 (the reference pads with zeros), which never changes a maximum of unsigned values.
    """
    h, w = ir.shape
    hb = (h + block - 1) // block
    wb = (w + block - 1) // block
    out = np.zeros((hb, wb), np.uint16)
    row = np.zeros(w, np.uint16)
    for by in range(hb):
        r0 = by * block
        r1 = min(r0 + block, h)
        # Row-wise maxima first: a contiguous inner loop that LLVM vectorises, written
        # with max() (a conditional store is not vectorised: 13x slower, 0.86 ms a frame
        # with numba 0.68). Plain element loops throughout: slice assignments cost
        # seconds of compile time.
        for c in range(w):
            row[c] = ir[r0, c]
        for r in range(r0 + 1, r1):
            for c in range(w):
                row[c] = max(row[c], ir[r, c])
        for bx in range(wb):
            c0 = bx * block
            m = row[c0]
            for c in range(c0 + 1, min(c0 + block, w)):
                m = max(m, row[c])
            out[by, bx] = m
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _find(parent: np.ndarray, x: int) -> int:
    """Root of provisional label ``x`` in the union-find forest ``parent``, compressing
    the path."""
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:
        up = parent[x]
        parent[x] = root
        x = up
    return root


@njit(cache=True, nogil=True, error_model="numpy")
def label(img: np.ndarray, e: float, connectivity: int, ordered: bool) -> tuple:
    """Connected components of ``img > e`` (strict), numbered as OpenCV numbers them.

    One raster pass assigns provisional labels and merges them (union-find, the smaller
    label is the root); a second pass numbers the components 1..K. OpenCV's 8-way
    labelling (Spaghetti / BBDT) works on 2x2 blocks, scanned block row by block row, and
    numbers a component by the first block it meets, so with ``ordered`` the second pass
    meets the components in that block order (all pixels of a 2x2 block are 8-connected);
    its 4-way labelling numbers them by their first pixel in raster order. The tests check
    the labels against ``cv2.connectedComponentsWithStats`` pixel for pixel.

    Returns
    -------
    (nlab, labels (h, w) int32): nlab counts the background label 0.
    """
    h, w = img.shape
    lab = np.zeros((h, w), np.int32)
    parent = np.empty(h * w + 1, np.int32)
    parent[0] = 0
    nxt = 1
    for r in range(h):
        for c in range(w):
            if not img[r, c] > e:
                continue
            best = 0
            for k in range(4):  # the visited neighbours: W, NW, N, NE
                rr = r - 1 if k > 0 else r
                cc = c + k - 2 if k > 0 else c - 1
                if rr < 0 or cc < 0 or cc >= w:
                    continue
                if connectivity == 4 and (k == 1 or k == 3):
                    continue
                q = lab[rr, cc]
                if q == 0:
                    continue
                q = _find(parent, q)
                if best == 0:
                    best = q
                elif q < best:
                    parent[best] = q
                    best = q
                elif q > best:
                    parent[q] = best
            if best == 0:
                parent[nxt] = nxt
                best = nxt
                nxt += 1
            lab[r, c] = best
    final = np.zeros(nxt, np.int32)
    nlab = 1
    if connectivity == 8 and ordered:
        for br in range(0, h, 2):
            for bc in range(0, w, 2):
                for r in range(br, min(br + 2, h)):
                    for c in range(bc, min(bc + 2, w)):
                        q = lab[r, c]
                        if q != 0:
                            root = _find(parent, q)
                            if final[root] == 0:
                                final[root] = nlab
                                nlab += 1
    else:
        for r in range(h):
            for c in range(w):
                q = lab[r, c]
                if q != 0:
                    root = _find(parent, q)
                    if final[root] == 0:
                        final[root] = nlab
                        nlab += 1
    for r in range(h):
        for c in range(w):
            q = lab[r, c]
            if q != 0:
                lab[r, c] = final[_find(parent, q)]
    return nlab, lab


@njit(cache=True, nogil=True, error_model="numpy")
def _boxes(lab: np.ndarray, nlab: int) -> tuple:
    """Per label: pixel count and bounding box (x0, y0, x1, y1 inclusive), and the flat
    index of its first pixel; (nlab,) and (nlab, 4) int64, (nlab,) int64."""
    h, w = lab.shape
    area = np.zeros(nlab, np.int64)
    box = np.empty((nlab, 4), np.int64)
    first = np.zeros(nlab, np.int64) - 1
    for b in range(nlab):
        box[b, 0] = w
        box[b, 1] = h
        box[b, 2] = -1
        box[b, 3] = -1
    for r in range(h):
        for c in range(w):
            b = lab[r, c]
            if b == 0:
                continue
            if area[b] == 0:
                first[b] = r * w + c
            area[b] += 1
            box[b, 0] = min(box[b, 0], c)
            box[b, 1] = min(box[b, 1], r)
            box[b, 2] = max(box[b, 2], c)
            box[b, 3] = max(box[b, 3], r)
    return area, box, first


@njit(cache=True, nogil=True, error_model="numpy")
def roi_mosaic(
    ir: np.ndarray, bmax: np.ndarray, level: float, block: int, mosaic_width: int
) -> tuple:
    """The mosaic of ``detect.compact_roi``, with the same layout.

    Parameters
    ----------
    ir : (H, W) uint16 frame; bmax : its block maxima (``block_max``).
    level : tiles with a pixel above it are gathered.
    block : tile size px; mosaic_width : shelf width px.

    Returns
    -------
    (image (h, w) uint16, tile (h, w) int32, du (k,), dv (k,), flat_ir, flat_u, flat_v
    (h*w,) float64): as ``Roi``; k = 0 when no tile is active. The 8-connected groups of
    active tiles (in OpenCV's order, :func:`label`) give boxes, merged where they overlap
    in the reference's order (``detect._merge_boxes``), stably sorted tallest first and
    shelf-packed.
    """
    H, W = ir.shape
    ng, glab = label(bmax, level, 8, True)
    _, gbox, _ = _boxes(glab, ng)
    n = ng - 1
    bx = np.empty((n, 4), np.int64)  # x0, y0, x1, y1 (exclusive) px
    for g in range(n):
        bx[g, 0] = gbox[g + 1, 0] * block
        bx[g, 1] = gbox[g + 1, 1] * block
        bx[g, 2] = min((gbox[g + 1, 2] + 1) * block, W)
        bx[g, 3] = min((gbox[g + 1, 3] + 1) * block, H)
    # _merge_boxes: merge the first overlapping pair (i, j > i) into i, drop j, restart.
    merged = n > 1
    while merged:
        merged = False
        for i in range(n):
            for j in range(i + 1, n):
                ox = bx[i, 0] < bx[j, 2] and bx[j, 0] < bx[i, 2]
                if ox and bx[i, 1] < bx[j, 3] and bx[j, 1] < bx[i, 3]:
                    bx[i, 0] = min(bx[i, 0], bx[j, 0])
                    bx[i, 1] = min(bx[i, 1], bx[j, 1])
                    bx[i, 2] = max(bx[i, 2], bx[j, 2])
                    bx[i, 3] = max(bx[i, 3], bx[j, 3])
                    for m in range(j, n - 1):
                        for q in range(4):
                            bx[m, q] = bx[m + 1, q]
                    n -= 1
                    merged = True
                    break
            if merged:
                break
    # Stable insertion sort, tallest first (the reference's list.sort on y0 - y1).
    for i in range(1, n):
        k = i
        while k > 0 and bx[k - 1, 1] - bx[k - 1, 3] > bx[k, 1] - bx[k, 3]:
            for q in range(4):
                bx[k - 1, q], bx[k, q] = bx[k, q], bx[k - 1, q]
            k -= 1
    # Shelf packing.
    du = np.empty(n, np.intp)
    dv = np.empty(n, np.intp)
    x = 0
    y = 0
    shelf_h = 0
    width = 0
    for g in range(n):
        ch = bx[g, 3] - bx[g, 1]
        cw = bx[g, 2] - bx[g, 0]
        if x > 0 and x + cw > mosaic_width:
            y += shelf_h + 1
            x = 0
            shelf_h = 0
        du[g] = bx[g, 0] - x
        dv[g] = bx[g, 1] - y
        x += cw + 1
        shelf_h = max(shelf_h, ch)
        width = max(width, x - 1)
    height = y + shelf_h
    img = np.zeros((height, width), np.uint16)
    tile = np.empty((height, width), np.int32)
    for r in range(height):
        for c in range(width):
            tile[r, c] = -1
    for g in range(n):
        for r in range(bx[g, 1], bx[g, 3]):
            for c in range(bx[g, 0], bx[g, 2]):
                img[r - dv[g], c - du[g]] = ir[r, c]
                tile[r - dv[g], c - du[g]] = g
    size = height * width
    flat_ir = np.empty(size)
    fu = np.empty(size)
    fv = np.empty(size)
    for r in range(height):
        for c in range(width):
            # Pixels outside the crops index du[-1], as the reference's du[tile] does;
            # they are 0 in the image and never foreground.
            t = tile[r, c]
            if t < 0:
                t = n - 1
            i = r * width + c
            flat_ir[i] = img[r, c]
            fu[i] = c + du[t]
            fv[i] = r + dv[t]
    return img, tile, du, dv, flat_ir, fu, fv


@njit(cache=True, nogil=True, error_model="numpy")
def count_at(
    img: np.ndarray, e: float, connectivity: int, min_area: int, max_region_radius: float
) -> int:
    """``detect.count_components``: blobs of at least ``min_area`` px in ``img > e``, or -1
    when one's box diagonal exceeds ``max_region_radius`` (its r_r might)."""
    nlab, lab = label(img, e, connectivity, False)
    area, box, _ = _boxes(lab, nlab)
    check = math.isfinite(max_region_radius)
    count = 0
    for b in range(1, nlab):
        if area[b] >= min_area:
            count += 1
            if check:
                diag = math.hypot(float(box[b, 2] - box[b, 0]), float(box[b, 3] - box[b, 1]))
                if diag > max_region_radius:
                    return -1
    return count


@njit(cache=True, nogil=True, error_model="numpy")
def components_at(
    img: np.ndarray,
    flat_ir: np.ndarray,
    flat_u: np.ndarray,
    flat_v: np.ndarray,
    e: float,
    connectivity: int,
    min_area: int,
    max_region_radius: float,
) -> tuple:
    """Alg. 2 on the mosaic at threshold e: labels and statistics, as ``detect.components``.

    Parameters
    ----------
    img : (h, w) uint16 mosaic; flat_ir, flat_u, flat_v : (h*w,) float64 its IR and each
        pixel's frame (u, v).
    e : threshold e_d (strict ``P > e``); a pixel's weight is ``P - e`` (Rec. [A-2a]).
    connectivity, min_area, max_region_radius : blob rules (4 or 8; px; px, may be inf).

    Returns
    -------
    (nlab, labels (h, w) int32, ids (K,) int32, centroid (K, 2), r_m (K,), r_r (K,),
    k (K,), area (K,) int32, box (K, 4) int64 mosaic x0, y0, x1, y1 inclusive, first (K,)
    flat index of each blob's first pixel, rejected) for the labels with at least
    ``min_area`` pixels and ``r_r <= max_region_radius`` (when finite), in label order.
    Sums run over the pixels in flat order, as ``np.bincount`` does, so every figure equals
    the reference's exactly.
    """
    nlab, labels = label(img, e, connectivity, True)
    area, box, first = _boxes(labels, nlab)
    lab = labels.ravel()
    sw = np.zeros(nlab)
    su = np.zeros(nlab)
    sv = np.zeros(nlab)
    sk = np.zeros(nlab)
    for i in range(lab.size):
        b = lab[i]
        if b == 0:
            continue
        val = flat_ir[i]
        wt = val - e
        sw[b] += wt
        su[b] += wt * flat_u[i]
        sv[b] += wt * flat_v[i]
        sk[b] += val
    sw[0] = 1.0
    pu = np.empty(nlab)
    pv = np.empty(nlab)
    for b in range(nlab):
        pu[b] = su[b] / sw[b]
        pv[b] = sv[b] / sw[b]
    srm = np.zeros(nlab)
    rr = np.zeros(nlab)
    for i in range(lab.size):
        b = lab[i]
        if b == 0:
            continue
        d = math.hypot(flat_u[i] - pu[b], flat_v[i] - pv[b])
        srm[b] += (flat_ir[i] - e) * d
        if d > rr[b]:
            rr[b] = d
    check = math.isfinite(max_region_radius)
    keep = np.zeros(nlab, np.int32)
    rejected = 0
    K = 0
    for b in range(1, nlab):
        if area[b] >= min_area:
            if check and rr[b] > max_region_radius:
                rejected += 1
            else:
                keep[K] = b
                K += 1
    ids = keep[:K].copy()
    cen = np.empty((K, 2))
    rm = np.empty(K)
    rrk = np.empty(K)
    k = np.empty(K)
    ak = np.empty(K, np.int32)
    bk = np.empty((K, 4), np.int64)
    fk = np.empty(K, np.int64)
    for j in range(K):
        b = ids[j]
        cen[j, 0] = pu[b]
        cen[j, 1] = pv[b]
        rm[j] = srm[b] / sw[b]
        rrk[j] = rr[b]
        k[j] = sk[b] / max(area[b], 1)
        ak[j] = area[b]
        for q in range(4):
            bk[j, q] = box[b, q]
        fk[j] = first[b]
    return nlab, labels, ids, cen, rm, rrk, k, ak, bk, fk, rejected


# --------------------------------------------------------------------------------------
# locate: Alg. 3 (R1-R8) for all blobs of a frame


@njit(cache=True, nogil=True, error_model="numpy")
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:
    """numpy's pairwise sum of a run of at most ``_PW_BLOCKSIZE`` values: sequential below
    8, else 8 interleaved accumulators combined as a tree, then the remainder."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0 = a[lo]
    r1 = a[lo + 1]
    r2 = a[lo + 2]
    r3 = a[lo + 3]
    r4 = a[lo + 4]
    r5 = a[lo + 5]
    r6 = a[lo + 6]
    r7 = a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, nogil=True, error_model="numpy")
def _pairwise_sum(a: np.ndarray, lo: int, n: int) -> float:
    """``a[lo:lo + n].sum()`` in numpy's pairwise order (``pairwise_sum`` of its float add
    loop), so that the R8 mean rounds exactly as the reference's ``sum(axis=1)``.

    numpy halves a run longer than ``_PW_BLOCKSIZE`` (the first half a multiple of 8) and
    adds the halves' sums; the recursion is walked here with an explicit stack (numba's
    on-disk cache cannot reload self-recursive functions).
    """
    if n <= _PW_BLOCKSIZE:
        return _block_sum(a, lo, n)
    depth = 2 * 64
    s_lo = np.empty(depth, np.int64)
    s_n = np.empty(depth, np.int64)
    s_right = np.zeros(depth, np.bool_)  # the left half's sum is in s_acc
    s_acc = np.empty(depth)
    sp = 0
    s_lo[0] = lo
    s_n[0] = n
    while True:
        m = s_n[sp]
        if m > _PW_BLOCKSIZE:  # descend into the left half
            h = m // 2
            h -= h % 8
            sp += 1
            s_lo[sp] = s_lo[sp - 1]
            s_n[sp] = h
            s_right[sp] = False
            continue
        ret = _block_sum(a, s_lo[sp], m)
        sp -= 1
        while sp >= 0:  # hand the sum to the parents whose halves are both done
            if not s_right[sp]:
                s_acc[sp] = ret
                s_right[sp] = True
                h = s_n[sp] // 2
                h -= h % 8
                s_lo[sp + 1] = s_lo[sp] + h
                s_n[sp + 1] = s_n[sp] - h
                s_right[sp + 1] = False
                sp += 1
                break
            ret = s_acc[sp] + ret
            sp -= 1
        if sp < 0:
            return ret


@njit(cache=True, nogil=True, error_model="numpy")
def _layer(
    z: np.ndarray,
    dd: np.ndarray,
    m: int,
    T0: float,
    r: float,
    W: float,
    D0: float,
    D1: float,
    D2: float,
) -> float:
    """R5-R8 on one job: the window pixels ``z[:m]`` (depth mm) in [T0, T0 + W], at
    distances ``dd[:m]`` px from the centroid; r = r_r px, m is also the window's valid
    pixel count nv. As ``locate._layers_core`` for one job (surface fit off). The pixels
    are taken in window order, not depth order: their depths are integers, so every sum
    is exact in any order. NaN if no bin is kept."""
    T1 = T0 + W
    nb = max(math.ceil(W / D1), 1)
    dmax = 0.0
    for i in range(m):
        if z[i] >= T0 and z[i] <= T1 and dd[i] > dmax:
            dmax = dd[i]
    ndist = int(dmax / D2) + 1
    cnt2 = np.zeros((nb, ndist), np.int64)
    sum2 = np.zeros((nb, ndist))
    counts = np.zeros(nb, np.int64)
    for i in range(m):
        if z[i] >= T0 and z[i] <= T1:
            zb = min(int((z[i] - T0) / D1), nb - 1)
            db = int(dd[i] / D2)
            counts[zb] += 1
            cnt2[zb, db] += 1
            sum2[zb, db] += z[i]
    B = 0
    for h in range(nb):
        if counts[h] != 0:
            B += 1
    B = max(B, 1)
    # R6 [A-3c]: the reference's np.minimum.reduce of the four bounds.
    d = 2.0 * (r + D0) + 1.0
    bound = min((r + D0) * (r + D0), d * d / B + D0, D0, m / B)
    num = np.zeros(nb)
    tot = 0.0
    for h in range(nb):
        if counts[h] > 0 and counts[h] >= bound:
            # R7: mean depth of the modal distance bin (first maximum, as np.argmax).
            mode = 0
            for q in range(1, ndist):
                if cnt2[h, q] > cnt2[h, mode]:
                    mode = q
            wt = float(counts[h])
            num[h] = sum2[h, mode] / cnt2[h, mode] * wt
            tot += wt
    if tot > 0:
        return _pairwise_sum(num, 0, nb) / tot
    return np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def _window(
    depth: np.ndarray,
    cu: float,
    cv: float,
    r: float,
    margin: float,
    maxd: float,
    z: np.ndarray,
    dd: np.ndarray,
    du: np.ndarray,
    dv: np.ndarray,
) -> int:
    """R1: the valid pixels (0 < depth <= maxd) of the blob's window of half-size
    ceil(r + margin) about the rounded centroid, into ``z`` (depth), ``dd`` (distance
    from the centroid, px) and ``du``, ``dv`` (its column and row offsets, px); returns
    their count."""
    H, Wd = depth.shape
    half = math.ceil(r + margin)
    iu = int(np.rint(cu))
    iq = int(np.rint(cv))
    r0 = max(iq - half, 0)
    c0 = max(iu - half, 0)
    r1 = min(iq + half + 1, H)
    c1 = min(iu + half + 1, Wd)
    m = 0
    for row in range(r0, r1):
        for col in range(c0, c1):
            val = depth[row, col]
            if val > 0 and val <= maxd:
                z[m] = val
                du[m] = col - cu
                dv[m] = row - cv
                dd[m] = math.hypot(du[m], dv[m])
                m += 1
    return m


@njit(cache=True, nogil=True, error_model="numpy")
def _sorted_depths(z: np.ndarray, m: int) -> np.ndarray:
    """``z[:m]`` (integer depths, mm) sorted ascending, by counting sort over their range
    (at most ``max_depth``): a window holds a few hundred pixels over a few thousand mm,
    where a comparison sort costs several times more."""
    lo = int(z[0])
    hi = lo
    for i in range(1, m):
        v = int(z[i])
        if v < lo:
            lo = v
        elif v > hi:
            hi = v
    cnt = np.zeros(hi - lo + 1, np.int64)
    for i in range(m):
        cnt[int(z[i]) - lo] += 1
    out = np.empty(m)
    k = 0
    for v in range(hi - lo + 1):
        for _ in range(cnt[v]):
            out[k] = v + lo
            k += 1
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def locate_depths(
    depth: np.ndarray,
    cen: np.ndarray,
    r: np.ndarray,
    W: float,
    D0: float,
    D1: float,
    D2: float,
    maxd: float,
    min_slab: int,
    reach: float,
    fit: bool,
    fit_min_px: int,
    fit_max_px: int,
    fit_max_step: float,
    fit_curvature: bool,
) -> np.ndarray:
    """Alg. 3 (Rec. R1-R8; top mode = normal) for every blob, as ``locate._widened(_ragged)``
    with the surface fit on (``fit``: its plain least squares, :func:`_surface_fit`) or off.

    Parameters
    ----------
    depth : (H, W) integer depth mm, 0 = invalid.
    cen : (N, 2) centroids (u, v) px; r : (N,) r_r px (a blob with any of them not
        finite gets NaN).
    W, D0, D1, D2, maxd, min_slab, reach : the stage parameters (mm, px, mm, px, mm, px,
        mm).
    fit, fit_min_px, fit_max_px, fit_max_step, fit_curvature : the surface fit's
        parameters (-, px, px, mm, -).

    Returns
    -------
    (N, 3) Z mm under normal, top, bottom; NaN where no layer is found.
    """
    n = cen.shape[0]
    out = np.empty((n, 3))
    for b in range(n):
        out[b, 0] = out[b, 1] = out[b, 2] = np.nan
    for b in range(n):
        cu, cv, rb = cen[b, 0], cen[b, 1], r[b]
        if not (math.isfinite(cu) and math.isfinite(cv) and math.isfinite(rb)):
            continue
        # R1: window margin D0, widened once by D0 when it holds fewer than 3 valid pixels.
        side = 2 * math.ceil(rb + 2.0 * D0) + 1
        z = np.empty(side * side)
        dd = np.empty(side * side)
        du = np.empty(side * side)
        dv = np.empty(side * side)
        m = _window(depth, cu, cv, rb, D0, maxd, z, dd, du, dv)
        if m < 3:
            m = _window(depth, cu, cv, rb, 2.0 * D0, maxd, z, dd, du, dv)
        if m == 0:
            continue
        zs = _sorted_depths(z, m)
        # R2-R4: greedy W-wide slabs from the nearest value; slabs under min_slab px are
        # flying pixels (R3). near = T0 of the normal (and top) mode; far = last value of
        # the farthest significant slab starting within ``reach`` of it (bottom mode).
        near = np.nan
        far = np.nan
        i = 0
        j = 0
        while i < m:
            s = zs[i]
            j = max(j, i + 1)
            while j < m and zs[j] < s + W:
                j += 1
            if j - i >= min_slab:
                if near != near:
                    near = s
                if s <= near + reach:
                    far = zs[j - 1]
            i = j
            if near == near and i < m and zs[i] > near + reach:
                break
        if near != near:
            continue
        # The layer [T0, T0 + W] of each mode: its surface at the centroid where the fit
        # serves, else R5-R8; bottom only where it differs.
        zn = np.nan
        if fit:
            zn = _surface_fit(
                z, du, dv, m, near, W, fit_min_px, fit_max_px, fit_max_step, fit_curvature
            )
        if zn != zn:
            zn = _layer(z, dd, m, near, rb, W, D0, D1, D2)
        out[b, 0] = zn
        out[b, 1] = zn
        out[b, 2] = zn
        t0b = far - W
        if t0b != near:
            zb = np.nan
            if fit:
                zb = _surface_fit(
                    z, du, dv, m, t0b, W, fit_min_px, fit_max_px, fit_max_step, fit_curvature
                )
            if zb != zb:
                zb = _layer(z, dd, m, t0b, rb, W, D0, D1, D2)
            out[b, 2] = zb
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _surface_fit(
    z: np.ndarray,
    du: np.ndarray,
    dv: np.ndarray,
    m: int,
    T0: float,
    W: float,
    min_px: int,
    max_px: int,
    max_step: float,
    curvature: bool,
) -> float:
    """The layer's surface extrapolated to the centroid, as ``locate._surface_fit`` with its
    defaults (plain least squares: no IRLS, no prior, no standard-error gate) for one job:
    ``z = a + b du + c dv [+ k (du^2 + dv^2)]`` over the window pixels ``z[:m]`` in
    [T0, T0 + W] (an even subsample on every s-th pixel diagonal when more than ``max_px``),
    depths taken from the layer's middle; returns the layer's middle + ``a``, or NaN where
    the fit cannot serve (fewer than ``min_px`` pixels, or ``a`` more than ``max_step``
    outside the layer). Equal to the numpy path to rounding (sums in another order)."""
    T1 = T0 + W
    nf = 0
    for i in range(m):
        if z[i] >= T0 and z[i] <= T1:
            nf += 1
    stride = 1
    if nf > max_px:
        stride = -(-nf // max_px)
    K = 4 if curvature else 3
    S = np.zeros((K + 1, K + 1))
    row = np.empty(K + 1)
    mid = T0 + 0.5 * W
    n = 0
    for i in range(m):
        if not (z[i] >= T0 and z[i] <= T1):
            continue
        x = du[i]
        y = dv[i]
        if stride > 1 and (math.floor(x) + math.floor(y)) % stride != 0:
            continue
        n += 1
        row[0] = 1.0
        row[1] = x
        row[2] = y
        if curvature:
            row[3] = x * x + y * y
        row[K] = z[i] - mid
        for a in range(K + 1):
            for c in range(K + 1):
                S[a, c] += row[a] * row[c]
    if n < min_px:
        return np.nan
    M = np.empty((K, K))
    rhs = np.empty(K)
    trace = 0.0
    for a in range(K):
        rhs[a] = S[a, K]
        trace += S[a, a]
        for c in range(K):
            M[a, c] = S[a, c]
    # the numpy path's ridge: degenerate layouts stay solvable, fit_max_step catches them
    ridge = 1e-9 * trace + 1e-6
    for a in range(K):
        M[a, a] += ridge
    a0 = np.linalg.solve(M, rhs)[0]
    if abs(a0) > 0.5 * W + max_step:
        return np.nan
    return mid + a0


@njit(cache=True, nogil=True, error_model="numpy")
def marker_points(xy: np.ndarray, zs: np.ndarray, offset: bool, back: float) -> np.ndarray:
    """R9 as ``locate.locate_all``: camera-space points from undistorted rays and depths.

    Parameters
    ----------
    xy : (N, 2) normalised image coordinates x = X/Z, y = Y/Z (undistorted centroids).
    zs : (N, 3) Z mm per mode (NaN = none).
    offset : move each point towards the camera along its ray by ``back`` mm (the marker
        centre behind the ring surface).

    Returns
    -------
    (N, 3, 3) [blob, mode, xyz] mm, with the reference's operations in its order.
    """
    n = zs.shape[0]
    pos = np.empty((n, 3, 3))
    for b in range(n):
        x = xy[b, 0]
        y = xy[b, 1]
        # |ray| in the order numpy's einsum sums (x, y, 1) . (x, y, 1): its two SIMD lanes
        # take x^2 + 1^2, then y^2 (checked bit for bit by the tests).
        s = math.sqrt((x * x + 1.0) + y * y)
        for k in range(3):
            z = zs[b, k]
            px = x * z
            py = y * z
            pz = z
            if offset:
                f = 1.0 - back / (z * s)
                if f < 0.0:
                    f = 0.0
                px *= f
                py *= f
                pz *= f
            pos[b, k, 0] = px
            pos[b, k, 1] = py
            pos[b, k, 2] = pz
    return pos


@njit(cache=True, nogil=True, error_model="numpy")
def _median_sorted(v: np.ndarray, lo: int, hi: int) -> float:
    """The median of the sorted run ``v[lo:hi]`` (hi > lo), as ``np.median`` gives it."""
    k = hi - lo
    mid = lo + k // 2
    return v[mid] if k % 2 else 0.5 * (v[mid - 1] + v[mid])


@njit(cache=True, nogil=True, error_model="numpy")
def complete_occluded(
    depth: np.ndarray,
    cen: np.ndarray,
    r: np.ndarray,
    area: np.ndarray,
    surface_z: np.ndarray,
    D0: float,
    maxd: float,
    gap: float,
    min_slab: int,
    fmax: float,
    peer_mm: float,
    min_peers: int,
    table_f: np.ndarray,
    table_shift: np.ndarray,
) -> tuple:
    """``locate.complete_occluded`` (its numpy path is the reference): the centroids (N, 2)
    with partly hidden markers completed, and which were (N,) bool. The direction's sums
    run in window order, not in the reference's depth order, and the cut-disc shift is
    interpolated here: centroids agree to 1e-9 px. ``table_f``, ``table_shift``: the cut
    disc's visible fraction (increasing) and centroid shift in radii."""
    n = cen.shape[0]
    out = cen.copy()
    done = np.zeros(n, np.bool_)
    size = np.full(n, np.nan)
    ok = np.zeros(n, np.bool_)
    for b in range(n):
        s = area[b] * surface_z[b] ** 2
        if (
            math.isfinite(s)
            and s > 0
            and math.isfinite(cen[b, 0])
            and math.isfinite(cen[b, 1])
            and math.isfinite(r[b])
        ):
            size[b] = s
            ok[b] = True
    peers = np.empty(n)
    for b in range(n):
        if not ok[b]:
            continue
        cnt = 0
        for q in range(n):
            if ok[q] and abs(surface_z[q] - surface_z[b]) <= peer_mm:
                peers[cnt] = size[q]
                cnt += 1
        if cnt < min_peers:
            continue
        K = _median_sorted(np.sort(peers[:cnt]), 0, cnt)
        if size[b] >= fmax * K:
            continue
        cu, cv, rb = cen[b, 0], cen[b, 1], r[b]
        side = 2 * math.ceil(rb + D0) + 1
        z = np.empty(side * side)
        dd = np.empty(side * side)
        du = np.empty(side * side)
        dv = np.empty(side * side)
        m = _window(depth, cu, cv, rb, D0, maxd, z, dd, du, dv)
        if m < 2 * min_slab:
            continue
        zs = _sorted_depths(z, m)
        # groups: runs of sorted depths with steps under ``gap``; the first two of at
        # least ``min_slab`` px are the occluder and the surface behind it.
        lo1 = hi1 = lo2 = hi2 = -1
        i = 0
        while i < m and lo2 < 0:
            j = i + 1
            while j < m and zs[j] - zs[j - 1] < gap:
                j += 1
            if j - i >= min_slab:
                if lo1 < 0:
                    lo1, hi1 = i, j
                else:
                    lo2, hi2 = i, j
            i = j
        if lo2 < 0:
            continue
        zlo, zhi = zs[lo1], zs[hi1 - 1]
        su = 0.0
        sv = 0.0
        for q in range(m):
            if zlo <= z[q] <= zhi:
                w = 1.0 / max(du[q] * du[q] + dv[q] * dv[q], 1.0)
                su += w * du[q]
                sv += w * dv[q]
        norm = math.hypot(su, sv)
        if norm == 0.0:
            continue
        zb = min(_median_sorted(zs, lo2, hi2), _median_sorted(zs, lo1, hi1) + peer_mm)
        expected = K / zb**2
        f = area[b] / expected
        if not f < fmax:
            continue
        shift = np.interp(min(max(f, 0.5), 1.0), table_f, table_shift)
        step = shift * math.sqrt(expected / math.pi) / norm
        out[b, 0] += step * su
        out[b, 1] += step * sv
        done[b] = True
    return out, done
