"""The capture daemon's REST API (FastAPI): see :func:`create_app` and docs/api.md.

Exports are loaded on first use so that ``m2s2hil --help`` does not import FastAPI.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .app import create_app, openapi_json
    from .manager import SessionManager
    from .settings import ServeSettings, load_serve_settings

__all__ = ["ServeSettings", "SessionManager", "create_app", "load_serve_settings", "openapi_json"]

_WHERE = {"create_app": "app", "openapi_json": "app", "SessionManager": "manager",
          "ServeSettings": "settings", "load_serve_settings": "settings"}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
