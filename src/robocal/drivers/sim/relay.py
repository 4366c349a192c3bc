"""Capture and replay of emScon sessions: a logging TCP relay and a replaying server.

The relay sits between a client (robocal, or the vendor's own software) and a real tracker
on port 700 and records every chunk of bytes, timestamped, in both directions::

    robocal sim relay --listen 0.0.0.0:7000 --target 192.168.0.1:700 --record site.jsonl

The recording is JSON lines: a header line, then one line per chunk or connection event::

    {"format": "robocal-emscon-capture/1", "target": "192.168.0.1:700", "started": "..."}
    {"t": 0.0, "conn": 1, "dir": "open"}
    {"t": 0.0012, "conn": 1, "dir": "c2s", "hex": "0c000000...", "packets": ["command ..."]}
    {"t": 0.0031, "conn": 1, "dir": "s2c", "hex": "38000000...", "packets": ["reply ..."]}
    {"t": 9.5, "conn": 1, "dir": "close"}

``t`` is seconds since the relay started; ``hex`` the raw bytes exactly as one ``recv``
returned them (splits and merges preserved); ``packets`` a readable decoding, for people.

:class:`EmsconReplayServer` answers a client from such a recording (``robocal sim
emscon-tracker --replay site.jsonl``): each command received is matched to the next
recorded client packet with the same command ID (or the same bytes), and the server packets
recorded after it are sent back.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any, Literal

import structlog

from robocal.drivers.sim._server import (
    SimServer,
    port_of,
    publish_ports,
    received,
    until_signalled,
)
from robocal.errors import ConfigError, FramingError, UnexpectedReply
from robocal.protocols import emscon

__all__ = [
    "FORMAT",
    "EmsconRelay",
    "EmsconReplayServer",
    "Record",
    "load_recording",
    "recorded_packets",
    "serve_cli",
]

_log = structlog.get_logger(__name__)

FORMAT = "robocal-emscon-capture/1"
Dir = Literal["c2s", "s2c", "open", "close"]


@dataclass(frozen=True)
class Record:
    """One line of a recording: time (s since start), connection number, direction, bytes."""

    t: float
    conn: int
    dir: Dir
    data: bytes = b""


def _summary(packet: emscon.Packet) -> str:
    name = type(packet).__name__
    if isinstance(packet, emscon.Command):
        return f"command {packet.name} {dict(packet.params)}"
    if isinstance(packet, emscon.Reply):
        return f"reply {packet.name} status={packet.status} {dict(packet.data)}"
    if isinstance(packet, emscon.StatusChange):
        return f"event {emscon.event_name(packet.event)}"
    if isinstance(packet, emscon.ErrorResponse):
        return f"error command={packet.command} status={emscon.status_name(packet.status)}"
    if isinstance(packet, emscon.UnknownPacket):
        return f"unknown type {packet.type} ({len(packet.body) + 8} bytes)"
    return f"{name} {emscon.as_dict(packet)}"


class _Annotator:
    """Frame and decode one direction of a connection for the readable ``packets`` field."""

    def __init__(self, direction: emscon.Direction) -> None:
        self.direction = direction
        self.framer = emscon.PacketFramer()

    def __call__(self, data: bytes) -> list[str]:
        if self.framer.broken:
            return ["(framing lost)"]
        self.framer.feed(data)
        out: list[str] = []
        try:
            for frame in self.framer.frames():
                try:
                    out.append(_summary(emscon.decode(frame, direction=self.direction)))
                except (FramingError, UnexpectedReply) as err:
                    out.append(f"undecodable: {err}")
        except FramingError as err:
            out.append(f"framing lost: {err}")
        return out


class _Writer:
    """Append JSON lines to the recording, flushed line by line."""

    def __init__(self, path: Path, header: dict[str, Any]) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: IO[str] | None = path.open("w", encoding="utf-8", buffering=1)
        self._t0 = time.monotonic()
        self.write(header)

    def now(self) -> float:
        return round(time.monotonic() - self._t0, 6)

    def write(self, obj: dict[str, Any]) -> None:
        if self._fh is not None:
            self._fh.write(json.dumps(obj, separators=(",", ":")) + "\n")

    def close(self) -> None:
        fh, self._fh = self._fh, None
        if fh is not None:
            fh.close()


class EmsconRelay(SimServer):
    """A TCP relay that records everything between a client and the tracker.

    Parameters
    ----------
    target_host, target_port
        The tracker's emScon server (port 700 on a real tracker).
    record : Path
        Recording to write (JSON lines, see the module docstring).
    connect_timeout_s
        Time allowed to reach the target for each client.
    """

    def __init__(self, target_host: str, target_port: int, record: Path,
                 *, connect_timeout_s: float = 10.0) -> None:
        super().__init__()
        self.target_host = target_host
        self.target_port = target_port
        self.record = Path(record)
        self.connect_timeout_s = connect_timeout_s
        self.port = 0
        self.connections = 0
        self._writer: _Writer | None = None
        self._streams: set[asyncio.StreamWriter] = set()

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen on ``host:port`` (0: a free port); return the bound port."""
        self._writer = _Writer(self.record, {
            "format": FORMAT,
            "target": f"{self.target_host}:{self.target_port}",
            "started": datetime.now(UTC).isoformat(),
        })
        self.port = port_of(await self._listen(self._on_client, host, port))
        _log.info("emscon relay listening", port=self.port,
                  target=f"{self.target_host}:{self.target_port}", record=str(self.record))
        return self.port

    async def _on_client(self, c_reader: asyncio.StreamReader,
                         c_writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        conn = self.connections
        rec = self._writer
        assert rec is not None
        self._streams.add(c_writer)
        t_writer: asyncio.StreamWriter | None = None
        opened = False
        try:
            try:
                async with asyncio.timeout(self.connect_timeout_s):
                    t_reader, t_writer = await asyncio.open_connection(
                        self.target_host, self.target_port)
            except (OSError, TimeoutError) as err:
                rec.write({"t": rec.now(), "conn": conn, "dir": "close",
                           "error": f"cannot reach the target: {err}"})
                _log.warning("relay: target unreachable", error=str(err))
                return
            self._streams.add(t_writer)
            rec.write({"t": rec.now(), "conn": conn, "dir": "open"})
            opened = True
            pumps = [
                asyncio.create_task(self._pump(c_reader, t_writer, conn, "c2s")),
                asyncio.create_task(self._pump(t_reader, c_writer, conn, "s2c")),
            ]
            try:
                await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for p in pumps:
                    p.cancel()
                for p in pumps:
                    with contextlib.suppress(asyncio.CancelledError, Exception):
                        await p
        finally:
            if opened:
                rec.write({"t": rec.now(), "conn": conn, "dir": "close"})
            for w in (c_writer, t_writer):
                if w is not None:
                    self._streams.discard(w)
                    w.close()
                    with contextlib.suppress(Exception, asyncio.CancelledError):
                        await w.wait_closed()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                    conn: int, direction: Literal["c2s", "s2c"]) -> None:
        rec = self._writer
        assert rec is not None
        annotate = _Annotator("from_client" if direction == "c2s" else "from_server")
        async for data in received(reader):
            rec.write({"t": rec.now(), "conn": conn, "dir": direction, "hex": data.hex(),
                       "packets": annotate(data)})
            writer.write(data)
            await writer.drain()

    async def stop(self) -> None:
        """Stop listening, close every connection and the recording; idempotent."""
        self._close_listeners()
        for w in list(self._streams):
            w.close()
        await self._stop_serving()
        if self._writer is not None:
            self._writer.close()


