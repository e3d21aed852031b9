"""Application-level typed errors.

Device errors live in ``m2s2hil.drivers.errors``; these cover user input
(configuration, catalog names, plans) and the application's own failures.
Each carries enough context to say what went wrong and where.
"""

from __future__ import annotations


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
