"""Z-buffer triangle rasteriser (numba), orthographic, for the simulated camera.

Coordinates are in pixels: a vertex at (sx, sy) covers pixel centres (x + 0.5, y + 0.5);
``sz`` is depth, larger = nearer the viewer. Kernels take a row range and release the
GIL, so a frame can be split into bands rendered on several threads that write
disjoint rows.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import cache

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _raster_rows(
    sx, sy, sz, nx, ny, nz, tris, tri_label, depth, nrm, label, r0, r1, write_attrs
):  # pragma: no cover
    _h, w = depth.shape
    for t in range(tris.shape[0]):
        i0, i1, i2 = tris[t, 0], tris[t, 1], tris[t, 2]
        x0, y0, x1, y1, x2, y2 = sx[i0], sy[i0], sx[i1], sy[i1], sx[i2], sy[i2]
        ymin = min(y0, min(y1, y2))
        ymax = max(y0, max(y1, y2))
        ya = max(r0, math.ceil(ymin - 0.5))
        yb = min(r1 - 1, math.floor(ymax - 0.5))
        if ya > yb:
            continue
        xmin = min(x0, min(x1, x2))
        xmax = max(x0, max(x1, x2))
        if xmax < 0.0 or xmin > w:
            continue
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-9:
            continue
        inv = 1.0 / area
        # Barycentric weight of vertex k is linear in (x, y): w_k = a_k x + b_k y + c_k.
        a0 = (y1 - y2) * inv
        b0 = (x2 - x1) * inv
        c0 = (x1 * y2 - x2 * y1) * inv
        a1 = (y2 - y0) * inv
        b1 = (x0 - x2) * inv
        c1 = (x2 * y0 - x0 * y2) * inv
        a2 = (y0 - y1) * inv
        b2 = (x1 - x0) * inv
        c2 = (x0 * y1 - x1 * y0) * inv
        z0, z1, z2 = sz[i0], sz[i1], sz[i2]
        for y in range(ya, yb + 1):
            yc = y + 0.5
            e0 = b0 * yc + c0
            e1 = b1 * yc + c1
            e2 = b2 * yc + c2
            lo = -1e30
            hi = 1e30
            empty = False
            for a, e in ((a0, e0), (a1, e1), (a2, e2)):
                if a > 1e-12:
                    lo = max(lo, -e / a)
                elif a < -1e-12:
                    hi = min(hi, -e / a)
                elif e < -1e-9:
                    empty = True
            if empty or lo > hi:
                continue
            xa = max(0, math.ceil(lo - 0.5))
            xb = min(w - 1, math.floor(hi - 0.5))
            for x in range(xa, xb + 1):
                xc = x + 0.5
                w0 = a0 * xc + e0
                w1 = a1 * xc + e1
                w2 = 1.0 - w0 - w1
                z = w0 * z0 + w1 * z1 + w2 * z2
                if z > depth[y, x]:
                    depth[y, x] = z
                    if write_attrs:
                        nrm[0, y, x] = w0 * nx[i0] + w1 * nx[i1] + w2 * nx[i2]
                        nrm[1, y, x] = w0 * ny[i0] + w1 * ny[i1] + w2 * ny[i2]
                        nrm[2, y, x] = w0 * nz[i0] + w1 * nz[i1] + w2 * nz[i2]
                        label[y, x] = tri_label[t]


@cache
def n_threads() -> int:
    return max(1, min(2, os.cpu_count() or 1))


@cache
def _pool(n: int) -> ThreadPoolExecutor:
    numba_ready()  # here, in the thread that fans the bands out, before a worker calls a kernel
    return ThreadPoolExecutor(max_workers=n, thread_name_prefix="sim-render")


def numba_ready() -> None:
    """Numba fills its type registry (``typeof_impl``, a ``functools.singledispatch``) on its first
    compile or cache load, importing as it goes (a second or more on a loaded machine); a thread
    typing its arguments meanwhile iterates that registry and fails with "dictionary changed size
    during iteration" (the render's bands compile at once on their first frame). Filled once here,
    under numba's compiler lock; later calls cost a fraction of a millisecond."""
    from numba.core.compiler_lock import global_compiler_lock
    from numba.core.registry import cpu_target

    with global_compiler_lock:
        cpu_target.target_context.refresh()


def split_rows(fn: Callable[[int, int], object], height: int, threads: int | None = None) -> None:
    """Run ``fn(r0, r1)`` over row bands on a small thread pool (kernels release the GIL)."""
    n = threads or n_threads()
    # Below 256 rows the hand-offs cost more than the rows: a 64² simulator frame took 6.8 ms in
    # bands, 2.6 ms in one (a 128² one 10.2 and 5.3 ms; equal at 256²; 2026-12-07, 2 vCPUs).
    if n <= 1 or height < 256:
        fn(0, height)
        return
    # More bands than threads balances a satellite that fills only part of the frame.
    bands = 4 * n
    edges = np.linspace(0, height, bands + 1).astype(int)
    futures = [_pool(n).submit(fn, int(a), int(b)) for a, b in itertools.pairwise(edges)]
    for f in futures:
        f.result()


def rasterize(
    screen: np.ndarray, normals: np.ndarray | None, triangles: np.ndarray, tri_label: np.ndarray,
    height: int, width: int, threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Rasterise triangles given screen-space vertices (N, 3) = (x px, y px, depth).

    Returns depth (H, W) float32 (-inf where empty), and, when ``normals`` is given,
    interpolated (unnormalised) normals (3, H, W) float32 and the label map (H, W) uint8.
    """
    sx = np.ascontiguousarray(screen[:, 0], dtype=np.float64)
    sy = np.ascontiguousarray(screen[:, 1], dtype=np.float64)
    sz = np.ascontiguousarray(screen[:, 2], dtype=np.float64)
    depth = np.full((height, width), -np.inf, dtype=np.float32)
    write = normals is not None
    if write:
        nx, ny, nz = (np.ascontiguousarray(normals[:, k], dtype=np.float64) for k in range(3))
        nrm = np.zeros((3, height, width), dtype=np.float32)
        label = np.zeros((height, width), dtype=np.uint8)
    else:
        nx = ny = nz = np.zeros(len(sx))
        nrm = np.zeros((3, 1, 1), dtype=np.float32)
        label = np.zeros((1, 1), dtype=np.uint8)
    tris = np.ascontiguousarray(triangles, dtype=np.int32)
    lab = np.ascontiguousarray(tri_label, dtype=np.uint8)
    split_rows(
        lambda r0, r1: _raster_rows(sx, sy, sz, nx, ny, nz, tris, lab, depth, nrm, label, r0, r1, write),
        height, threads,
    )
    return (depth, nrm, label) if write else (depth, None, None)