# --- reading recordings ------------------------------------------------------------------------
def load_recording(path: str | Path) -> list[Record]:
    """Read a recording written by :class:`EmsconRelay`.

    Raises
    ------
    ConfigError
        If the file is missing, not a recording, or has a malformed line (named).
    """
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as err:
        raise ConfigError(f"cannot read the recording: {err}", source=str(p)) from err
    if not lines:
        raise ConfigError("empty recording", source=str(p))
    try:
        header = json.loads(lines[0])
    except json.JSONDecodeError as err:
        raise ConfigError("first line is not JSON", source=f"{p}:1") from err
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ConfigError(f"not a {FORMAT} recording", source=f"{p}:1")
    out: list[Record] = []
    for i, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
            direction = obj["dir"]
            if direction not in ("c2s", "s2c", "open", "close"):
                raise ValueError(f"bad dir {direction!r}")
            out.append(Record(float(obj["t"]), int(obj["conn"]), direction,
                              bytes.fromhex(obj.get("hex", ""))))
        except (json.JSONDecodeError, KeyError, ValueError, TypeError) as err:
            raise ConfigError(f"malformed record: {err}", source=f"{p}:{i}") from err
    return out


def recorded_packets(records: Iterable[Record], conn: int | None = None
                     ) -> list[tuple[float, Literal["c2s", "s2c"], bytes]]:
    """Re-frame the byte chunks of one connection into whole packets, in time order.

    ``conn`` None takes the first connection that carried data.
    """
    recs = [r for r in records if r.dir in ("c2s", "s2c")]
    if conn is None:
        conn = recs[0].conn if recs else 0
    framers = {"c2s": emscon.PacketFramer(), "s2c": emscon.PacketFramer()}
    out: list[tuple[float, Literal["c2s", "s2c"], bytes]] = []
    for r in recs:
        if r.conn != conn:
            continue
        d: Literal["c2s", "s2c"] = "c2s" if r.dir == "c2s" else "s2c"
        framers[d].feed(r.data)
        out.extend((r.t, d, frame) for frame in framers[d].frames())
    return out


