"""Application-level typed errors.

Device errors live in ``m2s2hil.drivers.errors``; these cover user input
(configuration, catalog names, plans) and the application's own failures.
Each carries enough context to say what went wrong and where.
"""

from __future__ import annotations

from typing import Any


class M2S2Error(Exception):
    """Base of every error the application raises on purpose."""

    exit_code = 1


class UsageError(M2S2Error):
    """Bad input from a person or a client: exit code 2, HTTP 4xx."""

    exit_code = 2


class CatalogError(UsageError):
    """A satellite, build, material, lighting condition or elevation that is not in the catalog."""


class ConfigError(UsageError):
    """A rig configuration file that cannot be used.

    ``source`` names the file, ``key`` the dotted path inside it.
    """

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = source
        self.key = key
        self.problem = problem
        where = f"{source}: {key}" if key else source
        super().__init__(f"{where}: {problem}")


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
