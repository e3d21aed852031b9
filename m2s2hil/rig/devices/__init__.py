"""The device kinds a rig can have, one entry each: the one place a kind is described.

A kind's entry (a module of this package) holds its driver and simulator factories, what
``m2s2hil rig probe`` reads from it, how it is recognised on another device's port, what its
errors mean while it opens, and (read from the simulators) its fault kinds; its rig-file
rules (role, axis names) are ``config.PROTOCOLS``, below the rig. Adding a device kind: its
codec (``protocols/``), driver (``drivers/``), simulator (``simulators/``, with its faults in
``fault_injection.FAULT_KINDS_BY_DEVICE``), its protocol name in ``config.DeviceProtocol`` and
``PROTOCOLS``, and a module here listed in :data:`KINDS`; tests/test_rig_devices.py checks
that they agree.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from m2s2hil.rig.devices import ascii_relay, grbl, modbus_relay, u3v, zaber
from m2s2hil.rig.devices.kind import CameraKind, DeviceKind, MotionKind, RelayKind

#: Every kind by its protocol name, in the order identify_port sends their probes (Zaber's
#: status poll first: a GRBL answers it with an error line, which names it too).
KINDS: Mapping[str, DeviceKind] = MappingProxyType({
    kind.protocol: kind for kind in (zaber.KIND, grbl.KIND, modbus_relay.KIND, ascii_relay.KIND, u3v.KIND)
})


def kind_of(protocol: str) -> DeviceKind:
    """The entry of ``protocol`` (a rig file's protocol name, or ``u3v``)."""
    return KINDS[protocol]


def motion_kind(protocol: str) -> MotionKind:
    kind = KINDS[protocol]
    if not isinstance(kind, MotionKind):
        raise TypeError(f"{protocol} is not a motion protocol")
    return kind


def relay_kind(protocol: str) -> RelayKind:
    kind = KINDS[protocol]
    if not isinstance(kind, RelayKind):
        raise TypeError(f"{protocol} is not a relay protocol")
    return kind


CAMERA: CameraKind = u3v.KIND

__all__ = ["CAMERA", "KINDS", "kind_of", "motion_kind", "relay_kind"]
