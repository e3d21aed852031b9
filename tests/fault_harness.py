"""The fault matrix's cells, invariants and runners (issue 12), shared by its CI test
(tests/test_fault_matrix.py, a reduced matrix) and its benchmark (benchmarks/fault_matrix.py,
every cell, the table in docs/reliability.md).

A *fault cell* opens the simulated rig with one injected fault rule (``[simulation.faults]``
semantics: ``once`` = one occurrence after the rig has opened, ``few`` = a seeded rate of a
few percent, forever, ``persistent`` = every occurrence), runs a capture the way ``capture``
does (``build_run`` + the command's own ``_run_engine``, so the exit code is the command's),
and checks the invariants. A *kill cell* runs a capture in a child process that SIGKILLs
itself at a chosen point (after N frames, inside the darks, between a frame's temporary
write and its rename, between the files and the journal commit, inside the manifest
write), then resumes it in this process and checks the invariants after the resume. A
*disk cell* makes the free space short at the start or after N frames: the run must pause
(exit 3, resumable) and a resume with the space back must complete.

Invariants (:func:`check_invariants`), each one a line when broken:

- journal = files on disk = manifest: every file the journal lists exists with its sha256,
  no file in ``frames/``/``darks/`` the journal does not list, no temporary file left, and
  ``manifest.json`` lists exactly the journal's files with the same sha256;
- no event stored twice (journal rows, and ``frame`` log events net of quarantines);
- planned = stored + recorded skips for a session that ran to its end (``completed``:
  every planned event stored; ``completed_with_gaps``: the rest skipped, each with a
  reason); a failed session stored and skipped only planned events;
- lamps off and motion stopped at exit, as the simulated world and stage see it;
- the exit code the README documents for the final state (0 completed, 1 failed,
  3 paused, 4 aborted, 5 completed with gaps) and a state the cell allows;
- every device fault in the journal names its device and has a fault class (not ``other``).
"""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections import Counter, namedtuple
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from engine_helpers import small_rig_config, small_sweep

TESTS = Path(__file__).resolve().parent

EXIT_OF_STATE = {"completed": 0, "failed": 1, "paused": 3, "aborted": 4, "completed_with_gaps": 5}
RATES = ("once", "few", "persistent")
FEW = 0.05  # "a few percent" of the opportunities, seeded
# Occurrences to let pass so "once" hits the capture, not the rig opening (homing, set-up);
# the camera's first two frames are the dark.
AFTER = {"stage": 6, "relays": 3, "toucan": 2}
# Opportunities that are rarer than exchanges: moves (stall, alarm), coil writes (relay_stuck).
AFTER_KIND = {"stall": 1, "alarm": 1, "relay_stuck": 1}
KINDS: dict[str, tuple[str, ...]] = {
    "stage": ("drop_reply", "garble", "late_reply", "vanish", "stall", "alarm"),
    "relays": ("drop_reply", "garble", "vanish", "relay_stuck"),
    "toucan": ("frame_timeout", "incomplete", "trailer_error", "unplug"),
}
# What each kind needs besides when it fires.
PARAMS: dict[str, dict[str, Any]] = {
    "late_reply": {"delay_s": 5.0},
    "vanish": {"duration_s": 0.5},
    "unplug": {"duration_s": 0.5},
}
PERSISTENT_PARAMS: dict[str, dict[str, Any]] = {
    "vanish": {"duration_s": 3600.0},
    "unplug": {"duration_s": 3600.0},
}
KILL_POINTS = ("after_2_frames", "in_darks", "frame_temp_write", "before_frame_commit", "manifest_write")
DISK_POINTS = ("short_at_start", "full_after_2_frames")
# Faults whose policy gives up the whole session (alarm: home + retry once then abort;
# device_gone: reconnect twice then abort) may end a "few %" cell as failed.
ABORTING_KINDS = {"stall", "alarm", "vanish", "unplug"}


