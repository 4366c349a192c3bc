"""Sans-I/O line framing for CR LF text protocols (LTP/1, FANUC RMI).

Wire layout::

    <line bytes, no CR or LF> CR LF
    <line bytes> CR LF
    ...

The framer is forgiving on input (a bare LF also ends a line; a CR right before it is
stripped) and strict on output (lines it encodes must not contain CR or LF and must fit the
maximum length). A line longer than ``max_length`` raises :class:`~robocal.errors.FramingError`
once, and the framer discards bytes up to the next line end, so the stream resynchronises on
the following line.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator

from robocal.errors import FramingError

__all__ = ["CRLF", "LineFramer", "StreamBuffer"]

CRLF = b"\r\n"


class StreamBuffer:
    """Receive buffer every framer starts from: :meth:`feed` appends bytes as they arrive,
    :attr:`buffered` counts those not yet returned as a frame."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        """Append received bytes."""
        self._buf += data

    @property
    def buffered(self) -> int:
        """Bytes received and not yet returned as a frame."""
        return len(self._buf)


class LineFramer(StreamBuffer):
    """Split a byte stream into lines and encode lines for the wire.

    Parameters
    ----------
    max_length : int
        Largest accepted line, in bytes, not counting the line end.
    history : int
        Number of recent raw lines kept for error reports (``ProtocolError.last_frames``).
    """

    def __init__(self, *, max_length: int = 512, history: int = 32) -> None:
        if max_length < 1:
            raise ValueError("max_length must be positive")
        super().__init__()
        self.max_length = max_length
        self._discarding = False
        self.recent: deque[bytes] = deque(maxlen=history)
        #: First bytes of the last over-long line dropped (a bridge reads its tag from them).
        self.dropped_head = b""

    def encode(self, line: bytes | str) -> bytes:
        """Return ``line`` with the CR LF terminator, checking it can be framed.

        Raises
        ------
        FramingError
            If the line contains CR or LF or is longer than ``max_length``.
        """
        data = line.encode("ascii") if isinstance(line, str) else bytes(line)
        if b"\r" in data or b"\n" in data:
            raise FramingError("a line to send contains CR or LF", last_frames=[data])
        if len(data) > self.max_length:
            raise FramingError(
                f"a line to send has {len(data)} bytes, more than {self.max_length}",
                last_frames=[data[:64]],
            )
        self.recent.append(b"> " + data)
        return data + CRLF

    def next_line(self) -> bytes | None:
        """Return the next complete line (without terminator), or ``None`` if none is complete.

        Raises
        ------
        FramingError
            Once per over-long line; the framer has already skipped it, so calling again
            continues with the following line.
        """
        while True:
            end = self._buf.find(b"\n")
            if end < 0:
                if self._discarding:
                    self._buf.clear()
                    return None
                # +1 leaves room for a CR whose LF has not arrived yet.
                if len(self._buf) > self.max_length + 1:
                    head = bytes(self._buf[:64])
                    self.dropped_head = head
                    self._buf.clear()
                    self._discarding = True
                    raise FramingError(
                        f"line longer than {self.max_length} bytes without a line end; "
                        "skipping to the next line end",
                        last_frames=[*self.recent, head],
                    )
                return None
            raw = bytes(self._buf[:end])
            del self._buf[: end + 1]
            if self._discarding:
                # The tail of an over-long line; the error was raised already.
                self._discarding = False
                continue
            if raw.endswith(b"\r"):
                raw = raw[:-1]
            if len(raw) > self.max_length:
                self.dropped_head = raw[:64]
                raise FramingError(
                    f"line of {len(raw)} bytes is longer than {self.max_length}",
                    last_frames=[*self.recent, raw[:64]],
                )
            self.recent.append(b"< " + raw)
            return raw

    def lines(self) -> Iterator[bytes | FramingError]:
        """Yield every complete line buffered so far, or the framing error in its place."""
        while True:
            try:
                line = self.next_line()
            except FramingError as err:
                yield err
                continue
            if line is None:
                return
            yield line

    def reset(self) -> None:
        """Drop buffered input (after a reconnect)."""
        self._buf.clear()
        self._discarding = False
