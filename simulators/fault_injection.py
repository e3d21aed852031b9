"""Fault injection for simulated devices.

A :class:`FaultPlan` holds rules; a device asks it, at the points where a fault can
happen, whether one fires now. Rules come from the rig configuration
(``[simulation.faults.NAME]``) or straight from a test::

    dev.faults.add("drop_reply", count=1)
    dev.faults.add("stall", after=2)        # the third move stalls
    dev.faults.add("vanish", duration_s=0.5)

Generic kinds, handled by :class:`~m2s2hil.simulators.device.SimDevice` itself:
``drop_reply``, ``garble``, ``late_reply`` (``delay_s``), ``vanish`` (``duration_s``).
Device kinds, handled by the device: ``stall`` and ``alarm`` (motion),
``relay_stuck`` (relays), and the camera's ``frame_timeout``, ``incomplete``,
``trailer_error``, ``unplug``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

FAULT_KINDS = frozenset(
    {
        "drop_reply",
        "garble",
        "late_reply",
        "vanish",
        "stall",
        "alarm",
        "relay_stuck",
        "frame_timeout",
        "incomplete",
        "trailer_error",
        "unplug",
    }
)


@dataclass
class FaultRule:
    kind: str
    count: int = 1  # how many times it fires; -1 = forever
    after: int = 0  # occurrences to let pass first
    params: dict[str, Any] = field(default_factory=dict)
    fired: int = 0
    seen: int = 0

    @property
    def exhausted(self) -> bool:
        return self.count >= 0 and self.fired >= self.count


class FaultPlan:
    """Thread-safe list of fault rules for one device."""

    def __init__(self, rules: list[FaultRule] | None = None) -> None:
        self._rules: list[FaultRule] = list(rules or [])
        self._lock = threading.Lock()
        self.log: list[tuple[str, dict[str, Any]]] = []  # what fired, for tests and records

    def add(self, kind: str, count: int = 1, after: int = 0, **params: Any) -> FaultRule:
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r}; known: {', '.join(sorted(FAULT_KINDS))}")
        rule = FaultRule(kind=kind, count=count, after=after, params=params)
        with self._lock:
            self._rules.append(rule)
        return rule

    def clear(self) -> None:
        with self._lock:
            self._rules.clear()

    def take(self, kind: str) -> dict[str, Any] | None:
        """One occurrence of ``kind``: the rule's params if a fault fires now, else None."""
        with self._lock:
            for rule in self._rules:
                if rule.kind != kind or rule.exhausted:
                    continue
                rule.seen += 1
                if rule.seen <= rule.after:
                    continue
                rule.fired += 1
                self.log.append((kind, dict(rule.params)))
                return dict(rule.params)
        return None

    def pending(self, kind: str) -> bool:
        with self._lock:
            return any(r.kind == kind and not r.exhausted for r in self._rules)

    @classmethod
    def from_config(cls, items: list[dict[str, Any]]) -> FaultPlan:
        plan = cls()
        for i, item in enumerate(items):
            item = dict(item)
            try:
                kind = item.pop("kind")
            except KeyError:
                raise ValueError(f"fault #{i}: missing 'kind'") from None
            count = int(item.pop("count", 1))
            after = int(item.pop("after", 0))
            plan.add(kind, count=count, after=after, **item)
        return plan
