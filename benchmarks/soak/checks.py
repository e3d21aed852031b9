"""The invariants the soak checks, all from outside the daemon: the session folders on disk
(read through the store's read-only API and by hashing the files), the hold windows the soak
opened and closed, and the samples of the daemon's memory and file descriptors."""

from __future__ import annotations

import hashlib
import json
import statistics
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from m2s2hil.atomic import TMP_MARK
from m2s2hil.store.session import SessionStore

from .daemon import Sample

#: Layers of a session folder that hold the journal's files.
FILE_FOLDERS = ("frames", "darks")
#: How much the daemon may grow across the run, idle against idle, before it counts as a leak.
RSS_SLACK = (1.25, 24 * 1024)  # factor, plus KiB
FD_SLACK = 4
#: The daemon keeps the last 32 finished sessions open for reading (SessionManager's
#: ``keep_finished``), besides the running and the queued ones: their journals are not a leak,
#: more than that would be.
KEPT_FINISHED = 32


@dataclass(frozen=True)
class Counts:
    stored: frozenset[str]  # committed frame and dark ids
    runs: int  # run_started events
    state: str


def session_ids(root: Path) -> list[str]:
    return sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")
                  and p.name not in ("exports", "snapshots", "darks") and (p / "journal.sqlite").exists())


def read_counts(root: Path, sid: str) -> Counts:
    for attempt in range(5):  # a journal being checkpointed by its writer may refuse a reader briefly
        try:
            with SessionStore.open(root, sid) as st:
                runs = sum(e["kind"] == "run_started" for e in st.events())
                return Counts(frozenset(st.completed_event_ids()), runs, st.state)
        except Exception:
            if attempt == 4:
                raise
            time.sleep(0.05)
    raise AssertionError("unreachable")


def snapshot(root: Path) -> dict[str, Counts]:
    """What every session on the root has stored, and how many runs it started."""
    return {sid: read_counts(root, sid) for sid in session_ids(root)}


@dataclass
class HoldWindow:
    """A time the rig was held (an e-stop, an operator's hold, a failed session's hold): from
    the answer that set it (or the moment the soak saw it) to the release the soak sent. Only
    the session running when an operator's hold began may go on storing, and only until the
    daemon restarts (after that nothing runs until the release)."""

    kind: str  # estop | operator | failure
    started_s: float
    base: dict[str, Counts]
    running: str | None  # may finish its run under an operator's hold
    ended_s: float | None = None
    kills: int = 0
    violations: list[str] = field(default_factory=list)
    held_after_restart: list[bool] = field(default_factory=list)

    def at_kill(self, root: Path) -> None:
        """The daemon is dead: what is stored now is the baseline from here on, for everyone."""
        self.compare(snapshot(root), "before a kill -9")
        self.base = snapshot(root)
        self.running = None
        self.kills += 1

    def close(self, root: Path, now_s: float) -> None:
        self.compare(snapshot(root), "at the release")
        self.ended_s = now_s

    def compare(self, now: dict[str, Counts], when: str) -> None:
        for sid, c in now.items():
            b = self.base.get(sid, Counts(frozenset(), 0, "created"))
            new = sorted(c.stored - b.stored)
            if c.runs > b.runs:
                self.violations.append(f"{self.kind} hold: session {sid} started {c.runs - b.runs} run(s) "
                                       f"while held ({when}, {self.kills} kill(s) into the hold)")
            if new and sid != self.running:
                self.violations.append(f"{self.kind} hold: session {sid} stored {len(new)} frame(s) while "
                                       f"held, first {new[0]} ({when}, {self.kills} kill(s) into the hold)")


