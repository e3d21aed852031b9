"""Compiled hot loops (numba) for demosaicing and calibration.

Every kernel works for any period n; the common 4×4 case has unrolled fast paths that LLVM
vectorises (a runtime n leaves short inner loops it cannot). Kernels are parallel over blocks
of rows (``superpixel_rows`` is serial), each block with its own scratch rows, and write into
caller-provided outputs. The kernels that write a cube build each output row in a scratch row
and stream it out (``streaming.stream_copy``): a cube does not fit any cache, and ordinary
stores would read every line of it before writing it.
``cache=True`` keeps the compiled code in ``__pycache__`` so only the first run pays the
compile time; ``fastmath`` stays off so results do not depend on reassociation.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from m2s2hil.processing.streaming import store_fence, stream_copy

# --- shared helpers ---------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _same_band(i: int, size: int, n: int) -> int:
    """Clamp an index into [0, size) by whole periods, so it stays on the same MSFA phase."""
    while i < 0:
        i += n
    while i >= size:
        i -= n
    return i


@njit(cache=True, inline="always", error_model="numpy")
def _hinterp(src, row, c, n, nearest, dst, tmp):
    """Interpolate along ``src[row]`` the samples at x = c + k·n into ``dst`` (full width): linearly,
    or with ``nearest`` by copying the closest sample (ties go left).

    Outside the first/last sample the nearest sample is repeated.
    """
    w = src.shape[1]
    k_n = w // n
    samples = src[row, c::n]
    for k in range(k_n):
        tmp[k] = np.float32(samples[k])
    first = tmp[0]
    for x in range(c):
        dst[x] = first
    body = dst[c:]
    if nearest and n == 4:
        for k in range(k_n - 1):
            a = tmp[k]
            body[4 * k] = a
            body[4 * k + 1] = a
            body[4 * k + 2] = a  # a tie: the left sample
            body[4 * k + 3] = tmp[k + 1]
    elif nearest:
        for k in range(k_n - 1):
            cell = body[k * n : (k + 1) * n]
            a = tmp[k]
            b = tmp[k + 1]
            for j in range(n):
                cell[j] = a if 2 * j <= n else b
    elif n == 4:
        for k in range(k_n - 1):
            a = tmp[k]
            d = tmp[k + 1] - a
            body[4 * k] = a
            body[4 * k + 1] = a + np.float32(0.25) * d
            body[4 * k + 2] = a + np.float32(0.5) * d
            body[4 * k + 3] = a + np.float32(0.75) * d
    else:
        inv = np.float32(1.0 / n)
        for k in range(k_n - 1):
            a = tmp[k]
            d = tmp[k + 1] - a
            cell = body[k * n : (k + 1) * n]
            for j in range(n):
                cell[j] = a + (np.float32(j) * inv) * d
    last = tmp[k_n - 1]
    tail = dst[c + (k_n - 1) * n :]
    for i in range(tail.shape[0]):
        tail[i] = last


# --- weighted bilinear ------------------------------------------------------------------------


@njit(cache=True, inline="always", error_model="numpy")
def _blend_rows(rows, pr, fyt, wrows, s, cnt, cy, py, o):
    """Output row ``o`` (cell row ``cy``, row phase ``py``) of a band on positions ``s``..``s + cnt``:
    the weighted sum of its sub-lattices' vertical interpolations between the ring buffer's
    horizontally interpolated sample rows (``rows[p, k % 3]``)."""
    w = o.shape[0]
    for x in range(w):
        o[x] = 0.0
    for p in range(s, s + cnt):
        k0 = cy - 1 if py < pr[p] else cy
        a_row = rows[p, k0 % 3]
        b_row = rows[p, (k0 + 1) % 3]
        fy = fyt[p, py]
        wt = wrows[p, py]
        for x in range(w):
            o[x] += wt[x] * (a_row[x] + fy * (b_row[x] - a_row[x]))


@njit(parallel=True, cache=True, error_model="numpy")
def wb_kernel(src, pr, pc, band_start, band_count, fyt, wrows, add, scale, nearest, out, nblocks):
    """Weighted bilinear demosaicing of ``src`` (H, W) into ``out`` (bands, H, W).

    Per band, each of its cell positions p = (pr[p], pc[p]) is a rectangular sub-lattice that
    is interpolated bilinearly (separably: along sample rows, then between them); a band with
    several positions blends its sub-lattice estimates with the per-pixel weights ``wrows[p,
    y % n, x]`` (which sum to one over the band's positions). ``fyt[p, y % n]`` is the vertical
    fraction. When ``add`` is (H, W) it is added to every band and the sum multiplied by
    ``scale[band]`` (PPID adds the PPI back and undoes its band balancing). With ``nearest`` the
    rows copy their closest sample and ``fyt`` / ``wrows`` are 0/1: nearest-neighbour demosaicing.
    """
    h, w = src.shape
    n_pos = pr.shape[0]
    n = 1
    while n * n < n_pos:
        n += 1
    kh = h // n
    n_bands = band_start.shape[0]
    has_add = add.shape[0] == h
    for blk in prange(nblocks):
        y_lo = blk * kh // nblocks
        y_hi = (blk + 1) * kh // nblocks
        if y_lo >= y_hi:
            continue
        rows = np.empty((n_pos, 3, w), np.float32)  # ring buffer of interpolated sample rows
        tmp = np.empty(w // n, np.float32)
        o = np.empty(w, np.float32)  # each output row is built here, then streamed to ``out``
        for k in range(y_lo - 1, y_lo + 1):
            kk = min(max(k, 0), kh - 1)
            for p in range(n_pos):
                _hinterp(src, pr[p] + kk * n, pc[p], n, nearest, rows[p, k % 3], tmp)
        for cy in range(y_lo, y_hi):
            kk = min(cy + 1, kh - 1)
            for p in range(n_pos):
                _hinterp(src, pr[p] + kk * n, pc[p], n, nearest, rows[p, (cy + 1) % 3], tmp)
            for py in range(n):
                y = cy * n + py
                ad = add[y] if has_add else rows[0, 0]
                for b in range(n_bands):
                    s = band_start[b]
                    sc = scale[b] if has_add else np.float32(1.0)
                    cnt = band_count[b]
                    if cnt == 1:
                        k0 = cy - 1 if py < pr[s] else cy
                        a_row = rows[s, k0 % 3]
                        b_row = rows[s, (k0 + 1) % 3]
                        fy = fyt[s, py]
                        if has_add:
                            for x in range(w):
                                o[x] = sc * (a_row[x] + fy * (b_row[x] - a_row[x]) + ad[x])
                        else:
                            for x in range(w):
                                o[x] = a_row[x] + fy * (b_row[x] - a_row[x])
                    elif cnt == 2:  # the TOUCAN's duplicated bands: both sub-lattices in one pass
                        k1 = cy - 1 if py < pr[s] else cy
                        k2 = cy - 1 if py < pr[s + 1] else cy
                        a1 = rows[s, k1 % 3]
                        b1 = rows[s, (k1 + 1) % 3]
                        a2 = rows[s + 1, k2 % 3]
                        b2 = rows[s + 1, (k2 + 1) % 3]
                        f1 = fyt[s, py]
                        f2 = fyt[s + 1, py]
                        w1 = wrows[s, py]
                        w2 = wrows[s + 1, py]
                        if has_add:
                            for x in range(w):
                                o[x] = sc * (
                                    w1[x] * (a1[x] + f1 * (b1[x] - a1[x]))
                                    + w2[x] * (a2[x] + f2 * (b2[x] - a2[x]))
                                    + ad[x]
                                )
                        else:
                            for x in range(w):
                                o[x] = w1[x] * (a1[x] + f1 * (b1[x] - a1[x])) + w2[x] * (
                                    a2[x] + f2 * (b2[x] - a2[x])
                                )
                    else:
                        _blend_rows(rows, pr, fyt, wrows, s, cnt, cy, py, o)
                        if has_add:
                            for x in range(w):
                                o[x] = sc * (o[x] + ad[x])
                    stream_copy(out[b, y], o)
        store_fence()  # type: ignore[call-arg]  # a numba intrinsic


# --- super-pixel ------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def superpixel_rows(src, pr, pc, band_start, band_count, out, cy_lo, cy_hi):
    """One value per band per n×n cell (cell rows cy_lo..cy_hi): the mean of the band's positions."""
    w = src.shape[1]
    n_pos = pr.shape[0]
    n = 1
    while n * n < n_pos:
        n += 1
    kw = w // n
    n_bands = band_start.shape[0]
    for cy in range(cy_lo, cy_hi):
        for b in range(n_bands):
            s = band_start[b]
            cnt = band_count[b]
            o = out[b, cy]
            first = src[cy * n + pr[s], pc[s] :: n]
            for cx in range(kw):
                o[cx] = np.float32(first[cx])
            if cnt > 1:
                for p in range(s + 1, s + cnt):
                    more = src[cy * n + pr[p], pc[p] :: n]
                    for cx in range(kw):
                        o[cx] += np.float32(more[cx])
                inv = np.float32(1.0 / cnt)
                for cx in range(kw):
                    o[cx] *= inv


@njit(cache=True, inline="always", error_model="numpy")
def _superpixel_cell_row4(rows, pr, pc, band_start, band_count, planes, halves, o, out, cy):
    """The 4×4 case of one cell row: the n rows are split into one uint16 plane per cell position
    (a loop that reads all four phases of a cell vectorises; four loops with stride 4 do not:
    1.3–1.6× slower in median), then each band is the mean of its planes, converted to float32
    as it is read and summed in the same order as the general path (identical results). uint16
    planes rather than float32 ones: the split moves half the bytes and rows + planes (32 KB)
    stay in L1 (≈ 20 % less time for split + means, docs/benchmarks.md). Each band's row is built
    in the scratch row ``o`` and streamed to ``out`` (streaming.py: no read for ownership)."""
    kw = rows.shape[1] // 4
    for py in range(4):
        c = rows[py]
        ev = halves[0]
        od = halves[1]
        for i in range(2 * kw):  # two stride-2 splits vectorise better than one stride-4 (−26 %)
            ev[i] = c[2 * i]
            od[i] = c[2 * i + 1]
        q0 = planes[4 * py]
        q1 = planes[4 * py + 1]
        q2 = planes[4 * py + 2]
        q3 = planes[4 * py + 3]
        for cx in range(kw):
            q0[cx] = ev[2 * cx]
            q2[cx] = ev[2 * cx + 1]
            q1[cx] = od[2 * cx]
            q3[cx] = od[2 * cx + 1]
    for b in range(band_start.shape[0]):
        s = band_start[b]
        cnt = band_count[b]
        f = planes[4 * pr[s] + pc[s]]
        if cnt == 1:
            for cx in range(kw):
                o[cx] = np.float32(f[cx])
        elif cnt == 2:
            g = planes[4 * pr[s + 1] + pc[s + 1]]
            for cx in range(kw):
                o[cx] = (np.float32(f[cx]) + np.float32(g[cx])) * np.float32(0.5)
        else:
            for cx in range(kw):
                o[cx] = np.float32(f[cx])
            for p in range(s + 1, s + cnt):
                g = planes[4 * pr[p] + pc[p]]
                for cx in range(kw):
                    o[cx] += np.float32(g[cx])
            inv = np.float32(1.0 / cnt)
            for cx in range(kw):
                o[cx] *= inv
        stream_copy(out[b, cy], o)


@njit(parallel=True, cache=True, error_model="numpy")
def dark_superpixel_rows(raw, dark, full_scale, pr, pc, band_start, band_count, out, cell_sat, qc, qc_step,
                         nblocks):
    """Dark subtraction, saturation flags and super-pixel in one pass over ``raw`` and ``dark``.

    Equals ``superpixel_rows(max(raw − dark, 0))`` (uint16, clipped at 0), with ``cell_sat[cy, cx]``
    True where a raw pixel of the cell is ≥ ``full_scale``. ``dark`` of shape (0, 0) means no dark.
    Every ``qc_step``-th cell row of the corrected mosaic is written into ``qc`` (rows, n, W) for the
    QC checks that sample only those rows (none when ``qc`` has no rows). Returns the number of
    saturated raw pixels. Why one pass: the two-step chain wrote and re-read an 8 MB corrected
    mosaic and ran two thread pools; each cell row here is corrected into an L1-sized scratch and
    reduced from there, so memory sees each input once and each output once. Serial on purpose
    (see ``superpixel_rows``' caller) was the rule until a machine with 25 GB/s memory left the
    serial loop at 3× its floor: ``nblocks`` blocks of cell rows run in parallel, each with its own
    scratch (1: serial, the same result).

    The per-pixel loop stays in uint16 lanes (16 per AVX2 register): it keeps only the row's
    maximum, and counts clipped pixels cell by cell in the rare rows whose maximum reaches full
    scale. Counting ``a >= full_scale`` per pixel into an int64 widened every lane to 64 bits and
    made that loop 2.6× slower. A kept QC row is corrected straight into ``qc`` (no copy).
    """
    h, w = raw.shape
    n_pos = pr.shape[0]
    n = 1
    while n * n < n_pos:
        n += 1
    kw = w // n
    n_bands = band_start.shape[0]
    has_dark = dark.shape[0] == h
    never = full_scale > 65535  # no uint16 value reaches it
    fs = np.uint16(min(max(full_scale, 0), 65535))
    n_cy = h // n
    counts = np.zeros(nblocks, np.int64)
    for blk in prange(nblocks):
        counts[blk] = _dark_superpixel_span(raw, dark, has_dark, never, fs, full_scale, pr, pc, band_start,
                                            band_count, out, cell_sat, qc, qc_step, n, kw, n_bands,
                                            blk * n_cy // nblocks, (blk + 1) * n_cy // nblocks)
    return counts.sum()


@njit(cache=True, error_model="numpy")
def _dark_superpixel_span(raw, dark, has_dark, never, fs, full_scale, pr, pc, band_start, band_count, out,
                          cell_sat, qc, qc_step, n, kw, n_bands, cy_lo, cy_hi):
    """Cell rows ``cy_lo``..``cy_hi`` of ``dark_superpixel_rows``; returns their saturated pixels."""
    w = raw.shape[1]
    scratch = np.empty((n, w), np.uint16)
    planes = np.empty((n * n, kw), np.uint16)
    halves = np.empty((2, w // 2), np.uint16)
    orow = np.empty(kw, np.float32)
    n_sat = 0
    for cy in range(cy_lo, cy_hi):
        keep = qc.shape[0] > 0 and cy % qc_step == 0
        rows = qc[cy // qc_step] if keep else scratch
        mx = np.uint16(0)
        for py in range(n):
            r = raw[cy * n + py]
            c = rows[py]
            if has_dark:
                d = dark[cy * n + py]
                for x in range(w):
                    a = r[x]
                    c[x] = a - min(a, d[x])
                    mx = max(mx, a)
            else:
                for x in range(w):
                    a = r[x]
                    c[x] = a
                    mx = max(mx, a)
        flags = cell_sat[cy]
        if never or mx < fs:
            for cx in range(kw):
                flags[cx] = False
        else:  # rare: count and flag the clipped cells
            for cx in range(kw):
                hits = 0
                for py in range(n):
                    cells = raw[cy * n + py, cx * n : (cx + 1) * n]
                    for j in range(n):
                        hits += cells[j] >= full_scale
                n_sat += hits
                flags[cx] = hits > 0
        if n == 4:
            _superpixel_cell_row4(rows, pr, pc, band_start, band_count, planes, halves, orow, out, cy)
            continue
        for b in range(n_bands):
            s = band_start[b]
            cnt = band_count[b]
            o = out[b, cy]
            first = rows[pr[s], pc[s] :: n]
            for cx in range(kw):
                o[cx] = np.float32(first[cx])
            if cnt > 1:
                for p in range(s + 1, s + cnt):
                    more = rows[pr[p], pc[p] :: n]
                    for cx in range(kw):
                        o[cx] += np.float32(more[cx])
                inv = np.float32(1.0 / cnt)
                for cx in range(kw):
                    o[cx] *= inv
    store_fence()  # type: ignore[call-arg]  # a numba intrinsic
    return n_sat


@njit(cache=True, error_model="numpy")
def kth_smallest_cells_u16(mosaic, n, row_step, step, k):
    """The ``k``-th smallest (0-based) of ``mosaic`` sampled every ``row_step``-th cell row and every
    ``step``-th cell column (all n×n pixels of a sampled cell): exact, from a histogram read in
    place. numpy needed a strided copy, an int64 cast (``bincount``) and a cumsum: the whole
    low-light check on a frame's QC rows went from 0.32 to 0.20 ms of CPU (docs/benchmarks.md)."""
    h, w = mosaic.shape
    kh = h // n
    kw = w // n
    mx = np.int64(0)
    for cy in range(0, kh, row_step):
        for py in range(n):
            r = mosaic[cy * n + py]
            for cx in range(0, kw, step):
                for j in range(n):
                    v = np.int64(r[cx * n + j])
                    mx = max(mx, v)
    hist = np.zeros(mx + 1, np.int64)
    for cy in range(0, kh, row_step):
        for py in range(n):
            r = mosaic[cy * n + py]
            for cx in range(0, kw, step):
                for j in range(n):
                    hist[r[cx * n + j]] += 1
    seen = np.int64(0)
    for level in range(mx + 1):
        seen += hist[level]
        if seen > k:
            return level
    return mx


@njit(cache=True, error_model="numpy")
def count_below_cells_u16(mosaic, n, row_step, step, threshold):
    """How many of the cells ``kth_smallest_cells_u16`` samples are below ``threshold``: one pass,
    no histogram. The low-light check needs only whether the 95th percentile reaches its bound,
    which is whether at most k of the samples fall below it; the percentile itself is computed
    only for the warning's text."""
    h, w = mosaic.shape
    kh = h // n
    kw = w // n
    below = 0
    for cy in range(0, kh, row_step):
        for py in range(n):
            r = mosaic[cy * n + py]
            for cx in range(0, kw, step):
                for j in range(n):
                    if r[cx * n + j] < threshold:
                        below += 1
    return below


@njit(cache=True, error_model="numpy")
def position_sums_u16(mosaic, n, step):
    """(n, n) sums of x and of x² of each MSFA position over every ``step``-th cell row (all columns),
    in int64: exact, so equal to any float64 summation of the same integers. Accumulated per
    column (contiguous, vectorised), then folded by position."""
    h, w = mosaic.shape
    acc1 = np.zeros((n, w), np.int64)
    acc2 = np.zeros((n, w), np.int64)
    for cy in range(0, h // n, step):
        for py in range(n):
            r = mosaic[cy * n + py]
            a1 = acc1[py]
            a2 = acc2[py]
            for x in range(w):
                v = np.int64(r[x])
                a1[x] += v
                a2[x] += v * v
    s1 = np.zeros((n, n), np.int64)
    s2 = np.zeros((n, n), np.int64)
    for py in range(n):
        for x in range(w - w % n):
            s1[py, x % n] += acc1[py, x]
            s2[py, x % n] += acc2[py, x]
    return s1, s2


# --- PPID: pseudo-panchromatic image ----------------------------------------------------------
# Hot loops index only with loop variables that start at 0 (offsets go into slices): numba's
# negative-index wrap-around on any other index blocks vectorisation (≈25× slower).
#
# One pass (``ppid_kernel``): each block of cell rows carries every stage in ring buffers of rows
# (balanced mosaic, horizontally filtered rows, PPI0, |R(p) − R(p+n·d)|, γ, PPI, R − PPI), so the
# only frame-sized traffic is the mosaic read once and the cube written once. The stages were
# separate kernels with four 16 MB intermediates in memory (docs/benchmarks.md).

# The 4 "positive" directions d (each also serves −d) and the unit step across each.
_PDIR_Y = np.array([0, 1, 1, 1], dtype=np.int64)
_PDIR_X = np.array([1, 0, 1, -1], dtype=np.int64)
_PERP_Y = np.array([1, 0, 1, 1], dtype=np.int64)
_PERP_X = np.array([0, 1, -1, 1], dtype=np.int64)


@njit(cache=True, error_model="numpy")
def _hfilter_row(r, taps, n, dst):
    """``dst = r * taps`` along x (taps centred, len 2n−1), borders clamped onto the same phase."""
    w = r.shape[0]
    half = n - 1
    if n == 4 and w > 6:  # one pass, same summation order as the general loop below
        w0, w1, w2, w3, w4, w5, w6 = taps[0], taps[1], taps[2], taps[3], taps[4], taps[5], taps[6]
        span = w - 6
        a0 = r[0:]
        a1 = r[1:]
        a2 = r[2:]
        a3 = r[3:]
        a4 = r[4:]
        a5 = r[5:]
        a6 = r[6:]
        ds = dst[3:]
        for i in range(span):
            ds[i] = w0 * a0[i] + w1 * a1[i] + w2 * a2[i] + w3 * a3[i] + w4 * a4[i] + w5 * a5[i] + w6 * a6[i]
        for x in range(3):
            acc = np.float32(0.0)
            for t in range(-3, 4):
                acc += taps[t + 3] * r[_same_band(x + t, w, n)]
            dst[x] = acc
        for x in range(w - 3, w):
            acc = np.float32(0.0)
            for t in range(-3, 4):
                acc += taps[t + 3] * r[_same_band(x + t, w, n)]
            dst[x] = acc
        return
    for x in range(w):
        dst[x] = 0.0
    for t in range(-half, half + 1):
        wt = taps[t + half]
        lo = max(0, -t)
        hi = min(w, w - t)
        ds = dst[lo:hi]
        rs = r[lo + t : hi + t]
        for i in range(hi - lo):
            ds[i] += wt * rs[i]
        for x in range(lo):
            dst[x] += wt * r[_same_band(x + t, w, n)]
        for x in range(hi, w):
            dst[x] += wt * r[_same_band(x + t, w, n)]


@njit(cache=True, inline="always")
def _inside(y, x, h, w):
    return 0 <= y < h and 0 <= x < w


@njit(cache=True, inline="always")
def _edge_slow(rm, r0, rp, qm, q0, qp, h, y, x, k, n):
    """Border version of the edge measure A_k(y, x) (see ppid_kernel), from the rows of R at
    y − ⊥, y, y + ⊥ (``rm``, ``r0``, ``rp``) and those + n·d_k (``q*``); rows outside the frame are
    never read. A side pair with a pixel outside counts as the centre pair (summed in float64)."""
    w = r0.shape[0]
    dy = n * _PDIR_Y[k]
    dx = n * _PDIR_X[k]
    if not _inside(y + dy, x + dx, h, w):
        return np.float32(0.0)
    py = _PERP_Y[k]
    px = _PERP_X[k]
    centre = abs(r0[x] - q0[x + dx])
    acc = 2 * centre
    ay = y - py
    ax = x - px
    if _inside(ay, ax, h, w) and _inside(ay + dy, ax + dx, h, w):
        acc += abs(rm[ax] - qm[ax + dx])
    else:
        acc += centre
    ay = y + py
    ax = x + px
    if _inside(ay, ax, h, w) and _inside(ay + dy, ax + dx, h, w):
        acc += abs(rp[ax] - qp[ax + dx])
    else:
        acc += centre
    return np.float32(np.float32(0.25) * acc)


@njit(cache=True, inline="always", error_model="numpy")
def _absdiff_rows(rr, rs, h, d, k, n, dst):
    """D_k(d, ·) = |R(p) − R(p + n·d_k)| where both are in the frame (other entries left alone)."""
    w = rr.shape[1]
    dy = n * _PDIR_Y[k]
    dx = n * _PDIR_X[k]
    if d + dy >= h:
        return
    lo = max(0, -dx)
    hi = min(w, w - dx)
    a = rr[d % rs, lo:hi]
    b = rr[(d + dy) % rs, lo + dx : hi + dx]
    ds = dst[lo:hi]
    for i in range(hi - lo):
        ds[i] = abs(a[i] - b[i])


@njit(cache=True, inline="always", error_model="numpy")
def _gamma_row(rr, rs, dd, h, y, k, n, dst):
    """γ_k(y, ·) = 1 / (1 + A_k), A_k the 1-2-1 weighted mean of D_k at p − ⊥, p, p + ⊥ (rows of D_k
    in ``dd[row % 3]``); the frame's border pixels take ``_edge_slow``."""
    w = rr.shape[1]
    dy = n * _PDIR_Y[k]
    py = _PERP_Y[k]
    px = _PERP_X[k]
    m = n + 1
    one = np.float32(1.0)
    # rows of R the border pixels read (a row outside the frame is any ring row: never read)
    rm = rr[(y - py) % rs]
    r0 = rr[y % rs]
    rp = rr[(y + py) % rs]
    qm = rr[(y - py + dy) % rs]
    q0 = rr[(y + dy) % rs]
    qp = rr[(y + py + dy) % rs]
    if y - 1 >= 0 and y + 1 + dy < h:
        span = w - 2 * m
        da = dd[(y - py) % 3, m - px :]
        d0 = dd[y % 3, m:]
        db = dd[(y + py) % 3, m + px :]
        ds = dst[m:]
        for i in range(span):
            ds[i] = one / (one + np.float32(0.25) * (da[i] + np.float32(2.0) * d0[i] + db[i]))
        for x in range(m):
            dst[x] = one / (one + _edge_slow(rm, r0, rp, qm, q0, qp, h, y, x, k, n))
        for x in range(w - m, w):
            dst[x] = one / (one + _edge_slow(rm, r0, rp, qm, q0, qp, h, y, x, k, n))
    else:
        for x in range(w):
            dst[x] = one / (one + _edge_slow(rm, r0, rp, qm, q0, qp, h, y, x, k, n))


@njit(cache=True, inline="always", error_model="numpy")
def _refine_one(g, e, nu, de):
    for i in range(g.shape[0]):
        gq = g[i]
        nu[i] += gq * e[i]
        de[i] += gq


@njit(cache=True, inline="always", error_model="numpy")
def _refine_two(ga, ea, gb, eb, nu, de):
    for i in range(ga.shape[0]):
        a = ga[i]
        b = gb[i]
        nu[i] = (nu[i] + a * ea[i]) + b * eb[i]
        de[i] = (de[i] + a) + b


# The row stages below are separate functions (not inlined): a parfor body holding all of them
# took numba minutes to compile; a call per row costs nothing next to the row's work.


@njit(cache=True, error_model="numpy")
def _balance_row(gain, raw, dst):
    for x in range(dst.shape[0]):
        dst[x] = gain[x] * np.float32(raw[x])


@njit(cache=True, error_model="numpy")
def _tent_rows(hr, q, taps, n, rq, dst):
    """``dst`` = PPI0(q) − R(q): the horizontally filtered rows q − n + 1 .. q + n − 1 (ring ``hr``)
    filtered by ``taps``, minus R's row ``rq`` (the refinement reads only the difference)."""
    w = dst.shape[0]
    hs = hr.shape[0]
    half = n - 1
    if n == 4:  # one pass, same summation order as the general loop below
        v0 = hr[(q - 3) % hs]
        v1 = hr[(q - 2) % hs]
        v2 = hr[(q - 1) % hs]
        v3 = hr[q % hs]
        v4 = hr[(q + 1) % hs]
        v5 = hr[(q + 2) % hs]
        v6 = hr[(q + 3) % hs]
        t0, t1, t2, t3, t4, t5, t6 = taps[0], taps[1], taps[2], taps[3], taps[4], taps[5], taps[6]
        for x in range(w):
            dst[x] = t0 * v0[x] + t1 * v1[x] + t2 * v2[x] + t3 * v3[x] + t4 * v4[x] + t5 * v5[x] + t6 * v6[x]
    else:
        v = hr[(q - half) % hs]
        wt = taps[0]
        for x in range(w):
            dst[x] = wt * v[x]
        for t in range(-half + 1, half + 1):
            wt = taps[t + half]
            v = hr[(q + t) % hs]
            for x in range(w):
                dst[x] += wt * v[x]
    for x in range(w):
        dst[x] = dst[x] - rq[x]


@njit(cache=True, error_model="numpy")
def _gamma_rows(rr, rs, dd, gm, slot, h, y, n):
    """γ_k(y, ·) for the 4 directions into ``gm[k, slot]``, with D rows up to y + 1 in ``dd``."""
    for kd in range(4):
        _gamma_row(rr, rs, dd[kd], h, y, kd, n, gm[kd, slot])


@njit(cache=True, error_model="numpy")
def _absdiff_all(rr, rs, h, d, n, dd):
    for kd in range(4):
        _absdiff_rows(rr, rs, h, d, kd, n, dd[kd, d % 3])


@njit(cache=True, error_model="numpy")
def _refine_row(rr, rs, e0, gm, h, y, n, num, den, po, do):
    """PPI(y, ·) into ``po`` and R − PPI into ``do``: the γ-weighted mean of PPI0(q) − R(q) over the
    neighbours q = p ± n·d_k inside the frame, added to R (rings: R ``rr``, PPI0 − R ``e0``, γ ``gm``)."""
    w = po.shape[0]
    ps0 = e0.shape[0]
    gs = gm.shape[1]
    for x in range(w):
        num[x] = 0.0
        den[x] = 0.0
    for kd in range(4):
        dy = n * _PDIR_Y[kd]
        dx = n * _PDIR_X[kd]
        fwd = y + dy < h
        bwd = y - dy >= 0
        # γ of the pair (p, q): γ_k(p) towards q = p + n·d, γ_k(q) towards q = p − n·d
        ga = gm[kd, y % gs]
        ea = e0[(y + dy) % ps0]
        gb = gm[kd, (y - dy) % gs]
        eb = e0[(y - dy) % ps0]
        lo_f = max(0, -dx)
        hi_f = min(w, w - dx)
        lo_b = max(0, dx)
        hi_b = min(w, w + dx)
        if fwd and bwd:  # both in one pass where both exist, forward first as at the ends
            lo = max(lo_f, lo_b)
            hi = min(hi_f, hi_b)
            _refine_one(ga[lo_f:lo], ea[lo_f + dx : lo + dx], num[lo_f:lo], den[lo_f:lo])
            _refine_one(gb[lo_b - dx : lo - dx], eb[lo_b - dx : lo - dx], num[lo_b:lo], den[lo_b:lo])
            _refine_two(
                ga[lo:hi],
                ea[lo + dx : hi + dx],
                gb[lo - dx : hi - dx],
                eb[lo - dx : hi - dx],
                num[lo:hi],
                den[lo:hi],
            )
            _refine_one(ga[hi:hi_f], ea[hi + dx : hi_f + dx], num[hi:hi_f], den[hi:hi_f])
            _refine_one(gb[hi - dx : hi_b - dx], eb[hi - dx : hi_b - dx], num[hi:hi_b], den[hi:hi_b])
        elif fwd:
            _refine_one(ga[lo_f:hi_f], ea[lo_f + dx : hi_f + dx], num[lo_f:hi_f], den[lo_f:hi_f])
        elif bwd:
            _refine_one(gb[lo_b - dx : hi_b - dx], eb[lo_b - dx : hi_b - dx], num[lo_b:hi_b], den[lo_b:hi_b])
    rrow = rr[y % rs]
    for x in range(w):
        corr = num[x] / den[x]
        po[x] = rrow[x] + corr
        do[x] = -corr


@njit(cache=True, error_model="numpy")
def _hinterp_all(df, pr, pc, n, rows, slot, tmp):
    """WB's horizontal pass: each position's samples of R − PPI (one cell row, ``df``) along x."""
    for p in range(pr.shape[0]):
        _hinterp(df, pr[p], pc[p], n, False, rows[p, slot], tmp)


@njit(cache=True, error_model="numpy")
def _wb_cell_row(rows, pr, band_start, band_count, fyt, wrows, scale, pp, cy, n, o, out):
    """``out[b]`` for the n rows of cell row ``cy``: scale[b] · (WB_b(R − PPI) + PPI), the WB sample
    rows of cell rows cy − 1 .. cy + 1 in ``rows[:, k % 3]`` (``wb_kernel``'s arithmetic); each row
    is built in the scratch row ``o`` and streamed to ``out``."""
    n_bands = band_start.shape[0]
    pps = pp.shape[0]
    w = out.shape[2]
    for b in range(n_bands):  # band-major: n consecutive rows of a plane, not n·bands streams
        s = band_start[b]
        sc = scale[b]
        cnt = band_count[b]
        for py in range(n):
            y = cy * n + py
            ad = pp[y % pps]
            if cnt == 1:
                k0 = cy - 1 if py < pr[s] else cy
                a_row = rows[s, k0 % 3]
                b_row = rows[s, (k0 + 1) % 3]
                fy = fyt[s, py]
                for x in range(w):
                    o[x] = sc * (a_row[x] + fy * (b_row[x] - a_row[x]) + ad[x])
            elif cnt == 2:
                k1 = cy - 1 if py < pr[s] else cy
                k2 = cy - 1 if py < pr[s + 1] else cy
                a1 = rows[s, k1 % 3]
                b1 = rows[s, (k1 + 1) % 3]
                a2 = rows[s + 1, k2 % 3]
                b2 = rows[s + 1, (k2 + 1) % 3]
                f1 = fyt[s, py]
                f2 = fyt[s + 1, py]
                w1 = wrows[s, py]
                w2 = wrows[s + 1, py]
                for x in range(w):
                    o[x] = sc * (
                        w1[x] * (a1[x] + f1 * (b1[x] - a1[x]))
                        + w2[x] * (a2[x] + f2 * (b2[x] - a2[x]))
                        + ad[x]
                    )
            else:
                _blend_rows(rows, pr, fyt, wrows, s, cnt, cy, py, o)
                for x in range(w):
                    o[x] = sc * (o[x] + ad[x])
            stream_copy(out[b, y], o)


@njit(parallel=True, cache=True, error_model="numpy")
def ppid_kernel(src, gain_rows, taps, pr, pc, band_start, band_count, fyt, wrows, scale, out, nblocks):
    """PPID demosaicing of ``src`` (H, W) into ``out`` (bands, H, W), all stages in one pass.

    R = ``gain_rows[y % n] * src`` (band balancing); PPI0 = R filtered by ``taps ⊗ taps`` (borders
    clamped onto the same phase); PPI(p) = R(p) + Σ_q γ_q (PPI0(q) − R(q)) / Σ_q γ_q over the (up
    to) 8 pixels q = p ± n·d_k of p's band inside the frame, γ = 1 / (1 + A), A the 1-2-1 weighted
    mean of |R(p+δ) − R(q+δ)| for δ ∈ {−⊥, 0, +⊥} across the p→q line: A for p→p+n·d is A_k(p),
    for p→p−n·d it is A_k(p−n·d) (the same pixel pairs), so one γ row per positive direction
    serves both. Then ``out[b] = scale[b] * (PPI + WB_b(R − PPI))`` with ``wb_kernel``'s tables.

    Each block of cell rows computes its rows in order, each stage only as far ahead as the next
    needs, and recomputes the few rows it needs above and below (≈ 3n pixel rows of the early
    stages): the price of never writing an intermediate frame.
    """
    h, w = src.shape
    n = (taps.shape[0] + 1) // 2
    half = n - 1
    kh = h // n
    n_pos = pr.shape[0]
    rs = 3 * n + 2  # R rows live: r − n − 1 .. r + 2n − 1 (the tent's reach ahead of the refinement)
    hs = 2 * n - 1
    ps0 = 2 * n + 1
    gs = n + 1
    pps = 2 * n
    for blk in prange(nblocks):
        cy_lo = blk * kh // nblocks
        cy_hi = (blk + 1) * kh // nblocks
        if cy_lo >= cy_hi:
            continue
        rr = np.empty((rs, w), np.float32)  # R
        hr = np.empty((hs, w), np.float32)  # R filtered along x
        e0 = np.empty((ps0, w), np.float32)  # PPI0 − R
        dd = np.empty((4, 3, w), np.float32)  # |R(p) − R(p + n·d_k)|
        gm = np.empty((4, gs, w), np.float32)  # γ_k
        pp = np.empty((pps, w), np.float32)  # PPI
        df = np.empty((n, w), np.float32)  # R − PPI of one cell row
        rows = np.empty((n_pos, 3, w), np.float32)  # ring of interpolated sample rows of R − PPI
        tmp = np.empty(w // n, np.float32)
        num = np.empty(w, np.float32)
        den = np.empty(w, np.float32)
        orow = np.empty(w, np.float32)
        p_next = max(0, (cy_lo - 1) * n)  # next row of each stage
        p0_next = max(0, p_next - n)
        h_next = p0_next - half  # virtual row index (out-of-frame rows map onto the same phase)
        r_next = max(0, h_next)
        g_next = p0_next
        d_next = max(0, g_next - 1)
        for k in range(cy_lo - 1, cy_hi + 1):
            kk = min(max(k, 0), kh - 1)
            while p_next < (kk + 1) * n:  # PPI and R − PPI of cell row kk
                y = p_next
                while p0_next <= min(h - 1, y + n):
                    q = p0_next
                    while h_next <= q + half:
                        t = _same_band(h_next, h, n)
                        while r_next <= t:
                            _balance_row(gain_rows[r_next % n], src[r_next], rr[r_next % rs])
                            r_next += 1
                        _hfilter_row(rr[t % rs], taps, n, hr[h_next % hs])
                        h_next += 1
                    _tent_rows(hr, q, taps, n, rr[q % rs], e0[q % ps0])
                    p0_next += 1
                while g_next <= y:
                    while d_next <= min(h - 1, g_next + 1):
                        _absdiff_all(rr, rs, h, d_next, n, dd)
                        d_next += 1
                    _gamma_rows(rr, rs, dd, gm, g_next % gs, h, g_next, n)
                    g_next += 1
                _refine_row(rr, rs, e0, gm, h, y, n, num, den, pp[y % pps], df[y % n])
                p_next += 1
            _hinterp_all(df, pr, pc, n, rows, k % 3, tmp)
            if k - 1 >= cy_lo:  # the sample rows below cell row k − 1 are in: write it
                _wb_cell_row(rows, pr, band_start, band_count, fyt, wrows, scale, pp, k - 1, n, orow, out)
        store_fence()  # type: ignore[call-arg]  # a numba intrinsic


# --- calibration: crosstalk and white reference -----------------------------------------------


@njit(parallel=True, cache=True, error_model="numpy")
def mix_kernel(cube, m, gain, nblocks):
    """In place: ``cube[:, y, x] = gain[:, y, x] * (m @ cube[:, y, x])`` (gain skipped when empty)."""
    n_bands, h, w = cube.shape
    has_gain = gain.shape[0] == n_bands
    for blk in prange(nblocks):
        y_lo = blk * h // nblocks
        y_hi = (blk + 1) * h // nblocks
        tmp = np.empty((n_bands, w), np.float32)
        for y in range(y_lo, y_hi):
            for b in range(n_bands):
                t = tmp[b]
                for x in range(w):
                    t[x] = 0.0
                for j in range(n_bands):
                    c = m[b, j]
                    if c != 0.0:
                        src = cube[j, y]
                        for x in range(w):
                            t[x] += c * src[x]
            for b in range(n_bands):
                o = cube[b, y]
                t = tmp[b]
                if has_gain:
                    g = gain[b, y]
                    for x in range(w):
                        o[x] = t[x] * g[x]
                else:
                    for x in range(w):
                        o[x] = t[x]
