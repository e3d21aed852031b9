"""The root of every deliberate error of m2s2hil, and the codecs' own error.

It lives here, in the package that imports nothing of ours, so that every layer (codecs,
drivers, simulators, the application) can derive from one base without importing upwards:
a CLI or an API handler that catches :class:`M2S2Error` catches a device's error too.
"""


class M2S2Error(Exception):
    """Base of every error m2s2hil raises on purpose; ``exit_code`` is the CLI's exit status."""

    exit_code = 1


class CodecError(M2S2Error, ValueError):
    """Malformed bytes; ``data`` holds the offending input (possibly truncated)."""

    def __init__(self, message: str, data: bytes = b"") -> None:
        self.data = bytes(data[:200])
        super().__init__(f"{message} (data: {self.data!r})" if data else message)
