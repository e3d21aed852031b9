"""Non-temporal (streaming) row stores for the kernels that write a full-resolution cube.

A 2048² 10-band cube is 168 MB: it cannot stay in any cache, so every ordinary store of it first
reads the line it lands in (read for ownership) and later writes it back, twice the traffic the
cube needs. A streaming store writes the line without reading it. On the AMD EPYC VM the same
loop that writes the cube row by row from cached rows took 14.2 ms on one thread with ordinary
stores and 6.1 ms with streaming ones, 7.4 and 3.1 ms on two (docs/benchmarks.md, "Fifth pass").

``stream_copy(dst, src)`` copies a row computed in a cache-resident scratch row into the cube; the
kernels call ``store_fence()`` once a block is done, since streaming stores are weakly ordered
(x86: ``sfence``; elsewhere a sequentially consistent fence). LLVM lowers the vector store for the
machine it compiles on (``vmovntps`` on x86 at 128, 256 or 512 bits, ``stnp`` on AArch64), so
nothing here is specific to one CPU. The vector stores need a 64-byte aligned address: the head
of a row up to that boundary and its tail are copied one element at a time, and ``aligned_empty``
allocates the demosaicers' cubes on a 64-byte boundary so that, with rows a multiple of 16
floats, no row has a head.
"""

from __future__ import annotations

import platform

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

#: floats per vector store: 64 bytes, one cache line
LANES = 16
ALIGN = 64
_X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686", "x86")


@intrinsic
def _stream16(typingctx, dst, i, src, j):
    """``dst[i:i+16] = src[j:j+16]`` as one non-temporal vector store (dst + i 64-byte aligned)."""
    if not (
        isinstance(dst, types.Array)
        and isinstance(src, types.Array)
        and dst.dtype == types.float32
        and src.dtype == types.float32
    ):
        return None
    sig = types.void(dst, i, src, j)

    def codegen(context, builder, signature, args):
        d, iv, s, jv = args
        da = context.make_array(signature.args[0])(context, builder, d)
        sa = context.make_array(signature.args[2])(context, builder, s)
        vty = ir.VectorType(ir.FloatType(), LANES)
        sp = builder.bitcast(builder.gep(sa.data, [jv]), vty.as_pointer())
        dp = builder.bitcast(builder.gep(da.data, [iv]), vty.as_pointer())
        store = builder.store(builder.load(sp, align=4), dp, align=ALIGN)
        store.set_metadata("nontemporal", builder.module.add_metadata([ir.IntType(32)(1)]))
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def store_fence(typingctx):
    """Order the streaming stores before what follows (the end of a kernel's block)."""
    sig = types.void()

    def codegen(context, builder, signature, args):
        if _X86:
            fnty = ir.FunctionType(ir.VoidType(), [])
            builder.call(builder.module.declare_intrinsic("llvm.x86.sse.sfence", fnty=fnty), [])
        else:
            builder.fence("seq_cst")
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, inline="always")
def stream_copy(dst, src):
    """``dst[:] = src[:dst.shape[0]]`` with streaming stores where both rows are contiguous and
    ``dst`` is float-aligned (any other pair gets ordinary stores)."""
    w = dst.shape[0]
    addr = dst.ctypes.data
    if dst.strides[0] != 4 or src.strides[0] != 4 or addr & 3 != 0:
        for x in range(w):
            dst[x] = src[x]
        return
    head = min(w, ((ALIGN - (addr & (ALIGN - 1))) & (ALIGN - 1)) >> 2)
    for x in range(head):
        dst[x] = src[x]
    x = head
    while x + LANES <= w:
        _stream16(dst, x, src, x)  # type: ignore[call-arg]  # a numba intrinsic: numba supplies its context
        x += LANES
    for k in range(x, w):
        dst[k] = src[k]


def aligned_empty(shape: tuple[int, ...], dtype: type = np.float32) -> np.ndarray:
    """``np.empty(shape, dtype)`` starting on a 64-byte boundary (numpy guarantees 16)."""
    dt = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    buf = np.empty(nbytes + ALIGN, np.uint8)
    off = (-buf.ctypes.data) % ALIGN
    return buf[off : off + nbytes].view(dt).reshape(shape)
