"""``m2s2hil compile-kernels``: compile the numba kernels now rather than on the first frame."""

from __future__ import annotations

from rich.console import Console


def compile_kernels_cmd() -> None:
    """Compile every demosaicing, calibration and simulated-camera kernel into numba's cache.

    Run once after installing (``.ci/run`` does): otherwise the first session pays 1-2 minutes of
    compiling on its first frames. A warm cache makes this a no-op of a second or two."""
    from m2s2hil.warmup import compile_kernels

    console = Console(stderr=True)
    with console.status("compiling numba kernels"):
        total = compile_kernels(progress=lambda name, s: console.print(f"{name}: {s:.1f} s"))
    console.print(f"kernels ready in {total:.1f} s")
