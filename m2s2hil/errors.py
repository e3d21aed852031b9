"""The application's typed errors: bad input from a person, a file or a client.

The root :class:`M2S2Error` lives in ``m2s2hil.protocols.errors`` so that device errors
(``m2s2hil.drivers.errors``) share it; this module adds what only the application
raises. Each error carries enough context to say what went wrong and where.
"""

from __future__ import annotations

from typing import Any

from m2s2hil.protocols.errors import M2S2Error

__all__ = ["CatalogError", "ConfigError", "KeyedError", "M2S2Error", "UsageError", "validation_problem"]


class UsageError(M2S2Error):
    """Bad input from a person or a client: exit code 2, HTTP 4xx."""

    exit_code = 2


class CatalogError(UsageError):
    """A satellite, build, material, lighting condition or elevation that is not in the catalog."""


class KeyedError(UsageError):
    """Bad input found in a file or document: ``source`` names it, ``key`` the dotted path
    inside it (empty for the whole thing), ``problem`` what is wrong."""

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = source
        self.key = key
        self.problem = problem
        where = f"{source}: {key}" if key else source
        super().__init__(f"{where}: {problem}")


class ConfigError(KeyedError):
    """A rig configuration file that cannot be used."""


def validation_problem(exc: Any) -> tuple[str, str]:
    """(dotted key, message) of a pydantic ``ValidationError``'s first error, with a count
    of the others, so a bad file or request is reported as one clear line."""
    errors = exc.errors()
    err = errors[0]
    key = ".".join(str(p) for p in err["loc"])
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        msg = "unknown key"
    more = len(errors) - 1
    if more:
        msg += f" (and {more} more problem{'s' if more > 1 else ''})"
    return key, msg
