"""The soak (issue 21.5): the daemon as a process for an hour of simulated time with sessions,
e-stops, holds, kill -9 and restarts, viewers and exports mixed, then every invariant.

    .venv/bin/python -m benchmarks.soak [--sim-s 3600] [--kills 6] [--seed 21] [--write docs/reliability.md]

``run.py`` drives it (``schedule.py`` is the seeded plan), ``checks.py`` holds the invariants,
``report.py`` the tables; tests/test_soak.py runs a reduced soak in CI.
"""