@dataclass(frozen=True)
class Cell:
    group: str  # fault | kill | disk
    device: str
    kind: str
    rate: str = ""
    expected: frozenset[str] = frozenset({"completed"})

    @property
    def name(self) -> str:
        return "/".join(x for x in (self.group, self.device, self.kind, self.rate) if x)

    def faults(self) -> dict[str, list[dict[str, Any]]]:
        if self.group != "fault":
            return {}
        rule: dict[str, Any] = {"kind": self.kind, "after": AFTER_KIND.get(self.kind, AFTER[self.device])}
        if self.rate == "once":
            rule.update(count=1, **PARAMS.get(self.kind, {}))
        elif self.rate == "few":
            rule.update(rate=FEW, **PARAMS.get(self.kind, {}))
        else:
            rule.update(count=-1, **PERSISTENT_PARAMS.get(self.kind, PARAMS.get(self.kind, {})))
        if self.kind == "relay_stuck":
            # every lamp channel of the lighting condition, so the lamps really do not light
            return {self.device: [{**rule, "channel": ch} for ch in range(8)]}
        return {self.device: [rule]}


@dataclass
class Observed:
    cell: Cell
    state: str
    code: int
    stored: int
    planned: int
    skipped: int
    faults: int
    violations: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.violations


def fault_cells(devices: tuple[str, ...] = tuple(KINDS), rates: tuple[str, ...] = RATES,
                kinds: dict[str, tuple[str, ...]] | None = None) -> list[Cell]:
    out = []
    for dev in devices:
        for kind in (kinds or KINDS)[dev]:
            for rate in rates:
                if rate == "once":
                    exp = {"completed"}
                elif rate == "few":
                    exp = {"completed", "completed_with_gaps"}
                    if kind in ABORTING_KINDS:
                        exp.add("failed")
                else:
                    exp = {"failed"}
                out.append(Cell("fault", dev, kind, rate, frozenset(exp)))
    return out


def kill_cells(points: tuple[str, ...] = KILL_POINTS) -> list[Cell]:
    return [Cell("kill", "process", p) for p in points]


def disk_cells(points: tuple[str, ...] = DISK_POINTS) -> list[Cell]:
    return [Cell("disk", "disk", p) for p in points]


# -- the invariants ---------------------------------------------------------------------------------

def _stage_moving(rig: Any) -> bool:
    stage = getattr(rig, "sims", {}).get("stage")
    if stage is None:
        return False
    state = str(stage.state)
    return state.startswith(("Run", "Jog", "Home")) or state == "Hold:1"


