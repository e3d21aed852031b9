"""One transaction at a time on a shared serial line.

The engine, the API's emergency stop and status readers may call the same driver from
different threads; a command and its reply must not interleave with another thread's.
Classes using :func:`one_at_a_time` keep a reentrant lock in ``self._lock``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

_F = TypeVar("_F", bound=Callable[..., Any])


def one_at_a_time(method: _F) -> _F:
    """Run ``method`` holding ``self._lock``."""

    @functools.wraps(method)
    def wrapper(self, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper  # type: ignore[return-value]
