"""The soak's driver: one daemon at a time, fed sessions, stopped, held, released, killed and
restarted, watched and exported from, as the seeded schedule says; then every invariant."""

from __future__ import annotations

import random
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from .checks import (
    Flatness,
    HoldWindow,
    SessionCheck,
    check_session,
    disk_simulated_s,
    flatness,
    session_ids,
    snapshot,
)
from .daemon import Daemon, Sample, Traffic, client, get_json, post, write_rig_file, write_serve_file
from .schedule import ONCE, KillPoint, SoakConfig, kill_points, sweep
from .streams import Acks, EventWatcher, LiveViewer, Stream

TERMINAL = {"completed", "completed_with_gaps", "failed", "aborted", "cancelled", "estopped"}


@dataclass
class Result:
    cfg: SoakConfig
    ran: Counter[str]
    sessions: list[SessionCheck]
    windows: list[HoldWindow]
    flat: list[Flatness]
    samples: list[Sample]
    traffic: Traffic
    acked: int
    wall_s: float
    violations: dict[str, list[str]] = field(default_factory=dict)  # invariant -> what broke it

    @property
    def ok(self) -> bool:
        return not any(self.violations.values())


class Soak:
    def __init__(self, cfg: SoakConfig, work: Path, *, progress: bool = False) -> None:
        self.progress = progress
        self.cfg, self.work, self.root = cfg, work, work / "data"
        self.rng = random.Random(cfg.seed)
        self.serve_file = write_serve_file(work, write_rig_file(work, cfg.size), cfg.seed)
        self.traffic, self.acks = Traffic(), Acks()
        self.ran: Counter[str] = Counter()
        self.samples: list[Sample] = []
        self.windows: list[HoldWindow] = []
        self.window: HoldWindow | None = None
        self.hold_until = 0.0
        self.streams: list[Stream] = []
        self.exports: list[threading.Thread] = []
        self.watching: dict[tuple[int, str], EventWatcher] = {}
        self.kills = kill_points(cfg, self.rng)
        self.disk_sim_s = 0.0
        self.completed: list[str] = []
        self.estopped: set[str] = set()
        self.last_running: str | None = None
        self.export_errors: list[str] = []
        self.bad: dict[str, list[str]] = {k: [] for k in (
            "no 5xx answer", "holds honoured", "rig safe after every stop", "daemon up until stopped",
            "exports one at a time", "GET /sessions/{id}/verify ok")}
        self.t0 = time.monotonic()
        self.incarnation = -1
        self.d = self.start(resume=False)

    # ------------------------------------------------------------------ the daemon
    def now(self) -> float:
        return time.monotonic() - self.t0

    def start(self, *, resume: bool) -> Daemon:
        self.incarnation += 1
        d = Daemon(self.work, self.serve_file, self.incarnation, resume=resume)
        self.ran["daemon starts"] += 1
        return d

    def restart(self, why: str) -> None:
        if self.window is not None:
            self.window.at_kill(self.root)
        self.d = self.start(resume=True)
        self.ran[f"restarts after {why}"] += 1
        self.last_running = None
        q = get_json(self.d.http, self.traffic, "/queue", "/queue")
        if self.window is not None:
            held = q is not None and q["held"] is not None
            self.window.held_after_restart.append(held)
            if not held:
                self.window.violations.append(f"{self.window.kind} hold gone after kill -9 and --resume: "
                                              f"/queue says held={None if q is None else q['held']!r}")
            time.sleep(self.cfg.probe_s)  # a hold that did not survive would start a session now
            self.window.compare(snapshot(self.root), "after the restart")
        self.check_rig("after a restart")

    def kill(self, point: KillPoint) -> None:
        if point.held and self.window is None:
            q = get_json(self.d.http, self.traffic, "/queue", "/queue")
            if q is not None and not q["items"]:
                self.submit()  # something queued, so a hold that did not survive would show
            if q is not None and q["running"] and self.rng.random() < 0.5:
                self.estop()
            else:
                self.hold()
            time.sleep(self.rng.uniform(0.0, 1.0))
        self.ack_frames()
        self.d.kill9()
        self.ran["kill -9 while held" if self.window is not None else "kill -9"] += 1
        self.restart("kill -9")

    # ------------------------------------------------------------------ actions
    def submit(self) -> None:
        kind, body = sweep(self.rng, self.cfg, full=self.due("sessions submitted (full)"))
        r = post(self.d.http, self.traffic, "/sessions", "/sessions", json=body)
        if r is not None and r.status_code == 202:
            self.ran[f"sessions submitted ({kind})"] += 1

    def open_window(self, kind: str, running: str | None) -> None:
        self.window = HoldWindow(kind, self.now(), snapshot(self.root), running)
        self.hold_until = self.now() + self.rng.uniform(*self.cfg.hold_s)

    def estop(self) -> None:
        r = post(self.d.http, self.traffic, "/rig/stop", "/rig/stop")
        if r is None or r.status_code != 200:
            self.bad["rig safe after every stop"].append(f"POST /rig/stop answered "
                                                         f"{None if r is None else r.status_code}")
            return
        rep = r.json()
        self.ran["e-stops"] += 1
        if not rep["safe"] or rep["errors"]:
            self.bad["rig safe after every stop"].append(f"e-stop: safe={rep['safe']} lamps_on="
                                                         f"{rep['lamps_on']} moving={rep['moving']} "
                                                         f"errors={rep['errors'][:2]}")
        if rep["session_id"]:
            self.estopped.add(rep["session_id"])
        if self.window is None:
            self.open_window("estop", None)
        else:  # a stop during a hold: from now on nothing at all may store
            self.window.compare(snapshot(self.root), "at an e-stop during the hold")
            self.window.base, self.window.running = snapshot(self.root), None
        self.check_rig("after an e-stop")

    def hold(self) -> None:
        r = post(self.d.http, self.traffic, "/queue/hold", "/queue/hold",
                 params={"reason": "soak: mockup swap"})
        if r is not None and r.status_code == 200:
            self.ran["operator holds"] += 1
            self.open_window("operator", r.json()["running"])

    def release(self) -> None:
        assert self.window is not None
        self.window.close(self.root, self.now())
        r = post(self.d.http, self.traffic, "/queue/release", "/queue/release")
        if r is None or r.status_code != 200:
            return  # still held; try again next tick
        self.check_rig("at a release")
        self.windows.append(self.window)
        self.window = None
        self.ran["releases"] += 1
        for sid in sorted(self.estopped):  # stopped sessions capture what they lack
            r = post(self.d.http, self.traffic, "/sessions/{id}/resume", f"/sessions/{sid}/resume")
            if r is not None and r.status_code == 200:
                self.ran["e-stopped sessions resumed"] += 1
                self.estopped.discard(sid)

    def check_rig(self, when: str) -> None:
        """GET /rig while no session owns it: every lamp off, no axis moving."""
        rig = get_json(self.d.http, self.traffic, "/rig", "/rig")
        if rig is None or rig["session_id"] is not None:
            return
        for dev in rig["devices"]:
            st = dev["state"]
            if dev["health"] == "error" or st.get("lamps_on") or any(
                    v for k, v in st.items() if k.endswith("_moving")):
                self.bad["rig safe after every stop"].append(f"{when}: {dev['name']} {dev['health']} {st}")
        self.ran["rig read-backs"] += 1

    def ack_frames(self) -> None:
        """The running session's frame list: every frame in it is acknowledged as stored."""
        q = get_json(self.d.http, self.traffic, "/queue", "/queue")
        sid = q["running"] if q else None
        if sid:
            page = get_json(self.d.http, self.traffic, "/sessions/{id}/frames", f"/sessions/{sid}/frames",
                            params={"limit": 500})
            if page is not None:
                self.acks.add(sid, {f["event_id"] for f in page["items"]})
                self.ran["frame lists read"] += 1

    def viewer(self) -> None:
        v = LiveViewer(self.d.port, self.traffic, self.rng.randint(2, 12), max_s=15.0)
        v.start()
        self.streams.append(v)
        self.ran["live-view viewers"] += 1

    def export(self) -> None:
        sid = self.rng.choice(self.completed)
        n = self.rng.choice((1, 1, 2, 3))

        def one(overwrite: bool) -> None:
            with client(self.d.port, timeout=300) as http:
                r = post(http, self.traffic, "/sessions/{id}/export", f"/sessions/{sid}/export",
                         json={"layout": "m2s2", "overwrite": overwrite})
                # 422 "already exists": a second export without overwrite, refused by design
                again = (r is not None and r.status_code == 422 and "already exists" in r.text
                         and not overwrite)
                if r is not None and r.status_code not in (201, 409) and not again:
                    self.export_errors.append(f"overwrite={overwrite}: {r.status_code} {r.text[:200]}")

        threads = [threading.Thread(target=one, args=(self.rng.random() < 0.3,), daemon=True)
                   for _ in range(n)]
        for t in threads:
            t.start()
        self.exports += threads
        self.ran[f"exports ({n} at once)"] += 1

    def due(self, action: str) -> bool:
        """Past half the simulated time, an action the dice have not chosen yet is done now, so
        that every kind of action runs at least once however short the soak."""
        return self.ran[action] == 0 and self.sim_s() >= 0.5 * self.cfg.sim_s

    def missing(self) -> list[str]:
        """The kinds of action the soak must do at least once that it has not done yet, the kills
        still planned and a first export round: on a loaded machine the virtual clock reaches the
        target before the ticks have got that far."""
        out = [a for a in ONCE if self.ran[a] == 0]
        if self.kills:
            out.append("kill -9")
        if not any(k.startswith("exports") for k in self.ran):
            out.append("exports")
        return out

    # ------------------------------------------------------------------ the clock
    def sim_s(self) -> float:
        """Simulated capture time so far, from the journals (refreshed every few ticks), the
        figure the table reports (the status's elapsed_s summed over runs overshot it by 18 %)."""
        return self.disk_sim_s

    def follow(self, running: str | None) -> None:
        """What a session that stopped running ended as; an event stream on the running one."""
        if self.last_running and self.last_running != running:
            sid = self.last_running
            st = get_json(self.d.http, self.traffic, "/sessions/{id}", f"/sessions/{sid}")
            if st is not None and st["state"] == "completed" and sid not in self.completed:
                self.completed.append(sid)
        if running and (self.incarnation, running) not in self.watching:
            w = EventWatcher(self.d.port, self.traffic, running, self.acks, max_s=600.0)
            w.start()
            self.watching[(self.incarnation, running)] = w
            self.streams.append(w)
            self.ran["event subscribers"] += 1
        self.last_running = running

    # ------------------------------------------------------------------ one tick
    def busy(self) -> bool:
        self.streams = [s for s in self.streams if s.is_alive()]
        self.exports = [t for t in self.exports if t.is_alive()]
        return bool(self.exports) or any(isinstance(s, LiveViewer) for s in self.streams)

    def sample(self, running: str | None, waiting: int) -> None:
        got = self.d.sample()
        if got is not None:
            idle = running is None and not self.busy() and not any(s.is_alive() for s in self.streams)
            self.samples.append(Sample(self.incarnation, self.now(), got.rss_kib, got.fds, got.other_fds,
                                       got.journals, got.threads, idle, waiting))

    def tick(self, ticks: int, *, feeding: bool) -> dict | None:
        q = get_json(self.d.http, self.traffic, "/queue", "/queue")
        if q is None:
            if not self.d.alive():
                self.bad["daemon up until stopped"].append(
                    f"daemon {self.incarnation} died by itself (exit {self.d.proc.returncode}): "
                    f"{self.d.log()[-300:]!r}")
                self.restart("the daemon died")
            return None
        running, held = q["running"], q["held"]
        self.follow(running)
        self.sample(running, len(q["items"]))
        if held and self.window is None:
            self.open_window("failure" if "failed" in held else "unexplained", None)
        elif not held and self.window is not None:
            self.window.violations.append(f"{self.window.kind} hold vanished with no release "
                                          f"({self.window.kills} kill(s) into it)")
            self.window.close(self.root, self.now())
            self.windows.append(self.window)
            self.window = None
        if feeding and self.kills and self.sim_s() >= self.kills[0].at_sim_s:
            self.kill(self.kills.pop(0))
            return None
        rnd = self.rng.random
        if feeding and len(q["items"]) < self.cfg.max_waiting and sum(
                v for k, v in self.ran.items() if k.startswith("sessions submitted")) < self.cfg.max_sessions:
            self.submit()
        if self.window is not None:
            long = self.now() - self.window.started_s > 120  # a full sweep runs on under a swap hold
            if self.now() >= self.hold_until and (running is None or long):
                self.release()
        elif feeding and running and (rnd() < self.cfg.p_estop or self.due("e-stops")):
            self.estop()
        elif feeding and (rnd() < self.cfg.p_hold or self.due("operator holds")):
            self.hold()
        viewers = sum(isinstance(s, LiveViewer) for s in self.streams)
        if feeding and viewers < 3 and (rnd() < self.cfg.p_viewer or self.due("live-view viewers")):
            self.viewer()
        if feeding and self.completed and not self.exports and (
                rnd() < self.cfg.p_export or not any(k.startswith("exports") for k in self.ran)):
            self.export()
        if ticks % 5 == 0:
            self.disk_sim_s = disk_simulated_s(self.root)
        if rnd() < 0.05:
            self.ack_frames()
        return q

    # ------------------------------------------------------------------ the whole run
    def run(self) -> Result:
        cfg = self.cfg
        try:
            ticks = 0
            # On a loaded machine the virtual clock outruns the ticks: the run goes on past the
            # target until every kind of action has run once (bounded by max_wall_s).
            while ((self.sim_s() < cfg.sim_s or self.missing()) and ticks < cfg.max_ticks
                   and self.now() < cfg.max_wall_s):
                self.tick(ticks, feeding=True)
                ticks += 1
                if self.progress and ticks % 150 == 0:
                    print(f"soak: {self.now():.0f} s wall, {self.sim_s():.0f} s simulated, "
                          f"{dict(self.ran)}", file=sys.stderr, flush=True)
                time.sleep(cfg.tick_s)
            self.ran["ticks"] = ticks
            self.drain()
            self.final_stop()
        finally:
            if self.d.alive():
                self.d.kill9()
        return self.verdict()

    def drain(self) -> None:
        """No new sessions: release, resume the stopped ones, let the queue run dry; then a few
        idle samples of the daemon."""
        deadline = self.now() + self.cfg.drain_wall_s
        while self.now() < deadline:
            q = self.tick(1, feeding=False)
            if q is None:
                continue
            if self.window is None and self.estopped:
                for sid in sorted(self.estopped):
                    post(self.d.http, self.traffic, "/sessions/{id}/resume", f"/sessions/{sid}/resume")
                self.estopped.clear()
            if q["running"] is None and not q["items"] and self.window is None and not self.busy():
                break
            time.sleep(self.cfg.tick_s)
        else:
            self.bad["daemon up until stopped"].append(
                f"the queue did not drain in {self.cfg.drain_wall_s:g} s")
        for s in self.streams:
            s.join(timeout=20)
        for _ in range(self.cfg.idle_samples):
            self.sample(None, 0)
            time.sleep(self.cfg.tick_s)
        for sid in session_ids(self.root):
            v = get_json(self.d.http, self.traffic, "/sessions/{id}/verify", f"/sessions/{sid}/verify")
            if v is not None and not v["ok"]:
                self.bad["GET /sessions/{id}/verify ok"].append(f"{sid}: {v['problems'][:2]}")
        self.check_rig("at the end")

    def final_stop(self) -> None:
        rc = self.d.terminate()
        log = self.d.log()
        if rc != 0:
            self.bad["daemon up until stopped"].append(f"SIGTERM: exit {rc}")
        if "rig left safe: lamps off, motion stopped" not in log:
            self.bad["rig safe after every stop"].append(
                "SIGTERM: the log does not say the rig was left safe")

    def verdict(self) -> Result:
        checks = [check_session(self.root, sid, self.acks.by_session.get(sid, set()))
                  for sid in session_ids(self.root)]
        names = {c.sid for c in checks}
        per = {"journal = files on disk = manifest (sha256)": [], "no frame stored twice": [],
               "no acknowledged frame lost": []}
        for c in checks:
            for p in c.problems:
                key = ("no frame stored twice" if "twice" in p else
                       "no acknowledged frame lost" if "acknowledged" in p else
                       "journal = files on disk = manifest (sha256)")
                per[key].append(f"{c.sid}: {p}")
        per["no acknowledged frame lost"] += [f"{sid}: acknowledged but no session folder"
                                              for sid in self.acks.by_session if sid not in names]
        self.bad["holds honoured"] += [v for w in self.windows for v in w.violations]
        self.bad["no 5xx answer"] += self.traffic.server_errors
        self.bad["exports one at a time"] += self.export_errors
        flat = flatness(self.samples)
        mem = [f"daemon {f.incarnation}: RSS {f.rss_first_kib / 1024:.0f} -> {f.rss_last_kib / 1024:.0f} "
               f"MiB, fds besides journals {f.fds_first} -> {f.fds_last}, at most {f.journals_max} "
               f"journals open" for f in flat if not f.ok]
        if not flat:
            mem.append("no daemon lived long enough idle to judge (fewer than 6 idle samples after warm-up)")
        violations = {**per, **self.bad, "memory and file descriptors flat": mem}
        return Result(self.cfg, self.ran, checks, self.windows, flat, self.samples, self.traffic,
                      self.acks.total(), self.now(), violations)


def run_soak(cfg: SoakConfig, work: Path, *, progress: bool = False) -> Result:
    """Run the soak in ``work`` (the daemon's data root is ``work/data``); ``progress``: a line
    on stderr now and then."""
    work.mkdir(parents=True, exist_ok=True)
    return Soak(cfg, work, progress=progress).run()
