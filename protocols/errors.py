"""The error every codec raises for bytes that break its protocol."""


class CodecError(ValueError):
    """Malformed bytes; ``data`` holds the offending input (possibly truncated)."""

    def __init__(self, message: str, data: bytes = b"") -> None:
        self.data = bytes(data[:200])
        super().__init__(f"{message} (data: {self.data!r})" if data else message)