def check_invariants(root: Path, session_id: str, *, state: str, code: int, expected: frozenset[str],
                     rig: Any = None) -> list[str]:
    """Every broken invariant, one line each (empty: the cell holds)."""
    from m2s2hil.atomic import TMP_MARK
    from m2s2hil.store.session import SessionStore

    bad: list[str] = []
    if state not in expected:
        bad.append(f"state {state}, expected {'/'.join(sorted(expected))}")
    if EXIT_OF_STATE.get(state) != code:
        bad.append(f"exit {code} for state {state} (README: {EXIT_OF_STATE.get(state)})")
    if rig is not None:
        if rig.world.lamps_on():
            bad.append(f"lamps still on at exit: {sorted(rig.world.lamps_on())}")
        if _stage_moving(rig):
            bad.append("stage still moving at exit")
    with SessionStore.open(root, session_id) as st:
        if st.state != state:
            bad.append(f"journal state {st.state}, engine said {state}")
        frames, darks = st.frames(), st.darks()
        journal_files = {rec.path: rec.sha256 for fr in frames for rec in fr.files.values()}
        journal_files |= {rec.path: rec.sha256 for d in darks for rec in d.files.values()}
        problems = st.verify()
        if problems:
            bad.append(f"verify: {len(problems)} problem(s), first {problems[0]}")
        on_disk = {p.relative_to(st.path).as_posix() for folder in ("frames", "darks")
                   for p in (st.path / folder).glob("*") if p.is_file()}
        temps = sorted(p for p in on_disk if TMP_MARK in p)
        if temps and state != "paused":
            bad.append(f"temporary files left: {temps[:2]}")
        if on_disk - set(temps) != set(journal_files):
            bad.append(f"files on disk != journal ({len(on_disk - set(temps))} vs {len(journal_files)})")
        man_path = st.path / "manifest.json"
        if state in ("completed", "completed_with_gaps", "failed"):
            if not man_path.is_file():
                bad.append("no manifest.json")
            else:
                man = json.loads(man_path.read_text())
                listed = {f["path"]: f["sha256"] for f in man["files"]}
                if listed != journal_files:
                    bad.append(f"manifest != journal ({len(listed)} vs {len(journal_files)} files)")
        ids = [f.event_id for f in frames] + [d.dark_id for d in darks]
        if len(ids) != len(set(ids)):
            bad.append("an event is stored twice in the journal")
        events = st.events()
        net = Counter(e["payload"]["event_id"] for e in events if e["kind"] == "frame")
        net.subtract(Counter(e["payload"]["event_id"] for e in events if e["kind"] == "quarantined"))
        if any(n > 1 for n in net.values()):
            bad.append("a frame was committed twice")
        planned = {e.event_id for e in st.sweep.expand(st.rig)}
        stored = set(ids) & planned
        skipped = st.skipped_event_ids() & planned
        if set(ids) - planned - {d.dark_id for d in darks}:
            bad.append("frames stored that the plan does not hold")
        if state == "completed" and stored != planned:
            bad.append(f"completed with {len(planned - stored)} planned event(s) missing")
        if state == "completed_with_gaps" and (stored | skipped != planned or not skipped):
            bad.append(f"gaps: {len(planned - stored - skipped)} missing event(s) without a recorded skip")
        if state == "completed_with_gaps" and not any("/" in i and not i.startswith("dark") for i in stored):
            bad.append("completed_with_gaps with no frame stored")
        faults_journal = sum(e["kind"] == "fault" for e in events)
        for e in events:  # every device fault says which device and what class it is
            p = e["payload"]
            if e["kind"] == "fault" and p.get("fault_class") != "disk_full" and (
                    p.get("fault_class") == "other" or not p.get("device") or p.get("device") == "?"):
                bad.append(f"fault without a device or a class: {p.get('fault_class')} {p.get('message')}")
                break
        finished = [e["payload"] for e in events if e["kind"] == "run_finished"]
        if finished and finished[-1].get("faults") is not None and finished[-1]["faults"] > faults_journal:
            bad.append(f"summary says {finished[-1]['faults']} faults, journal holds {faults_journal}")
    return bad


# -- running cells ----------------------------------------------------------------------------------

def _run(rig: Any, root: Path, *, sweep: Any = None, resume: str | None = None) -> tuple[Any, int]:
    from m2s2hil.commands.capture import _run_engine
    from m2s2hil.engine.build import build_run

    engine = build_run(rig, root, sweep=sweep, resume=resume)
    code = _run_engine(engine, virtual=True)
    return engine, code


def _observe(cell: Cell, root: Path, engine: Any, code: int, rig: Any, t0: float) -> Observed:
    st = engine.status()
    with contextlib.suppress(Exception):
        engine.store.close()
    viol = check_invariants(root, engine.session_id, state=st.state.value, code=code, expected=cell.expected,
                            rig=rig)
    return Observed(cell, st.state.value, code, st.done, st.total, st.skipped, st.fault_count, viol,
                    time.perf_counter() - t0)


def run_fault_cell(cell: Cell, work: Path, *, size: int = 256, step: float = 90, seed: int = 0) -> Observed:
    from m2s2hil.rig.factory import open_simulated_rig

    t0 = time.perf_counter()
    root = work / cell.name.replace("/", "_")
    rig = open_simulated_rig(small_rig_config(size), faults=cell.faults(), seed=seed)
    try:
        engine, code = _run(rig, root, sweep=small_sweep(azimuth_step_deg=step))
        return _observe(cell, root, engine, code, rig, t0)
    finally:
        rig.close()