@dataclass
class SessionCheck:
    sid: str
    state: str
    planned: int
    stored: int
    runs: int
    sim_s: float
    problems: list[str]


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def check_session(root: Path, sid: str, acked: set[str]) -> SessionCheck:
    """journal = files on disk = manifest (sha256), no frame stored twice, every acknowledged
    frame still stored, no temporary file left, the store's own verification clean."""
    bad: list[str] = []
    with SessionStore.open(root, sid) as st:
        frames, darks, events, state = st.frames(), st.darks(), st.events(), st.state
        journal = {rec.path: rec.sha256 for fr in frames for rec in fr.files.values()}
        journal |= {rec.path: rec.sha256 for d in darks for rec in d.files.values()}
        planned = sum(1 for e in st.sweep.expand(st.rig) if e.kind == "frame")
        bad += [f"verify: {p}" for p in st.verify()[:3]]
        folder = st.path
    on_disk = {p.relative_to(folder).as_posix(): p for sub in FILE_FOLDERS
               for p in (folder / sub).glob("*") if p.is_file()}
    temps = sorted(k for k in on_disk if TMP_MARK in k)
    if temps:
        bad.append(f"temporary files left: {temps[:2]}")
    files = {k: v for k, v in on_disk.items() if TMP_MARK not in k}
    if set(files) != set(journal):
        extra, missing = sorted(set(files) - set(journal)), sorted(set(journal) - set(files))
        bad.append(f"files on disk != journal: {len(extra)} not in the journal {extra[:2]}, "
                   f"{len(missing)} missing {missing[:2]}")
    wrong = [k for k in set(files) & set(journal) if _sha256(files[k]) != journal[k]]
    if wrong:
        bad.append(f"sha256 of {len(wrong)} file(s) differs from the journal, first {sorted(wrong)[0]}")
    ids = [f.event_id for f in frames] + [d.dark_id for d in darks]
    net = Counter(e["payload"]["event_id"] for e in events if e["kind"] == "frame")
    net.subtract(Counter(e["payload"]["event_id"] for e in events if e["kind"] == "quarantined"))
    twice = sorted({i for i, n in Counter(ids).items() if n > 1} | {i for i, n in net.items() if n > 1})
    if twice:
        bad.append(f"{len(twice)} frame(s) stored twice, first {twice[0]}")
    lost = sorted(acked - set(ids))
    if lost:
        bad.append(f"{len(lost)} acknowledged frame(s) lost, first {lost[0]}")
    runs = [i for i, e in enumerate(events) if e["kind"] == "run_started"]
    last_ended = bool(runs) and any(e["kind"] == "run_finished" for e in events[runs[-1]:])
    man = folder / "manifest.json"
    if last_ended:  # every run that ends writes the manifest of what is stored
        if not man.is_file():
            bad.append("the last run ended but there is no manifest.json")
        else:
            listed = {f["path"]: f["sha256"] for f in json.loads(man.read_text())["files"]}
            if listed != journal:
                bad.append(f"manifest != journal ({len(listed)} vs {len(journal)} files, "
                           f"{len(set(listed) ^ set(journal))} differ by name)")
    return SessionCheck(sid, state, planned, len(frames), len(runs), simulated_s(events), bad)


def simulated_s(events: list[dict]) -> float:
    """The session's simulated capture time: each run from its start to its last journalled
    event (the journal's times are the daemon's virtual clock, so within one run they add up)."""
    total, start, last = 0.0, None, None
    for e in events:
        if e["kind"] == "run_started":
            if start is not None and last is not None:
                total += last - start
            start = last = e["time"]
        elif start is not None:
            last = e["time"]
    if start is not None and last is not None:
        total += last - start
    return total


def disk_simulated_s(root: Path) -> float:
    """Every session's simulated capture time, from the journals."""
    total = 0.0
    for sid in session_ids(root):
        with SessionStore.open(root, sid) as st:
            total += simulated_s(st.events())
    return total


@dataclass(frozen=True)
class Flatness:
    incarnation: int
    samples: int
    rss_first_kib: float
    rss_last_kib: float
    fds_first: int  # descriptors besides the session journals
    fds_last: int
    journals_max: int  # session journals open at most, at any sample
    ok: bool


def flatness(samples: list[Sample], min_samples: int = 6) -> list[Flatness]:
    """Per daemon incarnation with enough idle samples: the last quarter of its idle samples
    against the first quarter after its warm-up (its first run, then the first fifth of the idle
    samples after it). Idle: no session running and none of the soak's streams or exports open,
    so growth is what was left behind. A daemon's first run loads what capture-time QC needs
    (scikit-learn with SciPy, the numba kernels; 306 → 419 MiB in one reduced soak), so idle
    samples from before it are not the baseline. The session journals the daemon keeps open are
    judged apart: never more than it keeps by design."""
    out: list[Flatness] = []
    for inc in sorted({s.incarnation for s in samples}):
        mine = [s for s in samples if s.incarnation == inc]
        busy = next((i for i, s in enumerate(mine) if not s.idle), 0)
        idle = [s for s in mine[busy:] if s.idle]
        idle = idle[len(idle) // 5:]
        if len(idle) < min_samples:
            continue
        q = max(1, len(idle) // 4)
        first, last = idle[:q], idle[-q:]
        rss0, rss1 = statistics.median(s.rss_kib for s in first), statistics.median(s.rss_kib for s in last)
        fd0, fd1 = min(s.other_fds for s in first), max(s.other_fds for s in last)
        journals_ok = all(s.journals <= KEPT_FINISHED + 1 + s.waiting for s in mine)
        ok = rss1 <= rss0 * RSS_SLACK[0] + RSS_SLACK[1] and fd1 <= fd0 + FD_SLACK and journals_ok
        out.append(Flatness(inc, len(idle), rss0, rss1, fd0, fd1, max(s.journals for s in mine), ok))
    return out
