"""What ``m2s2hil rig probe`` reports: one :class:`Finding` per item a device was asked about.

Each device kind's probe (its registry entry) adds findings to a :class:`ProbeReport`;
:func:`m2s2hil.rig.probe.probe_rig` collects them for the whole rig.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from m2s2hil.rig.open_errors import RigOpenError

#: Relative difference below which two rates or accelerations agree (GRBL prints 3 decimals).
REL_TOL = 1e-3


@dataclass(frozen=True)
class Finding:
    device: str
    item: str  # "$110 X max rate", "model", ...
    expected: str  # what the rig file implies ("" = nothing to compare: shown for information)
    actual: str  # what the device reports
    ok: bool | None  # None: information only
    effect: str = ""  # what a mismatch causes
    #: For --apply: (setting, value) to write to fix it; None when it cannot be written.
    fix: tuple[str, float] | None = None


@dataclass
class ProbeReport:
    rig: str
    findings: list[Finding] = field(default_factory=list)
    errors: list[RigOpenError] = field(default_factory=list)  # devices that could not be opened

    @property
    def mismatches(self) -> list[Finding]:
        return [f for f in self.findings if f.ok is False]

    @property
    def ok(self) -> bool:
        return not self.mismatches and not self.errors


def agree(actual: float, expected: float) -> bool:
    return math.isclose(actual, expected, rel_tol=REL_TOL, abs_tol=1e-6)


def num(v: float) -> str:
    return f"{v:.6g}"
