"""Laser tracker over LTP/1 (the tracker line protocol of protocols.md 2.5), serial or TCP.

The tracker PC runs a bridge (vendor SDK to LTP/1); this driver speaks only LTP/1, on any
:func:`~robocal.protocols.open_transport` URL (``tcp://``, ``serial://``, ``socket://``).
One request is outstanding at a time; event lines (``* EVT ...``) between a request and its
reply are handled and skipped, replies with another tag (late replies to an earlier,
timed-out request) are discarded, and garbage lines are logged and skipped, so the stream
resynchronises on the next good line.

Errors: ``BEAM_BROKEN``/``NO_TARGET`` raise BeamLost, ``UNSTABLE`` Unstable, ``TIMEOUT`` and
a missing reply DriverTimeout; other refusals MeasurementError (``MEAS``) or OperationError.
"""

from __future__ import annotations

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

__all__ = ["LtpOptions", "LtpTracker"]

_TO_M = {"mm": 1e-3, "m": 1.0, "in": 0.0254}


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
    """

    url: str = Field(min_length=1)
    smr: str | None = "RRR15"
    stab_mm: float = Field(default=0.010, gt=0.0)
    stab_ms: int = Field(default=500, ge=0)
    mode: Literal["stationary", "fast"] = "stationary"
    request_timeout_s: float = Field(default=5.0, gt=0.0)
    reply_margin_s: float = Field(default=2.0, ge=0.0)
    reconnect: bool = True


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
        self._tag = 0
        self._units = "mm"

    # --- connection ----------------------------------------------------------------------------
    async def _connect_impl(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        await self._open(deadline)
        o = self.options
        status = await self._request("STATUS?", {}, deadline=deadline)
        if status.values.get("init") == "0":
            await self._request("INIT", {}, deadline=deadline)
        if o.smr:
            await self._request("SMR", {"type": o.smr}, deadline=deadline)
        await self._request("UNITS", {"len": "mm", "ang": "deg"}, deadline=deadline)
        self._units = "mm"
        self.log.info("tracker ready", **{k: v for k, v in self.info.items() if k != "proto"})

    async def _open(self, deadline: float) -> None:
        """Open the transport and check the protocol with HELLO."""
        transport = open_transport(self.options.url)
        await transport.open(timeout=max(0.05, deadline - time.monotonic()))
        self._stream = LineStream(transport, max_length=ltp.MAX_LINE)
        hello = await self._request("HELLO", {"proto": ltp.PROTO}, deadline=deadline, retry=False)
        if hello.values.get("proto") != ltp.PROTO:
            raise ConnectFailed(
                f"bridge speaks {hello.values.get('proto')!r}, not {ltp.PROTO}", kind=self.kind
            )
        self.info = dict(hello.values)

    async def _close_impl(self) -> None:
        stream, self._stream = self._stream, None
        if stream is None:
            return
        if stream.transport.is_open:
            try:
                self._tag += 1
                await stream.write_line(ltp.format_request(ltp.Request(str(self._tag), "BYE")))
            except Exception as err:  # best effort: the link may already be gone
                self.log.debug("BYE not sent", error=repr(err))
        await stream.transport.close()

    async def _reconnect(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            await stream.transport.close()
        self.log.warning("link lost; reconnecting")
        deadline = time.monotonic() + self.options.request_timeout_s
        with self.translate_errors(connecting=True):
            await self._open(deadline)
            await self._request("UNITS", {"len": "mm", "ang": "deg"}, deadline=deadline)

    # --- request / reply -----------------------------------------------------------------------
    def _next_tag(self) -> str:
        self._tag = self._tag % 99_999_999 + 1
        return str(self._tag)

    async def _request(
        self,
        verb: str,
        args: Mapping[str, object],
        *,
        deadline: float | None = None,
        retry: bool = True,
    ) -> ltp.Ok:
        """Send one request and return its OK reply; map ERR replies to driver errors."""
        if deadline is None:
            deadline = time.monotonic() + self.options.request_timeout_s
        for attempt in (1, 2):
            try:
                with self.translate_errors():
                    reply = await self._exchange(verb, args, deadline)
                break
            except ConnectFailed:
                if not (retry and self.options.reconnect and attempt == 1):
                    raise
                await self._reconnect()
        if isinstance(reply, ltp.Err):
            self._raise(verb, reply)
        return reply

    async def _exchange(
        self, verb: str, args: Mapping[str, object], deadline: float
    ) -> ltp.Ok | ltp.Err:
        stream = self._stream
        if stream is None:
            raise ConnectFailed("not connected", kind=self.kind)
        tag = self._next_tag()
        req = ltp.Request(tag, verb, {k: str(v) for k, v in args.items()})
        await stream.write_line(ltp.format_request(req))
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TransportTimeout(
                    f"no reply to {verb} in time", last_frames=stream.last_frames
                )
            try:
                msg = ltp.parse_message(await stream.read_line(timeout=remaining))
            except (TransportError, TransportTimeout):
                raise
            except FramingError as err:
                self.bad_lines += 1
                self.log.warning("garbage line skipped", error=str(err)[:100])
                continue
            if isinstance(msg, ltp.Event):
                self._on_event(msg)
                continue
            if msg.tag != tag:
                self.log.warning("stale reply discarded", tag=msg.tag, expected=tag)
                continue
            return msg

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
        if point_id is not None:
            args["id"] = point_id
        args.update(
            {
                "mode": o.mode,
                "n": samples,
                "stab_mm": f"{o.stab_mm:g}",
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
        return self._reading(ok, point_id)

    async def _stop_quietly(self) -> None:
        """Abort a MEAS the bridge may still be running; its late reply is discarded by tag."""
        try:
            await self._request(
                "STOP", {}, deadline=time.monotonic() + min(1.0, self.options.request_timeout_s)
            )
        except Exception as err:
            self.log.debug("STOP after timeout failed", error=repr(err))

    def _reading(self, ok: ltp.Ok, point_id: str | None) -> TrackerReading:
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
        if point_id is not None and v.get("id", point_id) != point_id:
            raise UnexpectedReply(f"MEAS reply for point {v.get('id')!r}, asked {point_id!r}")
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
