"""The capture daemon's REST API (FastAPI) on top of the session service
(:mod:`m2s2hil.daemon`): see :func:`create_app` and docs/api.md.

``app.py`` assembles the application from the routers (``routes/``), the operator console's
routes (``console/``), the error handlers (``handlers.py``) and the defences (``guards/``).
Exports are loaded on first use so that ``m2s2hil --help`` does not import FastAPI.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .app import create_app, openapi_json
    from .settings import ServeSettings, load_serve_settings

__all__ = ["ServeSettings", "create_app", "load_serve_settings", "openapi_json"]

_WHERE = {"create_app": "app", "openapi_json": "app", "ServeSettings": "settings",
          "load_serve_settings": "settings"}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
