"""Compiled hot loops (numba) for demosaicing and calibration.

Every kernel works for any period n; the common 4×4 case has unrolled fast paths that LLVM
vectorises (a runtime n leaves short inner loops it cannot). Kernels are parallel over blocks
of rows (the small super-pixel one is serial), each block with its own scratch rows, and write
into caller-provided outputs.
``cache=True`` keeps the compiled code in ``__pycache__`` so only the first run pays the
compile time; ``fastmath`` stays off so results do not depend on reassociation.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

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
                    o = out[b, y]
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
                        if has_add:
                            for x in range(w):
                                o[x] = sc * (o[x] + ad[x])


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
def _superpixel_cell_row4(rows, pr, pc, band_start, band_count, planes, halves, out, cy):
    """The 4×4 case of one cell row: the n rows are split into one uint16 plane per cell position
    (a loop that reads all four phases of a cell vectorises; four loops with stride 4 do not:
    1.3–1.6× slower in median), then each band is the mean of its planes, converted to float32
    as it is read and summed in the same order as the general path (identical results). uint16
    planes rather than float32 ones: the split moves half the bytes and rows + planes (32 KB)
    stay in L1 (≈ 20 % less time for split + means, docs/benchmarks.md)."""
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
        o = out[b, cy]
        f = planes[4 * pr[s] + pc[s]]
        if cnt == 1:
            for cx in range(kw):
                o[cx] = np.float32(f[cx])
            continue
        if cnt == 2:
            g = planes[4 * pr[s + 1] + pc[s + 1]]
            for cx in range(kw):
                o[cx] = (np.float32(f[cx]) + np.float32(g[cx])) * np.float32(0.5)
            continue
        for cx in range(kw):
            o[cx] = np.float32(f[cx])
        for p in range(s + 1, s + cnt):
            g = planes[4 * pr[p] + pc[p]]
            for cx in range(kw):
                o[cx] += np.float32(g[cx])
        inv = np.float32(1.0 / cnt)
        for cx in range(kw):
            o[cx] *= inv


@njit(cache=True, error_model="numpy")
def dark_superpixel_rows(raw, dark, full_scale, pr, pc, band_start, band_count, out, cell_sat, qc, qc_step):
    """Dark subtraction, saturation flags and super-pixel in one pass over ``raw`` and ``dark``.

    Equals ``superpixel_rows(max(raw − dark, 0))`` (uint16, clipped at 0), with ``cell_sat[cy, cx]``
    True where a raw pixel of the cell is ≥ ``full_scale``. ``dark`` of shape (0, 0) means no dark.
    Every ``qc_step``-th cell row of the corrected mosaic is written into ``qc`` (rows, n, W) for the
    QC checks that sample only those rows (none when ``qc`` has no rows). Returns the number of
    saturated raw pixels. Why one pass: the two-step chain wrote and re-read an 8 MB corrected
    mosaic and ran two thread pools; each cell row here is corrected into an L1-sized scratch and
    reduced from there, so memory sees each input once and each output once. Serial on purpose
    (see ``superpixel_rows``' caller).

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
    scratch = np.empty((n, w), np.uint16)
    planes = np.empty((n * n, kw), np.uint16)
    halves = np.empty((2, w // 2), np.uint16)
    n_sat = 0
    for cy in range(h // n):
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
            _superpixel_cell_row4(rows, pr, pc, band_start, band_count, planes, halves, out, cy)
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
    mx = 0
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
    seen = 0
    for v in range(mx + 1):
        seen += hist[v]
        if seen > k:
            return v
    return mx


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


@njit(cache=True, inline="always", error_model="numpy")
def _hfilter(src, row, taps, n, dst):
    """``dst = src[row] * taps`` along x (taps centred, len 2n−1), borders clamped onto the same phase."""
    w = src.shape[1]
    half = n - 1
    r = src[row]
    for x in range(w):
        dst[x] = 0.0
    for t in range(-half, half + 1):
        wt = taps[t + half]
        lo = max(0, -t)
        hi = min(w, w - t)
        ds = dst[lo:hi]
        rs = r[lo + t : hi + t]
        for i in range(hi - lo):
            ds[i] += wt * np.float32(rs[i])
        for x in range(lo):
            dst[x] += wt * np.float32(r[_same_band(x + t, w, n)])
        for x in range(hi, w):
            dst[x] += wt * np.float32(r[_same_band(x + t, w, n)])


@njit(parallel=True, cache=True, error_model="numpy")
def tent_filter_kernel(src, taps, n, out, nblocks):
    """PPI0 = src filtered by the separable tent ``taps ⊗ taps`` (borders clamped onto the same phase)."""
    h, w = src.shape
    half = n - 1
    span = 2 * n - 1
    for blk in prange(nblocks):
        y_lo = blk * h // nblocks
        y_hi = (blk + 1) * h // nblocks
        if y_lo >= y_hi:
            continue
        ring = np.empty((span, w), np.float32)
        for r in range(y_lo - half, y_lo + half):
            _hfilter(src, _same_band(r, h, n), taps, n, ring[r % span])
        for y in range(y_lo, y_hi):
            r = y + half
            _hfilter(src, _same_band(r, h, n), taps, n, ring[r % span])
            o = out[y]
            hr = ring[(y - half) % span]
            wt = taps[0]
            for x in range(w):
                o[x] = wt * hr[x]
            for t in range(-half + 1, half + 1):
                wt = taps[t + half]
                hr = ring[(y + t) % span]
                for x in range(w):
                    o[x] += wt * hr[x]


@njit(parallel=True, cache=True)
def balance_kernel(src, gpos, out, nblocks):
    """``out[y, x] = gpos[y % n, x % n] * src[y, x]`` as float32 (per-band gains of PPID).

    The n gain rows are tiled once per block: an ``x % n`` per pixel (a runtime n, so an integer
    division each) made this step 35 ms a frame, three times the tent filter (docs/benchmarks.md)."""
    h, w = src.shape
    n = gpos.shape[0]
    for blk in prange(nblocks):
        y_lo = blk * h // nblocks
        y_hi = (blk + 1) * h // nblocks
        gain_rows = np.empty((n, w), np.float32)
        for py in range(n):
            g = gpos[py]
            gr = gain_rows[py]
            for x0 in range(0, w - n + 1, n):
                for j in range(n):
                    gr[x0 + j] = g[j]
            for x in range(w - w % n, w):
                gr[x] = g[x - (w - w % n)]
        for y in range(y_lo, y_hi):
            row_gain = gain_rows[y % n]
            s = src[y]
            o = out[y]
            for x in range(w):
                o[x] = row_gain[x] * np.float32(s[x])


# The 4 "positive" directions d (each also serves −d) and the unit step across each.
_PDIR_Y = np.array([0, 1, 1, 1], dtype=np.int64)
_PDIR_X = np.array([1, 0, 1, -1], dtype=np.int64)
_PERP_Y = np.array([1, 0, 1, 1], dtype=np.int64)
_PERP_X = np.array([0, 1, -1, 1], dtype=np.int64)


@njit(cache=True, inline="always")
def _inside(y, x, h, w):
    return 0 <= y < h and 0 <= x < w


@njit(cache=True)
def _edge_slow(src, y, x, k, n):
    """Border version of the edge measure A_k(y, x) (see ppi_refine_kernel)."""
    h, w = src.shape
    qy = y + n * _PDIR_Y[k]
    qx = x + n * _PDIR_X[k]
    if not _inside(qy, qx, h, w):
        return np.float32(0.0)
    centre = abs(np.float32(src[y, x]) - np.float32(src[qy, qx]))
    acc = 2 * centre
    for s in (-1, 1):
        ay = y + s * _PERP_Y[k]
        ax = x + s * _PERP_X[k]
        by = ay + n * _PDIR_Y[k]
        bx = ax + n * _PDIR_X[k]
        if _inside(ay, ax, h, w) and _inside(by, bx, h, w):
            acc += abs(np.float32(src[ay, ax]) - np.float32(src[by, bx]))
        else:
            acc += centre
    return np.float32(0.25) * acc


@njit(cache=True, inline="always", error_model="numpy")
def _edge_row(src, y, k, n, dst):
    """A_k(y, ·): 1-2-1 weighted mean of |R(p+δ) − R(p+δ+n·d_k)| over δ ∈ {−perp, 0, +perp}."""
    h, w = src.shape
    dy = n * _PDIR_Y[k]
    dx = n * _PDIR_X[k]
    py = _PERP_Y[k]
    px = _PERP_X[k]
    m = n + 1
    if y - 1 >= 0 and y + 1 + dy < h:
        span = w - 2 * m
        ra = src[y - py, m - px :]
        qa = src[y - py + dy, m - px + dx :]
        r0 = src[y, m:]
        q0 = src[y + dy, m + dx :]
        rb = src[y + py, m + px :]
        qb = src[y + py + dy, m + px + dx :]
        ds = dst[m:]
        for i in range(span):
            ds[i] = np.float32(0.25) * (
                abs(np.float32(ra[i]) - np.float32(qa[i]))
                + np.float32(2.0) * abs(np.float32(r0[i]) - np.float32(q0[i]))
                + abs(np.float32(rb[i]) - np.float32(qb[i]))
            )
        for x in range(m):
            dst[x] = _edge_slow(src, y, x, k, n)
        for x in range(w - m, w):
            dst[x] = _edge_slow(src, y, x, k, n)
    else:
        for x in range(w):
            dst[x] = _edge_slow(src, y, x, k, n)


@njit(parallel=True, cache=True, error_model="numpy")
def ppi_refine_kernel(src, ppi0, n, ppi_out, diff_out, nblocks):
    """Edge-sensitive PPI (Mihoubi et al. 2017): PPI(p) = R(p) + Σ_q γ_q (PPI0(q) − R(q)) / Σ_q γ_q.

    q runs over the (up to) 8 pixels of p's band at distance n inside the frame, q = p ± n·d_k.
    γ = 1 / (1 + A), A = the 1-2-1 weighted mean of |R(p+δ) − R(q+δ)| for δ across the p→q line:
    A for p→p+n·d is A_k(p), for p→p−n·d it is A_k(p−n·d) (the same pixel pairs), so one edge row
    per positive direction serves both. ``diff_out`` receives R − PPI, which PPID interpolates.
    """
    h, w = src.shape
    slots = n + 1
    for blk in prange(nblocks):
        y_lo = blk * h // nblocks
        y_hi = (blk + 1) * h // nblocks
        if y_lo >= y_hi:
            continue
        edge = np.empty((4, slots, w), np.float32)  # ring of A rows y−n .. y
        num = np.empty(w, np.float32)
        den = np.empty(w, np.float32)
        for r in range(max(0, y_lo - n), y_lo):
            for k in range(4):
                _edge_row(src, r, k, n, edge[k, r % slots])
        for y in range(y_lo, y_hi):
            for k in range(4):
                _edge_row(src, y, k, n, edge[k, y % slots])
            for x in range(w):
                num[x] = 0.0
                den[x] = 0.0
            for k in range(4):
                for sgn in (1, -1):
                    qy = y + sgn * n * _PDIR_Y[k]
                    if qy < 0 or qy >= h:
                        continue
                    qx = sgn * n * _PDIR_X[k]
                    lo = max(0, -qx)
                    hi = min(w, w - qx)
                    # A of the pair (p, q): A_k(p) going forward, A_k(q) going back
                    a = edge[k, y % slots, lo:hi] if sgn > 0 else edge[k, qy % slots, lo + qx : hi + qx]
                    srow = src[qy, lo + qx : hi + qx]
                    prow = ppi0[qy, lo + qx : hi + qx]
                    nu = num[lo:hi]
                    de = den[lo:hi]
                    for i in range(hi - lo):
                        g = np.float32(1.0) / (np.float32(1.0) + a[i])
                        nu[i] += g * (prow[i] - np.float32(srow[i]))
                        de[i] += g
            rrow = src[y]
            po = ppi_out[y]
            do = diff_out[y]
            for x in range(w):
                corr = num[x] / den[x]
                po[x] = np.float32(rrow[x]) + corr
                do[x] = -corr


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
