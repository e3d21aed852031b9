"""The daemon's own settings (``m2s2hil serve``): where to listen, which rig, where the data goes.

They come from an optional TOML file with a ``[serve]`` table, then the environment
(``M2S2HIL_TOKEN``, ``M2S2HIL_DATA``), then command-line options, each overriding the one
before. Example::

    [serve]
    host = "127.0.0.1"          # anything but a loopback address needs a token
    port = 8750
    rig = "bench-rig.toml"      # default: the built-in simulated rig
    data_root = "/data/m2s2"
    token = "…"                 # or M2S2HIL_TOKEN (which wins); never on the command line
    resume_interrupted = true   # resume sessions the journal shows as interrupted
    cors_origins = []           # CORS stays off unless origins are listed
    allowed_hosts = []          # Host names besides 127.0.0.1, localhost, [::1] (e.g. "rig-pc.lab")
    max_body_bytes = 65536
    queue_limit = 16
    max_live_viewers = 64       # live-view streams at once; more get 503 with Retry-After
    max_sse_subscribers = 512   # event streams at once (the same)
    header_timeout_s = 10.0     # a client must send its request headers within this (slowloris)
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError, field_validator

from m2s2hil.config import read_toml
from m2s2hil.errors import ConfigError, validation_problem

from .guards.csrf import normalise_origin
from .guards.hosts import split_host

TOKEN_ENV = "M2S2HIL_TOKEN"
DEFAULT_PORT = 8750


class ServeSettings(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    host: str = Field(default="127.0.0.1", min_length=1)
    port: Annotated[int, Field(ge=0, le=65535)] = DEFAULT_PORT
    rig: Path | None = None
    data_root: Path = Path("sessions")  # load_serve_settings() applies $M2S2HIL_DATA (as the store does)
    token: SecretStr | None = None
    resume_interrupted: bool = False
    cors_origins: list[str] = Field(default_factory=list)
    #: Names the Host header may carry besides the loopback ones (DNS-rebinding defence, hosts.py).
    allowed_hosts: list[str] = Field(default_factory=list)
    max_body_bytes: Annotated[int, Field(ge=1024, le=16 * 1024 * 1024)] = 64 * 1024
    queue_limit: Annotated[int, Field(ge=0, le=1000)] = 16
    #: Plans with more frame events than this are refused (expanding and running them is costly).
    max_plan_frames: Annotated[int, Field(ge=1, le=1_000_000)] = 20_000
    #: A simulated rig on a real clock (a live daemon) or a virtual one (tests, dry runs).
    realtime: bool = True
    seed: int = 0
    #: How long SIGTERM waits (real seconds) for the session to reach a safe boundary.
    shutdown_timeout_s: Annotated[float, Field(gt=0, le=3600)] = 120.0
    #: How long an emergency stop waits for the running session to end before stopping motion itself.
    estop_grace_s: Annotated[float, Field(ge=0, le=60)] = 0.5
    estop_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    log_level: str = "info"
    #: Streams served at once (beyond: 503 with Retry-After), and how long one send to a stream's
    #: client may wait before the client counts as gone (m2s2hil.api.streams).
    max_live_viewers: Annotated[int, Field(ge=1, le=1000)] = 64
    max_sse_subscribers: Annotated[int, Field(ge=1, le=10_000)] = 512
    stream_send_timeout_s: Annotated[float, Field(gt=0, le=600)] = 15.0
    #: The server's limits (m2s2hil.api.http_server): time to send a request's headers, an idle
    #: keep-alive connection's life, the headers' size, connections at once (beyond: 503).
    header_timeout_s: Annotated[float, Field(gt=0, le=300)] = 10.0
    keep_alive_s: Annotated[float, Field(gt=0, le=300)] = 5.0
    max_header_bytes: Annotated[int, Field(ge=4096, le=1024 * 1024)] = 16 * 1024
    max_connections: Annotated[int, Field(ge=16, le=100_000)] = 1000

    @field_validator("allowed_hosts")
    @classmethod
    def _hosts(cls, v: list[str]) -> list[str]:
        for name in v:
            if split_host(name) is None:
                raise ValueError(f"{name!r} is not a host name (e.g. rig-pc.lab, 10.0.0.5, [fd00::5])")
        return v

    @field_validator("cors_origins")
    @classmethod
    def _origins(cls, v: list[str]) -> list[str]:
        for origin in v:
            if normalise_origin(origin) is None:
                raise ValueError(f"{origin!r} is not an origin (scheme://host[:port], e.g. http://rig-pc.lab:8750)")
        return v

    def host_names(self) -> list[str]:
        """The Host allow-list's extra names: the configured ones, and the listening address
        itself when it is one address (not a wildcard such as 0.0.0.0)."""
        names = list(self.allowed_hosts)
        if self.host not in ("0.0.0.0", "::", "[::]"):
            bare_v6 = ":" in self.host and not self.host.startswith("[")
            names.append(f"[{self.host}]" if bare_v6 else self.host)
        return names

    def token_value(self) -> str | None:
        return self.token.get_secret_value() if self.token is not None else None


def load_serve_settings(path: str | Path | None = None, *, env: dict[str, str] | None = None,
                        **overrides: object) -> ServeSettings:
    """File (``[serve]`` table) < environment < ``overrides`` (options given on the command line;
    ``None`` values are ignored so unset options keep the file's value)."""
    env = dict(os.environ) if env is None else env
    data: dict[str, object] = {}
    source = "<serve settings>"
    if path is not None:
        p = Path(path)
        source = str(p)
        doc = read_toml(p)
        unknown = sorted(set(doc) - {"serve"})
        if unknown:
            raise ConfigError(source, unknown[0], "unknown table (the daemon reads [serve] only)")
        serve = doc.get("serve", {})
        if not isinstance(serve, dict):
            raise ConfigError(source, "serve", "must be a table")
        data.update(serve)
        for key in ("rig", "data_root"):  # paths in the file are relative to the file
            if isinstance(data.get(key), str) and not Path(str(data[key])).is_absolute():
                data[key] = str(p.parent / str(data[key]))
    if env.get("M2S2HIL_DATA") and "data_root" not in data:
        data["data_root"] = env["M2S2HIL_DATA"]
    if env.get(TOKEN_ENV):
        data["token"] = env[TOKEN_ENV]
    data.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return ServeSettings.model_validate(data)
    except ValidationError as exc:
        key, msg = validation_problem(exc)
        raise ConfigError(source, f"serve.{key}", msg) from None