# --- replay ------------------------------------------------------------------------------------
def _key(frame: bytes) -> tuple[int, int]:
    size, type_ = emscon.HEADER.unpack_from(frame)
    cmd = int.from_bytes(frame[8:12], "little", signed=True) if size >= 12 else -1
    return type_, cmd


class EmsconReplayServer(SimServer):
    """Serve a recorded session back to a client, packet for packet.

    Parameters
    ----------
    records : list of Record
        A recording (:func:`load_recording`).
    conn : int, optional
        Which recorded connection to replay (default: the first with data).
    match : {"command", "bytes"}
        Match a received command to the next recorded one with the same command ID, or with
        identical bytes.
    time_scale : float
        Multiply the recorded delay between a command and each answer packet (0: at once).

    Attributes
    ----------
    unmatched : list of bytes
        Commands that had no recorded counterpart (answered ``NotImplemented``).
    """

    def __init__(self, records: list[Record], *, conn: int | None = None,
                 match: Literal["command", "bytes"] = "command", time_scale: float = 0.0) -> None:
        super().__init__()
        self.packets = recorded_packets(records, conn)
        if not any(d == "c2s" for _, d, _ in self.packets):
            raise ConfigError("the recording holds no client packets to replay against")
        self.match = match
        self.time_scale = time_scale
        self.unmatched: list[bytes] = []
        self.port = 0

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen; return the bound port."""
        self.port = port_of(await self._listen(self._on_client, host, port))
        return self.port

    def _answers(self, i: int) -> list[tuple[float, bytes]]:
        out = []
        for t, d, frame in self.packets[i:]:
            if d == "c2s":
                break
            out.append((t, frame))
        return out

    async def _on_client(self, reader: asyncio.StreamReader,
                         writer: asyncio.StreamWriter) -> None:
        framer = emscon.PacketFramer()
        cursor = 0
        try:
            for _, frame in self._answers(0):  # what the server sent before any command
                writer.write(frame)
            await writer.drain()
            cursor = next(i for i, (_, d, _) in enumerate(self.packets) if d == "c2s")
            while True:
                data = await reader.read(65536)
                if not data:
                    return
                framer.feed(data)
                for frame in framer.frames():
                    cursor = await self._answer(frame, cursor, writer)
        except (ConnectionError, FramingError):
            pass

    async def _answer(self, frame: bytes, cursor: int, writer: asyncio.StreamWriter) -> int:
        for i in range(cursor, len(self.packets)):
            t0, d, rec = self.packets[i]
            if d != "c2s":
                continue
            if (rec == frame) if self.match == "bytes" else (_key(rec) == _key(frame)):
                for t, answer in self._answers(i + 1):
                    delay = (t - t0) * self.time_scale
                    if delay > 0:
                        await asyncio.sleep(min(delay, 30.0))
                    writer.write(answer)
                await writer.drain()
                return i + 1
        self.unmatched.append(frame)
        _, cmd = _key(frame)
        _log.warning("replay: no recorded counterpart; answering NotImplemented", command=cmd)
        writer.write(emscon.reply(cmd, emscon.Status.NOT_IMPLEMENTED))
        await writer.drain()
        return cursor

    async def stop(self) -> None:
        """Stop serving; idempotent."""
        await self._stop_serving()


# --- command line ------------------------------------------------------------------------------
def _host_port(text: str | None, what: str) -> tuple[str, int]:
    if not text or ":" not in text:
        raise ConfigError("expected HOST:PORT", key=what)
    host, _, port = text.rpartition(":")
    try:
        value = int(port)
    except ValueError as err:
        raise ConfigError(f"bad port {port!r}", key=what) from err
    if not 0 <= value <= 65535:
        raise ConfigError(f"port {value} out of range", key=what)
    return host.strip("[]") or "127.0.0.1", value


async def serve_cli(args: argparse.Namespace) -> int:
    """``robocal sim relay ...`` and ``robocal sim emscon-tracker --replay FILE``."""
    server: EmsconRelay | EmsconReplayServer
    try:
        if args.which == "relay":
            if args.record is None:
                raise ConfigError("--record FILE is required", key="--record")
            listen_host, listen_port = _host_port(args.listen, "--listen")
            target_host, target_port = _host_port(args.target, "--target")
            server = EmsconRelay(target_host, target_port, args.record)
            await server.start(listen_host, listen_port)
            ports: dict[str, Any] = {"relay": {"host": listen_host, "port": server.port,
                                               "target": args.target,
                                               "record": str(args.record)}}
        else:
            server = EmsconReplayServer(load_recording(args.replay))
            await server.start(args.host, args.port)
            ports = {"host": args.host,
                     "emscon_tracker": {"port": server.port, "replay": str(args.replay)}}
    except ConfigError as err:
        sys.stderr.write(f"robocal sim: {err}\n")
        return 2
    try:
        async with until_signalled() as stop:
            publish_ports(ports, args.ports_file)
            await stop.wait()
    finally:
        await server.stop()
    return 0
