"""Sans-I/O request/reply sessions: which request a reply answers, and which are overdue.

A session holds the requests sent and not yet answered; it neither reads, writes nor looks
at a clock. The driver tells it what it sent (with the request's deadline, monotonic
seconds), feeds it every message it decodes, and calls ``timeout(now)`` when a wait ran out;
the session answers with the request a message settles, the requests it makes moot, and the
requests that are overdue. Drivers keep the I/O (sockets, futures, retries, reconnects).

:class:`Window`
    The core: up to ``size`` requests outstanding, each under a unique key.
:class:`RmiSession`
    FANUC RMI: one command at a time (a command reply echoes only the command's name) and
    up to eight instructions matched by SequenceID; a reply for a SequenceID no longer
    outstanding (timed out, stopped, faulted) is discarded.
:class:`LtpSession`
    LTP/1: one request at a time (``STOP`` may join a running ``MEAS``), tags assigned here.
    A bridge answers in order, so a reply settles every earlier request; a request that
    timed out stays owed for a grace period before the next one may be sent.
:class:`EmsconSession`
    Leica emScon: one command in flight, matched by the echoed command ID; ``StartMeasurement``
    also awaits its result packet (in either order), a type-1 packet for the pending command
    fails it, and event 25 starts a grace period after which the measurement counts as lost.

Design: ``docs/adr/0043-sans-io-request-reply-sessions.md``.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterator
from dataclasses import dataclass
from enum import Enum
from typing import Generic, Literal, TypeVar

from robocal.errors import RequestPending, UnexpectedReply
from robocal.protocols import emscon, ltp
from robocal.protocols import fanuc_rmi as rmi

__all__ = [
    "BadFrame",
    "Disposition",
    "EmsconExchange",
    "EmsconSession",
    "LtpReceipt",
    "LtpSession",
    "Request",
    "RmiReceipt",
    "RmiSession",
    "Window",
]

K = TypeVar("K", bound=Hashable)


@dataclass(eq=False, slots=True)
class Request(Generic[K]):
    """One request sent: the ``key`` its reply carries, a ``name`` for messages, its deadline.

    Compared by identity, so a driver may key its waiters by the request itself.
    """

    key: K
    name: str
    deadline: float
    #: Set by ``timeout``: the request is overdue (its reply, if it comes, is late).
    late: bool = False


class Window(Generic[K]):
    """Requests sent and not yet answered, at most ``size``, oldest first.

    Raises
    ------
    ValueError
        If ``size`` is below 1.
    """

    def __init__(self, size: int = 1) -> None:
        if size < 1:
            raise ValueError(f"window size must be at least 1, not {size}")
        self.size = size
        self._open: dict[K, Request[K]] = {}

    def __len__(self) -> int:
        return len(self._open)

    def __iter__(self) -> Iterator[Request[K]]:
        return iter(list(self._open.values()))

    def __contains__(self, key: object) -> bool:
        return key in self._open

    @property
    def full(self) -> bool:
        """True when no further request may be sent."""
        return len(self._open) >= self.size

    def open(self, key: K, name: str, deadline: float) -> Request[K]:
        """Record a request about to be sent.

        Raises
        ------
        RequestPending
            If the window is full or ``key`` is still outstanding.
        """
        if self.full:
            raise RequestPending(f"{name} not sent: {len(self._open)} request(s) outstanding")
        if key in self._open:
            raise RequestPending(f"{name} not sent: {key!r} is still outstanding")
        req = Request(key, name, deadline)
        self._open[key] = req
        return req

    def answer(self, key: K) -> Request[K] | None:
        """Close and return the request under ``key``; None if none is outstanding."""
        return self._open.pop(key, None)

    def drop(self, req: Request[K]) -> bool:
        """Forget ``req`` (its reply, should it come, is then unmatched); True if it was open."""
        if self._open.get(req.key) is req:
            del self._open[req.key]
            return True
        return False

    def timeout(self, now: float) -> list[Request[K]]:
        """Close and return every request whose deadline is at or before ``now``."""
        expired = [r for r in self._open.values() if r.deadline <= now]
        for r in expired:
            del self._open[r.key]
            r.late = True
        return expired

    def clear(self) -> list[Request[K]]:
        """Close and return every outstanding request (link lost, motion stopped)."""
        gone = list(self._open.values())
        self._open.clear()
        return gone

    def next_deadline(self) -> float | None:
        """The earliest deadline of an outstanding request, or None."""
        return min((r.deadline for r in self._open.values()), default=None)


# --- FANUC RMI ---------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class RmiReceipt:
    """What a received RMI packet means for the session.

    ``kind``: ``reply`` (answers ``request``), ``unmatched`` (no outstanding request takes
    it), ``fault`` (FRC_SystemFault: ``failed`` lists the instructions it ended),
    ``terminate`` (the controller ended the session: ``failed`` lists every request),
    ``disconnect`` (FRC_Disconnect acknowledged) or ``other`` (a communication packet
    robocal does not use).
    """

    kind: Literal["reply", "unmatched", "fault", "terminate", "disconnect", "other"]
    request: Request[str] | Request[int] | None = None
    failed: tuple[Request[str] | Request[int], ...] = ()


class RmiSession:
    """FANUC RMI request matching (commands by name, instructions by SequenceID).

    Parameters
    ----------
    window : int
        Instructions allowed in flight (the controller buffers 8).

    Attributes
    ----------
    next_seq : int
        SequenceID of the next instruction.
    hold : bool
        The controller reported a fault (or refused a SequenceID) and holds until
        ``FRC_Reset``; the driver recovers before the next instruction.
    """

    def __init__(self, window: int = rmi.MAX_IN_FLIGHT) -> None:
        self.commands: Window[str] = Window(1)
        self.instructions: Window[int] = Window(window)
        self.next_seq = 1
        self.hold = False

    def command(self, name: str, deadline: float) -> Request[str]:
        """Record command ``name`` about to be sent (one at a time)."""
        return self.commands.open(name, name, deadline)

    def instruction(self, name: str, deadline: float) -> Request[int]:
        """Record an instruction about to be sent under the next SequenceID (``key``)."""
        req = self.instructions.open(self.next_seq, name, deadline)
        self.next_seq = rmi.next_sequence_id(self.next_seq)
        return req

    def withdraw(self, req: Request[int]) -> None:
        """``req`` could not be sent: forget it and give its SequenceID back if it was the
        last one handed out."""
        if self.instructions.drop(req) and rmi.next_sequence_id(req.key) == self.next_seq:
            self.next_seq = req.key

    def resync(self, next_sequence_id: int) -> None:
        """Continue from the controller's NextSequenceID (out of range: from 1)."""
        ok = 1 <= next_sequence_id <= rmi.MAX_SEQUENCE_ID
        self.next_seq = next_sequence_id if ok else 1

    def receive(self, packet: rmi.Packet) -> RmiReceipt:
        """Match one received packet."""
        if packet.category == "Command":
            open_cmds = list(self.commands)
            if open_cmds and packet.name in (open_cmds[0].name, "Unknown"):
                return RmiReceipt("reply", self.commands.answer(open_cmds[0].key))
            return RmiReceipt("unmatched")
        if packet.category == "Instruction":
            seq = packet.sequence_id
            req = self.instructions.answer(seq) if seq is not None else None
            return RmiReceipt("unmatched") if req is None else RmiReceipt("reply", req)
        if packet.name == "FRC_SystemFault":
            self.hold = True
            return RmiReceipt("fault", failed=tuple(self.instructions.clear()))
        if packet.name == "FRC_Terminate":
            return RmiReceipt("terminate", failed=tuple(self.clear()))
        if packet.name == "FRC_Disconnect":
            return RmiReceipt("disconnect")
        return RmiReceipt("other")

    def timeout(self, now: float) -> list[Request[str] | Request[int]]:
        """Close the requests overdue at ``now``; their late replies are then unmatched."""
        return [*self.commands.timeout(now), *self.instructions.timeout(now)]

    def clear(self) -> list[Request[str] | Request[int]]:
        """Close every outstanding request."""
        return [*self.commands.clear(), *self.instructions.clear()]


