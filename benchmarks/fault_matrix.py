"""The fault matrix: every device × fault kind × rate, and SIGKILL at chosen points, each cell
checked against the invariants a session must never break (issue 12).

    .venv/bin/python benchmarks/fault_matrix.py [--size 512] [--step 10] [--only stage,kill]
                                                [--write docs/reliability.md]

The cells, the invariants and how a cell runs are in tests/fault_harness.py, which the CI test
(tests/test_fault_matrix.py, a reduced matrix) imports too; this script runs every cell and
writes the table of docs/reliability.md.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test helpers, as bench_console
from fault_harness import EXIT_OF_STATE, Observed, disk_cells, fault_cells, kill_cells, run_cell

MACHINE = "AMD EPYC x86_64 VM, 2 logical CPUs, 24 GiB, Python 3.11.7"


def table(results: list[Observed]) -> str:
    lines = ["| cell | expected | observed (state, exit) | stored / planned | skips | faults | "
             "invariants | s |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        exp = " / ".join(f"{s} ({EXIT_OF_STATE[s]})" for s in sorted(r.cell.expected))
        if r.cell.group == "disk":
            exp = "paused (3) → completed (0)"
        inv = "hold" if r.ok else "**BROKEN**: " + "; ".join(r.violations)
        lines.append(f"| {r.cell.name} | {exp} | {r.state} ({r.code}) | {r.stored} / {r.planned} | "
                     f"{r.skipped} | {r.faults} | {inv} | {r.seconds:.1f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512, help="sensor width and height (px)")
    ap.add_argument("--step", type=float, default=10, help="azimuth step (deg): 10 = 36 frames")
    ap.add_argument("--only", default="", help="comma-separated: devices (stage, relays, toucan), kill, disk")
    ap.add_argument("--write", type=Path, help="write the table into this Markdown file")
    args = ap.parse_args()
    only = {x for x in args.only.split(",") if x}
    cells = [c for c in fault_cells() if not only or c.device in only]
    cells += kill_cells() if not only or "kill" in only else []
    cells += disk_cells() if not only or "disk" in only else []
    results = []
    with tempfile.TemporaryDirectory(prefix="fault-matrix-") as tmp:
        for c in cells:
            r = run_cell(c, Path(tmp), size=args.size, step=args.step)
            print(f"{c.name:40s} {r.state:34s} exit {r.code}  {'ok' if r.ok else r.violations}", flush=True)
            results.append(r)
    text = table(results)
    held = sum(r.ok for r in results)
    head = (f"Run {dt.date.today().isoformat()} on {MACHINE}, sensor "
            f"{args.size}×{args.size}, azimuth step {args.step:g}° (one lighting, one tilt): "
            f"{held} of {len(results)} cells hold every invariant "
            f"({sum(r.seconds for r in results):.0f} s of wall time in all).")
    print(head)
    if args.write:
        _write(args.write, head, text)
    return 0 if held == len(results) else 1


def _write(path: Path, head: str, text: str) -> None:
    begin, end = "<!-- fault-matrix:begin -->", "<!-- fault-matrix:end -->"
    doc = path.read_text() if path.exists() else ""
    block = f"{begin}\n{head}\n\n{text}\n{end}"
    if begin in doc and end in doc:
        doc = doc[:doc.index(begin)] + block + doc[doc.index(end) + len(end):]
    else:
        doc = doc.rstrip() + "\n\n" + block + "\n"
    path.write_text(doc)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    raise SystemExit(main())