CHILD = textwrap.dedent("""
    import os, signal, sys
    sys.path.insert(0, {tests!r})
    from engine_helpers import small_rig_config, small_sweep
    from m2s2hil.engine.build import build_run
    from m2s2hil.engine.state import FrameStored
    from m2s2hil.rig.factory import open_simulated_rig
    from m2s2hil import atomic
    from m2s2hil.store import journal

    point = {point!r}
    die = lambda: os.kill(os.getpid(), signal.SIGKILL)
    if point == "in_darks":
        journal.Journal.add_dark = lambda self, **kw: die()        # files renamed, row never committed
    elif point == "before_frame_commit":
        journal.Journal.add_frame = lambda self, **kw: die()
    elif point in ("frame_temp_write", "manifest_write"):
        real = atomic._write_temp
        want = "manifest.json" if point == "manifest_write" else ".raw.tiff"
        def temp_then_die(final, data):
            tmp = real(final, data)
            if str(final).endswith(want):
                die()                                              # temp file fsynced, not renamed
            return tmp
        atomic._write_temp = temp_then_die
    rig = open_simulated_rig(small_rig_config({size}))
    engine = build_run(rig, {root!r}, sweep=small_sweep(azimuth_step_deg={step}), session_id="killed")
    if point == "after_2_frames":
        n = []
        engine.subscribe(lambda e: (n.append(1), len(n) == 2 and die())
                         if isinstance(e, FrameStored) else None)
    engine.run()
    print("not killed", flush=True)
""")


def run_kill_cell(cell: Cell, work: Path, *, size: int = 256, step: float = 90) -> Observed:
    from m2s2hil.rig.factory import open_simulated_rig

    t0 = time.perf_counter()
    root = work / cell.name.replace("/", "_")
    code = CHILD.format(tests=str(TESTS), point=cell.kind, size=size, step=step, root=str(root))
    child = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    pre: list[str] = []
    if child.returncode != -signal.SIGKILL:  # keep the whole traceback: a race shows once in many runs
        pre.append(f"child was not killed (exit {child.returncode}): {child.stderr[-4000:]}")
    rig = open_simulated_rig(small_rig_config(size))
    try:
        engine, rc = _run(rig, root, resume="killed")
        obs = _observe(cell, root, engine, rc, rig, t0)
    finally:
        rig.close()
    obs.violations[:0] = pre
    return obs


def run_disk_cell(cell: Cell, work: Path, *, size: int = 256, step: float = 90) -> Observed:
    """Free space short (at the start, or after 2 frames): paused, exit 3; resumed once the
    space is back: completed. Both runs' invariants are checked."""
    from m2s2hil.rig.factory import open_simulated_rig

    t0 = time.perf_counter()
    root = work / cell.name.replace("/", "_")
    real = shutil.disk_usage
    usage = namedtuple("usage", "total used free")
    full_from = 0 if cell.kind == "short_at_start" else 2  # raw frames on disk when the space runs out
    short = {"on": True}

    def fake(path: Any) -> Any:
        u = real(path)
        full = short["on"] and sum(1 for _ in root.rglob("*.raw.tiff")) >= full_from
        return usage(u.total, u.used, 4 * 10**6) if full else u

    rig = open_simulated_rig(small_rig_config(size))
    shutil.disk_usage = fake  # type: ignore[assignment]
    try:
        engine, code = _run(rig, root, sweep=small_sweep(azimuth_step_deg=step))
        short["on"] = False
        first = engine.status().state.value
        sid = engine.session_id
        engine.store.close()
        pre = check_invariants(root, sid, state=first, code=code, expected=frozenset({"paused"}), rig=rig)
    finally:
        shutil.disk_usage = real  # type: ignore[assignment]
        rig.close()
    rig = open_simulated_rig(small_rig_config(size))
    try:
        engine, rc = _run(rig, root, resume=sid)
        obs = _observe(cell, root, engine, rc, rig, t0)
    finally:
        rig.close()
    obs.violations[:0] = [f"first run: {v}" for v in pre]
    obs.state = f"{first} → {obs.state}"
    obs.code = rc if not pre else code
    return obs


def run_cell(cell: Cell, work: Path, **kw: Any) -> Observed:
    run = {"fault": run_fault_cell, "kill": run_kill_cell, "disk": run_disk_cell}[cell.group]
    return run(cell, work, **kw)