# --- LTP/1 -------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class LtpReceipt:
    """What a received LTP/1 reply means: the ``request`` it answers (None: unknown tag) and
    the earlier requests whose replies were ``lost`` (a later one was answered first)."""

    request: Request[str] | None
    lost: tuple[Request[str], ...] = ()


class LtpSession:
    """LTP/1 request matching: in order, one request outstanding (``STOP`` may join ``MEAS``).

    Parameters
    ----------
    late_grace_s : float
        How long a request that timed out stays owed: the next request waits for its late
        reply until then (seconds).
    """

    #: Tags run 1..99,999,999 and wrap (at most 8 characters on the wire).
    MAX_TAG = 99_999_999

    def __init__(self, late_grace_s: float) -> None:
        self.late_grace_s = late_grace_s
        self._tag = 0
        self._open: dict[str, Request[str]] = {}
        #: Until when the late replies still owed are awaited (monotonic seconds).
        self.owed_until = 0.0

    def __len__(self) -> int:
        return len(self._open)

    def __iter__(self) -> Iterator[Request[str]]:
        return iter(list(self._open.values()))

    def owed(self, verb: str) -> list[Request[str]]:
        """The outstanding requests ``verb`` must wait for (``STOP`` need not wait for MEAS)."""
        return [r for r in self._open.values() if not (verb == "STOP" and r.name == "MEAS")]

    def send(self, verb: str, deadline: float) -> Request[str]:
        """Record ``verb`` about to be sent; its ``key`` is the tag to send it under.

        Raises
        ------
        RequestPending
            If an earlier request is still owed (see :meth:`owed`).
        """
        owed = self.owed(verb)
        if owed:
            names = ", ".join(f"{r.name} (tag {r.key})" for r in owed)
            raise RequestPending(f"bridge has not answered {names}; {verb} not sent")
        self._tag = self._tag % self.MAX_TAG + 1
        req = Request(str(self._tag), verb, deadline)
        self._open[req.key] = req
        return req

    def receive(self, reply: ltp.Ok | ltp.Err) -> LtpReceipt:
        """Match one reply; a reply settles every earlier request, unless it is ``ERR BUSY``
        (the bridge is still running the earlier request)."""
        if reply.tag not in self._open:
            return LtpReceipt(None)
        lost: list[Request[str]] = []
        if not (isinstance(reply, ltp.Err) and reply.code == ltp.ErrorCode.BUSY):
            for key in list(self._open):  # in the order sent
                if key == reply.tag:
                    break
                lost.append(self._open.pop(key))
        return LtpReceipt(self._open.pop(reply.tag), tuple(lost))

    def timeout(self, now: float) -> list[Request[str]]:
        """Mark the requests overdue at ``now`` late: they stay owed until ``now`` plus the
        grace period. Returns the requests newly marked."""
        newly = [r for r in self._open.values() if r.deadline <= now and not r.late]
        for r in newly:
            r.late = True
        if newly:
            self.owed_until = now + self.late_grace_s
        return newly

    def reset(self) -> None:
        """Forget every outstanding request (a new link)."""
        self._open.clear()


