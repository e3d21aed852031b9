"""Fault injection for simulated devices.

A :class:`FaultPlan` holds rules; a device asks it, at the points where a fault can
happen (an *opportunity*: a reply, a move, a frame), whether one fires now. Rules come
from the rig configuration (``[[simulation.faults.NAME]]``) or straight from a test::

    dev.faults.add("drop_reply", count=1)
    dev.faults.add("stall", after=2)             # the third move stalls
    dev.faults.add("vanish", duration_s=0.5)
    dev.faults.add("garble", rate=0.01)          # 1 % of replies, forever, seeded

A rule lets ``after`` opportunities pass, then fires on each one (or, with ``rate``, on
each with that probability, drawn from the plan's seeded generator) until it has fired
``count`` times (``-1``: forever; the default is 1, or forever when a rate is given).

:data:`FAULT_KINDS_BY_DEVICE` says which kinds each simulator handles and which
parameters each kind takes (with the simulator's default); the rig configuration checks
faults against it. Generic serial kinds, handled by
:class:`~m2s2hil.simulators.device.SimDevice` itself: ``drop_reply``, ``garble``
(``bytes``), ``late_reply`` (``delay_s``), ``vanish`` (``duration_s``). Device kinds:
``stall`` (``fraction``) and ``alarm`` (``at``, plus GRBL's ``code`` or Zaber's ``flag``)
for motion, ``slow_motion`` (``factor``), ``hang`` (``fraction``) and GRBL's ``hold_stuck``
for a slow or stuck rig, ``relay_stuck`` (``channel``) for relays, and the camera's ``frame_timeout``,
``incomplete`` (``fraction``), ``trailer_error`` (``status``), ``stall``, ``unplug``
(``duration_s``).
"""

from __future__ import annotations

import random
import threading
from dataclasses import dataclass, field
from typing import Any

_SERIAL: dict[str, tuple[str, ...]] = {
    "drop_reply": (),
    "garble": ("bytes",),  # default 3: about three bytes of every reply flipped
    "late_reply": ("delay_s",),  # default 2 s
    "vanish": ("duration_s",),  # default 1 s
}

#: A slow or stuck rig (simulators.grbl_motion / simulators.zaber): ``slow_motion`` runs moves
#: ``factor`` times slower than the controller's settings say (default 5); ``hang`` freezes
#: one part-way while the controller still reports it moving (default fraction 0.5).
_SLOW_RIG: dict[str, tuple[str, ...]] = {"slow_motion": ("factor",), "hang": ("fraction",)}

#: For each kind of simulated device (the rig file's protocol names, ``u3v`` for the
#: camera), the fault kinds its simulator handles and the parameters each kind takes. Each
#: kind's registry entry reads its row (m2s2hil/rig/devices/, ``DeviceKind.fault_kinds``);
#: tests/test_rig_devices.py checks that the entry's simulator asks for exactly these.
FAULT_KINDS_BY_DEVICE: dict[str, dict[str, tuple[str, ...]]] = {
    "grbl": {**_SERIAL, "stall": ("fraction",), "alarm": ("at", "code"), **_SLOW_RIG, "hold_stuck": ()},
    "zaber": {**_SERIAL, "stall": ("fraction",), "alarm": ("at", "flag"), **_SLOW_RIG},
    "modbus-rtu": {**_SERIAL, "relay_stuck": ("channel",)},
    "ascii-relay": {**_SERIAL, "relay_stuck": ("channel",)},
    "u3v": {
        "drop_reply": (),  # a GenCP acknowledge
        "late_reply": ("delay_s",),  # default 1 s
        "unplug": ("duration_s",),
        "stall": (),
        "frame_timeout": (),
        "incomplete": ("fraction",),
        "trailer_error": ("status",),
    },
}

FAULT_KINDS = frozenset(k for kinds in FAULT_KINDS_BY_DEVICE.values() for k in kinds)


@dataclass
class InjectedFault:
    """One rule of a :class:`FaultPlan` and its counters."""

    kind: str
    count: int = 1  # how many times it fires; -1 = forever
    after: int = 0  # opportunities to let pass first
    rate: float | None = None  # probability of firing at each opportunity; None = always
    params: dict[str, Any] = field(default_factory=dict)
    fired: int = 0
    seen: int = 0

    @property
    def exhausted(self) -> bool:
        return self.count >= 0 and self.fired >= self.count


class FaultPlan:
    """Thread-safe list of fault rules for one device; ``seed`` drives the ``rate`` draws."""

    def __init__(self, rules: list[InjectedFault] | None = None, *, seed: int | str = 0) -> None:
        self._rules: list[InjectedFault] = list(rules or [])
        self._lock = threading.Lock()
        self._rng = random.Random(seed)
        self.log: list[tuple[str, dict[str, Any]]] = []  # what fired, for tests and records

    def add(
        self, kind: str, count: int | None = None, after: int = 0, rate: float | None = None, **params: Any
    ) -> InjectedFault:
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r}; known: {', '.join(sorted(FAULT_KINDS))}")
        if rate is not None and not 0.0 < rate <= 1.0:
            raise ValueError(f"fault rate must be in (0, 1], got {rate!r}")
        if count is None:
            count = -1 if rate is not None else 1
        if count < -1 or after < 0:
            raise ValueError(f"fault count must be >= -1 and after >= 0, got count={count}, after={after}")
        rule = InjectedFault(kind=kind, count=count, after=after, rate=rate, params=params)
        with self._lock:
            self._rules.append(rule)
        return rule

    def clear(self) -> None:
        with self._lock:
            self._rules.clear()

    def take(self, kind: str) -> dict[str, Any] | None:
        """One opportunity for ``kind``: the rule's params if a fault fires now, else None."""
        with self._lock:
            for rule in self._rules:
                if rule.kind != kind or rule.exhausted:
                    continue
                rule.seen += 1
                if rule.seen <= rule.after:
                    continue
                if rule.rate is not None and self._rng.random() >= rule.rate:
                    continue
                rule.fired += 1
                self.log.append((kind, dict(rule.params)))
                return dict(rule.params)
        return None

    def pending(self, kind: str) -> bool:
        with self._lock:
            return any(r.kind == kind and not r.exhausted for r in self._rules)

    @classmethod
    def from_config(cls, items: list[dict[str, Any]], *, seed: int | str = 0) -> FaultPlan:
        """A plan from plain mappings (``kind``, optional ``count``/``after``/``rate``, params)."""
        plan = cls(seed=seed)
        for i, item in enumerate(items):
            item = dict(item)
            try:
                kind = item.pop("kind")
            except KeyError:
                raise ValueError(f"fault #{i}: missing 'kind'") from None
            count = item.pop("count", None)
            rate = item.pop("rate", None)
            plan.add(
                kind, count=None if count is None else int(count), after=int(item.pop("after", 0)),
                rate=None if rate is None else float(rate), **item,
            )
        return plan
