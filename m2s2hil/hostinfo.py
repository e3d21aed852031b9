"""The machine a figure was measured on: recorded with every benchmark figure, in
``evaluate``'s ``summary.json`` and by ``m2s2hil bench demosaic``."""

from __future__ import annotations

import os
import platform

import psutil


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe_machine() -> str:
    """CPU model, logical CPUs, memory, OS and Python, e.g. for docs/benchmarks.md."""
    mem = psutil.virtual_memory().total / 2**30
    return (
        f"{cpu_model()} ({platform.machine()}), {os.cpu_count()} logical CPUs, {mem:.0f} GiB, "
        f"{platform.system()} {platform.release()}, Python {platform.python_version()}"
    )
