"""Laser tracker over LTP/1 (normative description: ``docs/protocols/ltp1.md``), serial or TCP.

The tracker PC runs a bridge (vendor SDK to LTP/1); this driver speaks only LTP/1, on any
:func:`~robocal.protocols.open_transport` URL (``tcp://``, ``serial://``, ``socket://``).

Exactly one request is outstanding at a time. A request whose reply did not come in time
stays outstanding: before the next request the driver waits for that late reply (and
discards it), so it never pipelines; the one exception is ``STOP``, which the protocol
allows while a ``MEAS`` runs. If a late reply never comes the link is re-opened. A bridge
answers in order, so a reply to a later request (other than ``ERR 14 BUSY``) settles every
earlier one: a reply lost on a serial line (the MEAS before a STOP, typically) is no longer
awaited, and costs no later request. Event lines (``* EVT ...``) are handled and skipped
anywhere; garbage lines are logged and skipped.
``ERR 14 BUSY`` is retried with back-off until the request's deadline.

After ``HELLO`` the driver sets ``INIT`` (if needed), ``SMR``, ``UNITS len=mm ang=deg`` and
``FRAME name=<frame>`` and checks them with ``STATUS?``, so readings are never mislabelled by
a bridge left in another frame. Point ids are made valid (characters outside
``A-Z a-z 0-9 _ . : -`` become ``_``) or refused (empty, longer than 64) before sending.

Errors: ``BEAM_BROKEN``/``NO_TARGET`` raise BeamLost, ``UNSTABLE`` Unstable, ``TIMEOUT``,
a missing reply and a bridge that stays ``BUSY`` DriverTimeout (all retryable); other
refusals MeasurementError (``MEAS``) or OperationError.
"""

from __future__ import annotations

import asyncio
import re
import time
from collections.abc import Mapping
from datetime import datetime
from typing import Any, ClassVar, Literal, NoReturn

from pydantic import Field

from robocal.drivers._base import DriverBase, DriverOptions
from robocal.drivers.api import TrackerReading
from robocal.errors import (
    BeamLost,
    ConfigError,
    ConnectFailed,
    DriverTimeout,
    FramingError,
    MeasurementError,
    OperationError,
    TransportError,
    TransportTimeout,
    UnexpectedReply,
    Unstable,
)
from robocal.protocols import LineStream, ltp, open_transport
from robocal.protocols.session import LtpSession

__all__ = ["LtpOptions", "LtpTracker", "decimal_text", "wire_point_id"]

_TO_M = {"mm": 1e-3, "m": 1.0, "in": 0.0254}
#: Lines still read (non-blocking) once a deadline has passed: a reply already waiting
#: behind a few events is taken, a bridge that talks without end is not waited for.
_LATE_LINES = 32


class LtpOptions(DriverOptions):
    """Options of :class:`LtpTracker`.

    Attributes
    ----------
    url
        Transport URL: ``tcp://host:7710``, ``serial:///dev/ttyUSB0?baudrate=115200``, ...
    smr
        Reflector type announced with ``SMR`` after connecting (None: leave it).
    stab_mm, stab_ms
        Stability criterion sent with every ``MEAS``.
    mode
        ``MEAS`` mode.
    request_timeout_s
        Timeout for requests other than ``MEAS``, seconds.
    reply_margin_s
        Extra wait beyond a ``MEAS`` timeout for the bridge's reply, seconds.
    reconnect
        Reconnect once and repeat the request when the link drops mid-request.
    frame
        Frame the bridge is put in after connecting; readings are labelled with it.
    smr_offset_mm
        Reflector distance offset announced with ``SMR``, mm.
    """

    url: str = Field(min_length=1)
    smr: str | None = "RRR15"
    stab_mm: float = Field(default=0.010, gt=0.0)
    stab_ms: int = Field(default=500, ge=0)
    mode: Literal["stationary", "fast"] = "stationary"
    request_timeout_s: float = Field(default=5.0, gt=0.0)
    reply_margin_s: float = Field(default=2.0, ge=0.0)
    reconnect: bool = True
    frame: str = Field(default="tracker", pattern=r"^[A-Za-z0-9_.-]{1,32}$")
    smr_offset_mm: float = 0.0


