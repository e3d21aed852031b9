"""``python -m benchmarks.soak``: run the soak, print its tables, optionally write them into
docs/reliability.md between the soak's markers. Exit 1 when an invariant broke."""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
from pathlib import Path

from .report import markdown
from .run import run_soak
from .schedule import SoakConfig

BEGIN, END = "<!-- soak:begin -->", "<!-- soak:end -->"


def write_into(doc: Path, table: str) -> None:
    text = doc.read_text()
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{doc}: no {BEGIN} ... {END} markers to write the table between")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    doc.write_text(f"{head}{BEGIN}\n{table}{END}{tail}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    d = SoakConfig()
    ap.add_argument("--sim-s", type=float, default=d.sim_s, help="simulated capture time to reach")
    ap.add_argument("--kills", type=int, default=d.kills)
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--size", type=int, default=d.size, help="sensor width and height")
    ap.add_argument("--full-step", type=float, default=d.full_step_deg, help="a full sweep's azimuth step")
    ap.add_argument("--work", type=Path, help="folder for the daemon's data (default: a temporary one)")
    ap.add_argument("--markdown", type=Path, help="write the tables to this file")
    ap.add_argument("--write", type=Path, help="put the tables into this page between the soak markers")
    a = ap.parse_args()
    # SIGTERM ends the soak through its clean-up (the daemon it started is killed too)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    cfg = SoakConfig(sim_s=a.sim_s, kills=a.kills, seed=a.seed, size=a.size, full_step_deg=a.full_step)
    with tempfile.TemporaryDirectory(prefix="m2s2hil-soak-") as tmp:
        result = run_soak(cfg, a.work or Path(tmp), progress=True)
    table = markdown(result)
    print(table)
    if a.markdown:
        a.markdown.write_text(table)
    if a.write:
        write_into(a.write, table)
    return 0 if result.ok else 1


if __name__ == "__main__":
    sys.exit(main())
