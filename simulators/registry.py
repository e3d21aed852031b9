"""Names of in-process simulated devices, for ``sim://NAME`` URLs."""

from __future__ import annotations

import threading
from typing import Any

_devices: dict[str, Any] = {}
_lock = threading.Lock()


def register(name: str, device: Any, *, replace: bool = True) -> None:
    with _lock:
        if not replace and name in _devices:
            raise KeyError(f"sim://{name} is already registered")
        _devices[name] = device


def unregister(name: str) -> None:
    with _lock:
        _devices.pop(name, None)


def lookup(name: str) -> Any:
    with _lock:
        try:
            return _devices[name]
        except KeyError:
            known = ", ".join(sorted(_devices)) or "none"
            raise KeyError(f"no simulated device sim://{name} (registered: {known})") from None


def names() -> list[str]:
    with _lock:
        return sorted(_devices)
