"""``m2s2hil serve``: the capture daemon (REST API on uvicorn).

On start it checks the listening rules (a token off loopback), opens the rig from its
configuration, locks the data root, optionally queues the sessions the journals show as
interrupted, and serves. On SIGTERM or SIGINT it stops accepting sessions, pauses the
running one at its next safe boundary, records it as ``interrupted``, leaves the rig
safe (lamps off, motion stopped, read back), closes the devices and exits 0.

Register with ``app.command("serve")(serve)``; also runs as
``python -m m2s2hil.commands.serve``.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from types import FrameType

import typer

from m2s2hil.api.settings import TOKEN_ENV, ServeSettings, load_serve_settings

log = logging.getLogger("m2s2hil.serve")


def serve(
    config: Path | None = typer.Option(None, "--config", help="daemon settings TOML (its \"serve\" table)"),
    rig: Path | None = typer.Option(None, "--rig", help="rig TOML (default: the built-in simulated rig)"),
    host: str | None = typer.Option(None, "--host", help="address to listen on (default 127.0.0.1); "
                                    f"any non-loopback address needs a token ({TOKEN_ENV})"),
    port: int | None = typer.Option(None, "--port", help="TCP port (default 8750)"),
    data_root: Path | None = typer.Option(None, "--data-root", help="session folders (default $M2S2HIL_DATA "
                                          "or ./sessions)"),
    resume: bool | None = typer.Option(None, "--resume/--no-resume",
                                       help="queue the sessions the journals show as interrupted"),
    realtime: bool | None = typer.Option(None, "--realtime/--virtual-clock",
                                         help="simulated rig on a real clock (default) or a virtual one"),
    cors_origin: list[str] | None = typer.Option(
        None, "--cors-origin", help="allow this origin (repeatable); CORS is off otherwise"),
    allowed_host: list[str] | None = typer.Option(
        None, "--allowed-host", help="a Host name clients use besides 127.0.0.1/localhost (repeatable)"),
    queue_limit: int | None = typer.Option(None, "--queue-limit", help="sessions that may wait (default 16)"),
    log_level: str | None = typer.Option(None, "--log-level", help="debug, info, warning, error"),
    access_log: bool = typer.Option(False, "--access-log", help="log every request"),
) -> None:
    """Run the capture daemon: REST API, session queue, live events."""
    settings = load_serve_settings(
        config, host=host, port=port, rig=rig, data_root=data_root, resume_interrupted=resume,
        realtime=realtime, cors_origins=cors_origin or None, allowed_hosts=allowed_host or None,
        queue_limit=queue_limit, log_level=log_level,
    )
    run_daemon(settings, access_log=access_log)


def run_daemon(settings: ServeSettings, *, access_log: bool = False) -> None:
    import uvicorn

    from m2s2hil.api.app import create_app
    from m2s2hil.api.guards.security import check_listen
    from m2s2hil.api.http_server import server_limits
    from m2s2hil.api.streams import StreamLimits
    from m2s2hil.config import load_rig
    from m2s2hil.daemon.hold import HoldFile
    from m2s2hil.daemon.manager import SessionManager
    from m2s2hil.daemon.rootlock import lock_data_root
    from m2s2hil.engine.build import open_capture_rig

    level = settings.log_level.upper()
    logging.basicConfig(level=level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    token = settings.token_value()
    check_listen(settings.host, token)  # before touching any hardware
    cfg = load_rig(settings.rig)
    root_lock = lock_data_root(settings.data_root)  # a second daemon on this root stops here
    log.info("opening rig %r (%s)", cfg.rig.name, settings.rig or "built-in simulated rig")
    # A device that cannot be opened: RigOpenError, one line naming it, the port and the cause
    # (exit 6 unreachable, 7 unusable: m2s2hil.rig.open_errors); anything else RigUnavailable (exit 1).
    # A hold left on the data root (an e-stop, an operator's hold) is in force from the start:
    # homing is motion, so axes with switches are homed only when the first session starts
    # after an operator released it.
    held = HoldFile(settings.data_root).load() is not None
    if held:
        log.info("the data root holds the rig: axes with switches are not homed now, but before "
                 "the first session after a release")
    rig = open_capture_rig(cfg, realtime=settings.realtime, seed=settings.seed, home=not held,
                           source=str(settings.rig) if settings.rig is not None else None)
    try:
        manager = SessionManager(
            rig, settings.data_root, queue_limit=settings.queue_limit,
            max_plan_frames=settings.max_plan_frames, estop_grace_s=settings.estop_grace_s,
            estop_timeout_s=settings.estop_timeout_s, root_lock=root_lock, home_deferred=held,
        )
        app = create_app(
            manager, token=token, cors_origins=settings.cors_origins, allowed_hosts=settings.host_names(),
            max_body_bytes=settings.max_body_bytes,
            manage_lifecycle=True, resume_interrupted=settings.resume_interrupted,
            shutdown_timeout_s=settings.shutdown_timeout_s,
            stream_limits=StreamLimits(live_viewers=settings.max_live_viewers,
                                       sse_subscribers=settings.max_sse_subscribers,
                                       send_timeout_s=settings.stream_send_timeout_s),
        )
        server = _make_server(uvicorn.Config(
            app, host=settings.host, port=settings.port, log_config=None,
            log_level=settings.log_level.lower(), access_log=access_log, lifespan="on",
            timeout_graceful_shutdown=5,
            **server_limits(header_timeout_s=settings.header_timeout_s, keep_alive_s=settings.keep_alive_s,
                            max_header_bytes=settings.max_header_bytes,
                            max_connections=settings.max_connections),
        ), manager)
        log.info("serving on http://%s:%d (data root %s, token %s)", settings.host, settings.port,
                 settings.data_root, "required" if token else "off")
        server.run()
        if not server.started:
            raise typer.Exit(1)  # uvicorn logged why (e.g. the port is taken)
    finally:
        try:
            rig.safe()
        finally:
            rig.close()
    log.info("daemon stopped")


def _make_server(config: object, manager: object) -> object:
    """uvicorn's server, told about the manager so a signal starts the pause at once (before
    uvicorn drains the connections and runs the lifespan shutdown). After a graceful stop the
    process closes the devices and exits 0 instead of re-raising the signal."""
    import uvicorn

    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            name = signal.Signals(sig).name if sig else "signal"
            manager.request_shutdown(reason=name)  # type: ignore[attr-defined]
            super().handle_exit(sig, frame)

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            if threading.current_thread() is not threading.main_thread():
                yield
                return
            previous = {sig: signal.signal(sig, self.handle_exit) for sig in (signal.SIGINT, signal.SIGTERM)}
            try:
                yield
            finally:
                for sig, handler in previous.items():
                    signal.signal(sig, handler)

    return Server(config)  # type: ignore[arg-type]


app = typer.Typer(help="The capture daemon.", add_completion=False)
app.command()(serve)


if __name__ == "__main__":
    from m2s2hil.commands.running import run_app

    run_app(app)
