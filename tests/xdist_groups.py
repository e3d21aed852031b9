"""Which tests of a ``pytest -n N`` run share a worker (tests/conftest.py installs the scheduler).

Tests are handed out one by one (as ``--dist load`` does), except:

- the tests of a module that defines a module- or class-scoped fixture (a simulated capture,
  an evaluation, a plan expansion) go to one worker as a unit, so the fixture is built once
  rather than once per worker;
- the modules of :data:`KERNEL_MODULES`, which compile the numba kernels of every demosaicing
  method and of calibration (about 45 s on a cold cache, as in CI's fresh clone), form one unit,
  so one worker compiles them, not both. A capture's kernels (default method, the simulated
  camera) are compiled by every worker that captures.

xdist's own ``--dist loadgroup`` cannot do this here: it renames the test ids through an
attribute that pytest 9.2 no longer reads, so its groups are silently ignored. The scheduler
runs in the controller, which sees test ids only; a module's fixtures are read from its source.
"""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

from xdist.scheduler import LoadScopeScheduling

KERNEL_MODULES = frozenset({"test_demosaic.py", "test_calibration.py", "test_processing_pipeline.py",
                            "test_processing_stability.py",
                            # PPID's and WB's kernels, uint16 and float32, against a NumPy reference
                            "test_ppid_fused.py",
                            # compile-kernels runs every method (cold only where .ci/run's step was skipped)
                            "test_warmup.py"})
SHARED_SCOPES = frozenset({"module", "class", "package"})


@cache
def defines_shared_fixture(path: Path) -> bool:
    """Whether the module at ``path`` defines a fixture with a module, class or package scope."""
    try:
        tree = ast.parse(path.read_text(), str(path))
    except (OSError, SyntaxError):
        return False
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for deco in node.decorator_list:
                scopes = [kw.value.value for kw in getattr(deco, "keywords", ())
                          if kw.arg == "scope" and isinstance(kw.value, ast.Constant)]
                if set(scopes) & SHARED_SCOPES:
                    return True
    return False


def unit_of(nodeid: str, rootdir: Path) -> str:
    """The work unit of a test id: a shared group, its module, or the test itself."""
    module = nodeid.split("::", 1)[0]
    if Path(module).name in KERNEL_MODULES:
        return "numba-kernels"
    if defines_shared_fixture(rootdir / module):
        return module
    return nodeid


class GroupedScheduling(LoadScopeScheduling):
    """``--dist load`` with the units above."""

    def _split_scope(self, nodeid: str) -> str:
        return unit_of(nodeid, self.config.rootpath)
