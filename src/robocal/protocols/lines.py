"""A line channel: a :class:`~robocal.protocols.transport.Transport` plus a :class:`LineFramer`."""

from __future__ import annotations

import time

from robocal.errors import TransportTimeout
from robocal.protocols.framing import LineFramer
from robocal.protocols.transport import Transport

__all__ = ["LineStream"]


class LineStream:
    """Read and write CR LF lines over a transport, every wait bounded.

    Parameters
    ----------
    transport : Transport
        An opened (or to be opened) transport.
    max_length : int
        Longest accepted line in bytes.
    """

    def __init__(self, transport: Transport, *, max_length: int = 512) -> None:
        self.transport = transport
        self.framer = LineFramer(max_length=max_length)

    @property
    def last_frames(self) -> list[bytes]:
        """Recent raw lines, ``b"> "`` sent and ``b"< "`` received, oldest first."""
        return list(self.framer.recent)

    async def write_line(self, line: bytes | str) -> None:
        """Frame and send one line."""
        await self.transport.write(self.framer.encode(line))

    async def read_line(self, *, timeout: float) -> bytes:
        """Return the next line without its terminator.

        Raises
        ------
        FramingError
            For an over-long line (already skipped; the next call continues after it).
        TransportTimeout
            If no complete line arrived within ``timeout`` seconds.
        TransportError
            If the peer closed the connection.
        """
        deadline = time.monotonic() + timeout
        while True:
            line = self.framer.next_line()
            if line is not None:
                return line
            # Past the deadline this is a last, non-blocking read: bytes already waiting
            # still complete the line (the transport's read looks once more before it fails).
            remaining = max(0.0, deadline - time.monotonic())
            try:
                data = await self.transport.read(4096, timeout=remaining)
            except TransportTimeout as err:
                raise TransportTimeout(
                    f"{self.transport.url}: no complete line within {timeout:.3g} s",
                    last_frames=self.last_frames,
                ) from err
            self.framer.feed(data)

    def reset(self) -> None:
        """Forget buffered input (after reconnecting)."""
        self.framer.reset()