# --- Leica emScon ------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class BadFrame:
    """A frame that could not be decoded, with its header's ``type`` and ``command`` fields
    (so the pending command can fail on it at once)."""

    type: int
    command: int
    error: Exception

    @classmethod
    def of(cls, frame: bytes, error: Exception) -> BadFrame:
        """The bad ``frame`` (at least 12 bytes of header) and why it was refused."""
        return cls(
            int.from_bytes(frame[4:8], "little", signed=True),
            int.from_bytes(frame[8:12], "little", signed=True),
            error,
        )


class Disposition(Enum):
    """What a packet fed to :meth:`EmsconSession.receive` was."""

    #: Part of the pending command's answer (its reply, result or type-1 failure).
    ANSWER = "answer"
    #: A reply or result no pending command takes (a late answer to an abandoned one).
    STALE = "stale"
    #: Not an answer (event, unsolicited error, live position, unknown type, bad frame).
    UNSOLICITED = "unsolicited"


EmsconResult = emscon.SingleMeasResult | emscon.SingleMeasResult2
_RESULT_TYPES = (emscon.DataType.SINGLE_MEAS_RESULT, emscon.DataType.SINGLE_MEAS_RESULT2)


@dataclass(slots=True)
class EmsconExchange:
    """One command in flight and what has arrived for it."""

    command: int
    deadline: float
    measurement: bool
    reply: emscon.Reply | None = None
    result: EmsconResult | None = None
    #: Failed by a type-1 packet before its reply came: the reply may still follow.
    reply_owed: bool = False
    #: When event 25 (MeasStatus_NotReady) arrived during the measurement.
    not_ready_at: float | None = None
    failed: bool = False

    @property
    def done(self) -> bool:
        """The command has its outcome (a measurement also needs its result unless refused)."""
        if self.failed:
            return True
        return self.reply is not None and (
            not self.measurement or self.reply.status != 0 or self.result is not None
        )


