"""Test processes side by side never share a numba cache (tests/numba_cache.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent

KERNEL = '''
import numpy as np
from numba import njit


@njit(cache=True)
def twice_sum(a):
    s = a.dtype.type(0)
    for x in a:
        s += x
    return 2 * s
'''

WORKER = '''
import sys, time
sys.path[:0] = [{here!r}, {tree!r}]
from numba_cache import claim_slot
slot = claim_slot(__import__("pathlib").Path({base!r}))
import numpy as np
import kernel
values = [kernel.twice_sum(np.arange(1000, dtype=dtype)) for dtype in sys.argv[1].split(",")]
print(slot.name, min(values), sum(kernel.twice_sum.stats.cache_hits.values()), flush=True)
time.sleep(float(sys.argv[2]))  # hold the slot while the other one runs
'''


def _start(tree: Path, base: Path, dtype: str, hold_s: float) -> subprocess.Popen:
    code = WORKER.format(here=str(HERE), tree=str(tree), base=str(base))
    return subprocess.Popen([sys.executable, "-c", code, dtype, str(hold_s)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow  # three interpreters importing numba and compiling: ~6 s on 2 shared cores
def test_two_processes_compiling_one_tree_get_their_own_caches(tmp_path):
    tree, base = tmp_path / "tree", tmp_path / "caches"
    tree.mkdir()
    (tree / "kernel.py").write_text(KERNEL)
    # Two signatures of one cache=True kernel compiled at the same time, as two test runs would.
    procs = [_start(tree, base, "float32", 0.3), _start(tree, base, "int64", 0.3)]
    outs = [p.communicate(timeout=120) for p in procs]
    for p, (_out, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err
    slots = sorted(out.split()[0] for out, _ in outs)
    assert slots == ["slot-0", "slot-1"]
    assert sorted(float(out.split()[1]) for out, _ in outs) == [999000.0, 999000.0]
    # The next run, alone, takes slot 0 again and finds the kernel compiled there.
    again = _start(tree, base, "float32,int64", 0.0)
    out, err = again.communicate(timeout=120)
    assert again.returncode == 0, err
    name, value, hits = out.split()
    assert name == "slot-0" and float(value) == 999000.0 and int(hits) >= 1


CLAIM = '''
import os, sys
sys.path.insert(0, {here!r})
from numba_cache import use_private_numba_cache
use_private_numba_cache(worker=sys.argv[1] == "worker")
print(os.environ["NUMBA_CACHE_DIR"], flush=True)
sys.stdin.read()  # hold the slot until the test lets go
'''


def _claim(role: str, env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", CLAIM.format(here=str(HERE)), role], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_xdist_workers_get_their_own_slots_under_a_cache_dir_given_from_outside(tmp_path):
    """`pytest -n 3` with NUMBA_CACHE_DIR set (by CI, say): the workers inherit the same value, so
    each claims a slot under it; a process that is no worker (a test's subprocess) keeps it as it is."""
    given = tmp_path / "given"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(given)}
    procs, dirs, errs = [], [], []
    try:
        for role in ("worker", "worker", "plain"):
            procs.append(_claim(role, env))
            dirs.append(procs[-1].stdout.readline().strip())  # claimed, and held, before the next starts
        errs = [p.communicate(input="", timeout=60)[1] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert [p.returncode for p in procs] == [0, 0, 0], errs
    assert dirs == [str(given / "slot-0"), str(given / "slot-1"), str(given)]


LOAD = '''
import os, sys
if len(sys.argv) > 1:
    os.environ["NUMBA_CACHE_DIR"] = sys.argv[1]
sys.path.insert(0, {pkg!r})
import numpy as np
import kernel
kernel.twice_sum(np.arange(3.0))
print(sum(kernel.twice_sum.stats.cache_hits.values()), flush=True)
'''


@pytest.mark.slow  # two interpreters importing numba, one compiling: ~3 s
def test_a_fresh_slot_is_seeded_from_the_package_cache(tmp_path):
    """What a run without NUMBA_CACHE_DIR (or `m2s2hil compile-kernels`) compiled into __pycache__
    is copied into a new slot, so a test process there loads the kernel instead of compiling it."""
    from numba_cache import seed_slot

    tree = tmp_path / "tree"
    pkg = tree / "simulators"  # one of the package-dir mapping's folders
    pkg.mkdir(parents=True)
    (pkg / "kernel.py").write_text(KERNEL)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    code = LOAD.format(pkg=str(pkg))
    first = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert first.returncode == 0 and first.stdout.split() == ["0"], first.stderr  # compiled, in tree
    assert len(list((pkg / "__pycache__").glob("kernel.twice_sum-*.nbi"))) == 1

    slot = tmp_path / "caches" / "slot-0"
    assert seed_slot(slot, tree) == 1
    assert seed_slot(slot, tree) == 0  # up to date: nothing copied again
    loaded = subprocess.run([sys.executable, "-c", code, str(slot)], env=env, capture_output=True, text=True,
                            timeout=120)
    assert loaded.returncode == 0 and loaded.stdout.split() == ["1"], loaded.stderr  # a cache hit
    # The package's cache changes (a newer index): the slot takes the new one.
    index = next((pkg / "__pycache__").glob("*.nbi"))
    os.utime(index, (index.stat().st_atime, index.stat().st_mtime + 10))
    assert seed_slot(slot, tree) == 1