class LtpTracker(DriverBase):
    """A laser tracker behind an LTP/1 bridge.

    Parameters
    ----------
    options : LtpOptions or mapping
        Validated options (``url`` is required).

    Attributes
    ----------
    info : dict
        The bridge's ``HELLO`` reply (vendor, model, serial, fw, bridge).
    beam : str
        Last beam state seen (``LOCKED``, ``BROKEN``, ``SEARCHING``).
    weather : dict
        Last environment values seen (``temp_c``, ``press_hpa``, ``hum_pct``).
    bad_lines : int
        Garbage lines skipped so far.
    """

    kind: ClassVar[str] = "ltp"
    Options: ClassVar[type[DriverOptions]] = LtpOptions
    options: LtpOptions

    def __init__(self, options: LtpOptions | Mapping[str, Any] | None = None) -> None:
        super().__init__(options)
        self.info: dict[str, str] = {}
        self.beam = "UNKNOWN"
        self.weather: dict[str, float] = {}
        self.bad_lines = 0
        self._stream: LineStream | None = None
        #: Request matching (sans-I/O): tags, what is still owed, which reply answers what.
        #: A request that timed out stays owed for one more request timeout.
        self._session = LtpSession(late_grace_s=self.options.request_timeout_s)
        self._units = "mm"

    # --- connection ----------------------------------------------------------------------------
    async def _connect_impl(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        await self._open(deadline)
        status = await self._request("STATUS?", {}, deadline=deadline)
        if status.values.get("init") == "0":
            await self._request("INIT", {}, deadline=deadline)
        await self._setup(deadline)
        self.log.info("tracker ready", **{k: v for k, v in self.info.items() if k != "proto"})

    async def _setup(self, deadline: float) -> None:
        """Announce the SMR, set units and frame, and check them with ``STATUS?``."""
        o = self.options
        if o.smr:
            args: dict[str, object] = {"type": o.smr}
            if o.smr_offset_mm:
                args["offset_mm"] = decimal_text(o.smr_offset_mm, 4)
            await self._request("SMR", args, deadline=deadline, retry=False)
        await self._request("UNITS", {"len": "mm", "ang": "deg"}, deadline=deadline, retry=False)
        self._units = "mm"
        frame = await self._request("FRAME", {"name": o.frame}, deadline=deadline, retry=False)
        status = await self._request("STATUS?", {}, deadline=deadline, retry=False)
        got = (frame.values.get("name"), status.values.get("frame"), status.values.get("units"))
        if got[0] != o.frame or got[1] not in (None, o.frame) or got[2] not in (None, "mm"):
            raise ConnectFailed(
                f"bridge did not take frame {o.frame!r} and units mm "
                f"(FRAME name={got[0]!r}, STATUS? frame={got[1]!r} units={got[2]!r})",
                kind=self.kind,
            )

    async def _open(self, deadline: float) -> None:
        """Open the transport and check the protocol with HELLO."""
        transport = open_transport(self.options.url)
        await transport.open(timeout=max(0.05, deadline - time.monotonic()))
        self._stream = LineStream(transport, max_length=ltp.MAX_LINE)
        self._session.reset()
        hello = await self._request("HELLO", {"proto": ltp.PROTO}, deadline=deadline, retry=False)
        if hello.values.get("proto") != ltp.PROTO:
            raise ConnectFailed(
                f"bridge speaks {hello.values.get('proto')!r}, not {ltp.PROTO}", kind=self.kind
            )
        self.info = dict(hello.values)

    async def _close_impl(self) -> None:
        stream = self._stream
        if stream is None:
            return
        if stream.transport.is_open:
            try:
                # BYE only when nothing is outstanding: never two requests at once.
                deadline = time.monotonic() + 0.5
                await self._settle(stream, deadline, "BYE")
                await self._exchange("BYE", {}, deadline)
            except Exception as err:  # best effort: the link may already be gone
                self.log.debug("BYE not sent or not answered", error=repr(err))
        self._stream = None
        self._session.reset()
        await stream.transport.close()

    async def _reconnect(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            await stream.transport.close()
        self.log.warning("link lost or out of step; reconnecting")
        deadline = time.monotonic() + self.options.request_timeout_s
        with self.translate_errors(connecting=True):
            await self._open(deadline)
            await self._setup(deadline)

    # --- request / reply -----------------------------------------------------------------------
    async def _request(
        self,
        verb: str,
        args: Mapping[str, object],
        *,
        deadline: float | None = None,
        retry: bool = True,
    ) -> ltp.Ok:
        """Send one request and return its OK reply; map ERR replies to driver errors.

        ``ERR 14 BUSY`` is retried with back-off until ``deadline``; a link that drops, or
        an earlier request that is never answered, is re-opened once when ``retry``.
        """
        if deadline is None:
            deadline = time.monotonic() + self.options.request_timeout_s
        reopened = False
        delay = 0.01
        while True:
            try:
                with self.translate_errors():
                    reply = await self._exchange(verb, args, deadline)
            except (ConnectFailed, _Unanswered) as err:
                if reopened or not (retry and self.options.reconnect):
                    if isinstance(err, _Unanswered):
                        raise DriverTimeout(str(err), kind=self.kind) from err
                    raise
                reopened = True
                await self._reconnect()
                continue
            if isinstance(reply, ltp.Err) and reply.code == ltp.ErrorCode.BUSY:
                remaining = deadline - time.monotonic()
                if remaining <= delay:
                    raise DriverTimeout(
                        f"{verb}: bridge stayed BUSY until the deadline", kind=self.kind
                    )
                self.log.info("bridge busy; retrying", verb=verb, delay_s=delay)
                await asyncio.sleep(delay)
                delay = min(delay * 2, 0.5)
                continue
            break
        if isinstance(reply, ltp.Err):
            self._raise(verb, reply)
        return reply

    async def _exchange(
        self, verb: str, args: Mapping[str, object], deadline: float
    ) -> ltp.Ok | ltp.Err:
        stream = self._stream
        if stream is None:
            raise ConnectFailed("not connected", kind=self.kind)
        await self._settle(stream, deadline, verb)
        tag = self._session.send(verb, deadline).key
        await stream.write_line(
            ltp.format_request(ltp.Request(tag, verb, {k: str(v) for k, v in args.items()}))
        )
        try:
            msg = await self._read_until(stream, deadline, tag, verb)
        except TransportTimeout:
            # Left outstanding: its reply is still owed, for one more request timeout.
            self._session.timeout(max(time.monotonic(), deadline))
            raise
        assert msg is not None
        return msg

    async def _settle(self, stream: LineStream, deadline: float, verb: str) -> None:
        """Wait for the replies still owed before ``verb`` may be sent.

        A late reply is awaited for one request timeout after its request timed out.

        Raises
        ------
        _Unanswered
            If they do not arrive by ``deadline`` (the request is then not sent).
        """
        if not self._session.owed(verb):
            return
        try:
            await self._read_until(stream, min(deadline, self._session.owed_until), None, verb)
        except TransportTimeout as err:
            names = ", ".join(f"{r.name} (tag {r.key})" for r in self._session.owed(verb))
            raise _Unanswered(f"bridge has not answered {names}; {verb} not sent") from err

    async def _read_until(
        self,
        stream: LineStream,
        deadline: float,
        tag: str | None,
        verb: str,
    ) -> ltp.Ok | ltp.Err | None:
        """Read lines until the reply to ``tag`` arrives (or, tag None, every reply ``verb``
        must wait for)."""
        overdue = 0
        while True:
            if tag is None and not self._session.owed(verb):
                return None
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                # Past the deadline only lines already waiting are taken (non-blocking),
                # a bounded number of them.
                overdue += 1
                if overdue > _LATE_LINES:
                    raise TransportTimeout(
                        f"no reply to {verb} in time", last_frames=stream.last_frames
                    )
            try:
                msg = ltp.parse_message(await stream.read_line(timeout=max(0.0, remaining)))
            except TransportTimeout as err:
                raise TransportTimeout(
                    f"no reply to {verb} in time", last_frames=stream.last_frames
                ) from err
            except TransportError:
                raise
            except FramingError as err:
                self.bad_lines += 1
                self.log.warning("garbage line skipped", error=str(err)[:100])
                continue
            if isinstance(msg, ltp.Event):
                self._on_event(msg)
                continue
            receipt = self._session.receive(msg)
            for lost in receipt.lost:
                # A bridge answers in order (ltp1.md, section 5): a later reply means the
                # earlier one was lost (on a serial line, a garbled line).
                self.log.warning("reply lost; request no longer awaited", tag=lost.key,
                                 verb=lost.name, answered=msg.tag)
            if receipt.request is None:
                self.log.warning("reply with unknown tag discarded", tag=msg.tag)
            elif msg.tag == tag:
                return msg
            else:
                self.log.info("late reply discarded", tag=msg.tag, verb=receipt.request.name)

    def _on_event(self, event: ltp.Event) -> None:
        v = event.values
        if event.name == "BEAM":
            self.beam = v.get("state", self.beam)
            self.log.info("beam", state=self.beam)
        elif event.name == "WEATHER":
            self.weather.update(_weather(v))
        elif event.name == "FAULT":
            self.log.warning("tracker fault event", code=v.get("code"), msg=v.get("msg"))
        else:
            self.log.debug("event", name=event.name)

    def _raise(self, verb: str, err: ltp.Err) -> NoReturn:
        text = f"{verb}: ERR {err.code} {err.name}" + (f" ({err.msg})" if err.msg else "")
        if err.code in (ltp.ErrorCode.BEAM_BROKEN, ltp.ErrorCode.NO_TARGET):
            raise BeamLost(text, kind=self.kind)
        if err.code == ltp.ErrorCode.UNSTABLE:
            raise Unstable(text, kind=self.kind)
        if err.code == ltp.ErrorCode.TIMEOUT:
            raise DriverTimeout(text, kind=self.kind)
        if verb == "MEAS":
            raise MeasurementError(text, kind=self.kind)
        raise OperationError(text, kind=self.kind)

    # --- tracker API ---------------------------------------------------------------------------
    async def measure(
        self, *, samples: int = 10, timeout: float = 10.0, point_id: str | None = None
    ) -> TrackerReading:
        """Measure the reflector, averaging ``samples``; position in metres, tracker frame.

        Raises
        ------
        BeamLost, Unstable
            Recoverable measurement failures (retry, see ``measure_with_retry``).
        DriverTimeout
            No result within ``timeout`` seconds (the bridge is then told to ``STOP``).
        """
        self._ensure_connected()
        if samples < 1:
            raise ConfigError("samples must be at least 1", source="measure", key="samples")
        o = self.options
        args: dict[str, object] = {}
        wire_id = None if point_id is None else wire_point_id(point_id)
        if wire_id is not None:
            args["id"] = wire_id
        args.update(
            {
                "mode": o.mode,
                "n": samples,
                "stab_mm": decimal_text(o.stab_mm),
                "stab_ms": o.stab_ms,
                "timeout_ms": max(1, int(timeout * 1000)),
            }
        )
        deadline = time.monotonic() + timeout + o.reply_margin_s
        try:
            ok = await self._request("MEAS", args, deadline=deadline)
        except DriverTimeout:
            await self._stop_quietly()
            raise
        return self._reading(ok, point_id, wire_id)

    async def _stop_quietly(self) -> None:
        """Abort a MEAS the bridge may still be running; its late reply is awaited later."""
        try:
            await self._request(
                "STOP",
                {},
                deadline=time.monotonic() + min(1.0, self.options.request_timeout_s),
                retry=False,
            )
        except Exception as err:
            self.log.debug("STOP after timeout failed", error=repr(err))

    def _reading(self, ok: ltp.Ok, point_id: str | None, wire_id: str | None) -> TrackerReading:
        v = ok.values
        k = _TO_M[self._units]
        try:
            pos = (float(v["x"]) * k, float(v["y"]) * k, float(v["z"]) * k)
            std = None
            if all(s in v for s in ("sx", "sy", "sz")):
                std = (float(v["sx"]) * k, float(v["sy"]) * k, float(v["sz"]) * k)
            n = int(v.get("n", "1"))
            rms = float(v["rms"]) * k if "rms" in v else None
        except (KeyError, ValueError) as err:
            raise UnexpectedReply(f"MEAS reply lacks or garbles a field: {err}") from err
        if not all(map(_finite, pos)):
            raise UnexpectedReply("MEAS reply has non-finite coordinates")
        weather = _weather(v) or dict(self.weather)
        if wire_id is not None and v.get("id", wire_id) != wire_id:
            raise UnexpectedReply(f"MEAS reply for point {v.get('id')!r}, asked {wire_id!r}")
        if v.get("frame", self.options.frame) != self.options.frame:
            raise UnexpectedReply(
                f"MEAS reply in frame {v.get('frame')!r}, expected {self.options.frame!r}"
            )
        return TrackerReading(
            position_m=pos,
            std_m=std,
            n=n,
            rms_m=rms,
            timestamp=_timestamp(v.get("t")),
            status="ok",
            weather=weather,
            point_id=point_id,
        )

    async def status(self) -> dict[str, str]:
        """Return the bridge's ``STATUS?`` reply as strings."""
        self._ensure_connected()
        return dict((await self._request("STATUS?", {})).values)


class _Unanswered(Exception):
    """An earlier request is still unanswered, so no new one may be sent."""


_ID_BAD = re.compile(r"[^A-Za-z0-9_.:-]")


def wire_point_id(point_id: str) -> str:
    """Return ``point_id`` as LTP/1 carries it: ``A-Z a-z 0-9 _ . : -``, others become ``_``.

    Raises
    ------
    ConfigError
        If the id is empty or longer than 64 characters.
    """
    wire = _ID_BAD.sub("_", point_id)
    if not 1 <= len(wire) <= 64:
        raise ConfigError(
            f"point id {point_id[:80]!r} cannot be sent over LTP/1: 1..64 characters",
            source="measure",
            key="point_id",
        )
    return wire


def decimal_text(x: float, places: int = 6) -> str:
    """Return ``x`` as an LTP/1 decimal: fixed point, no exponent (``1e-05`` is not one)."""
    text = f"{x:.{places}f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def _finite(x: float) -> bool:
    return x == x and x not in (float("inf"), float("-inf"))


def _weather(v: Mapping[str, str]) -> dict[str, float]:
    out: dict[str, float] = {}
    for key, name in (("temp", "temp_c"), ("press", "press_hpa"), ("hum", "hum_pct")):
        try:
            if key in v:
                out[name] = float(v[key])
        except ValueError:
            continue
    return out


def _timestamp(text: str | None) -> float:
    if text:
        try:
            return datetime.fromisoformat(text).timestamp()
        except ValueError:
            pass
    return time.time()