class EmsconSession:
    """emScon request matching: one command in flight, matched by the echoed command ID.

    Parameters
    ----------
    result_order : {"any", "reply_first", "result_first"}
        Order of the ``StartMeasurement`` reply and its result packet; the other order is an
        UnexpectedReply unless ``any``.
    fail_on_not_ready_event : bool
        Event 25 during a measurement starts ``not_ready_grace_s``, after which a timeout
        reports the beam as lost (``timeout`` returns ``"not_ready"``).
    """

    def __init__(
        self,
        *,
        result_order: Literal["any", "reply_first", "result_first"] = "any",
        fail_on_not_ready_event: bool = True,
        not_ready_grace_s: float = 0.2,
    ) -> None:
        self.result_order = result_order
        self.fail_on_not_ready_event = fail_on_not_ready_event
        self.not_ready_grace_s = not_ready_grace_s
        self.pending: EmsconExchange | None = None

    def send(self, command: int, deadline: float, *, measurement: bool = False) -> EmsconExchange:
        """Record ``command`` about to be sent.

        Raises
        ------
        RequestPending
            If a command is still in flight.
        """
        if self.pending is not None and not self.pending.done:
            raise RequestPending(
                f"command {command} not sent: command {self.pending.command} is in flight"
            )
        self.pending = EmsconExchange(command, deadline, measurement)
        return self.pending

    def wait_until(self) -> float:
        """When the wait for the pending command ends (deadline, or the end of the grace
        period after event 25)."""
        x = self._current()
        if x.not_ready_at is None:
            return x.deadline
        return min(x.deadline, x.not_ready_at + self.not_ready_grace_s)

    def receive(self, packet: emscon.Packet | BadFrame, now: float) -> Disposition:
        """Match one received packet against the pending command (if any).

        Raises
        ------
        UnexpectedReply
            The pending command's own answer is malformed or in the refused order.
        """
        x = self.pending
        if x is None or x.done:
            answer_types = emscon.Reply | emscon.SingleMeasResult | emscon.SingleMeasResult2
            return Disposition.STALE if isinstance(packet, answer_types) else (
                Disposition.UNSOLICITED
            )
        if isinstance(packet, BadFrame):
            if (packet.type == emscon.DataType.COMMAND and packet.command == x.command) or (
                x.measurement and packet.type in _RESULT_TYPES
            ):
                raise UnexpectedReply(str(packet.error)) from packet.error
            return Disposition.UNSOLICITED
        if isinstance(packet, emscon.Reply):
            return self._reply(x, packet)
        if isinstance(packet, emscon.SingleMeasResult | emscon.SingleMeasResult2):
            return self._result(x, packet)
        if isinstance(packet, emscon.ErrorResponse) and packet.command == x.command:
            # The pending command failed (the MS reading of a type-1 packet).
            x.reply_owed = x.reply is None
            x.reply = emscon.Reply(x.command, packet.status)
            x.failed = True
            return Disposition.ANSWER
        if (
            x.measurement
            and self.fail_on_not_ready_event
            and isinstance(packet, emscon.StatusChange)
            and packet.event == emscon.Event.MEAS_STATUS_NOT_READY
            and x.result is None
            and x.not_ready_at is None
        ):
            # Give the server not_ready_grace_s to fail the command itself.
            x.not_ready_at = now
        return Disposition.UNSOLICITED

    def _reply(self, x: EmsconExchange, packet: emscon.Reply) -> Disposition:
        if packet.command != x.command or x.reply is not None:
            return Disposition.STALE
        if x.measurement and x.result is None and self.result_order == "result_first":
            raise UnexpectedReply("StartMeasurement reply before its result")
        x.reply = packet
        return Disposition.ANSWER

    def _result(self, x: EmsconExchange, packet: EmsconResult) -> Disposition:
        if not x.measurement or x.result is not None:
            return Disposition.STALE
        if x.reply is None and self.result_order == "reply_first":
            raise UnexpectedReply("result before the StartMeasurement reply")
        x.result = packet
        return Disposition.ANSWER

    def timeout(self, now: float) -> Literal["expired", "not_ready"] | None:
        """The wait ran out at ``now``: ``not_ready`` when event 25's grace period ended
        before the deadline (the beam is lost), ``expired`` when the deadline passed, None
        when neither is due. The pending command is abandoned either way."""
        x = self._current()
        if now < self.wait_until():
            return None
        self.pending = None
        if x.not_ready_at is not None and now < x.deadline:
            return "not_ready"
        return "expired"

    def abandon(self) -> None:
        """Forget the pending command (link lost, reconnect)."""
        self.pending = None

    def _current(self) -> EmsconExchange:
        if self.pending is None:
            raise RequestPending("no emScon command is in flight")
        return self.pending
