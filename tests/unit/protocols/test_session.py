"""Sans-I/O request/reply sessions: any interleaving of sends, replies, garbage and timeouts."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.errors import RequestPending, UnexpectedReply
from robocal.protocols import emscon, ltp
from robocal.protocols import fanuc_rmi as rmi
from robocal.protocols.session import (
    BadFrame,
    Disposition,
    EmsconSession,
    LtpSession,
    Request,
    RmiSession,
    Window,
)

# One step of a run: (operation, small integer argument, time advance in seconds).
_steps = st.lists(
    st.tuples(st.sampled_from("srgtcd"), st.integers(0, 12), st.floats(0.0, 2.0)),
    max_size=60,
)


# --- Window ------------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(size=st.integers(1, 4), steps=_steps)
def test_window_never_exceeds_its_size_and_closes_each_request_once(size, steps):
    window: Window[int] = Window(size)
    now = 0.0
    opened: list[Request[int]] = []
    closed: list[Request[int]] = []
    for op, arg, dt in steps:
        now += dt
        if op == "s":
            if window.full or arg in window:
                with pytest.raises(RequestPending):
                    window.open(arg, "req", now + 1.0)
            else:
                opened.append(window.open(arg, "req", now + 1.0))
        elif op in "rg":
            got = window.answer(arg)
            if got is not None:
                closed.append(got)
        elif op == "t":
            expired = window.timeout(now)
            assert all(r.deadline <= now and r.late for r in expired)
            closed.extend(expired)
        elif op == "c":
            closed.extend(window.clear())
        elif opened and window.drop(opened[arg % len(opened)]):
            closed.append(opened[arg % len(opened)])
        assert len(window) <= size
        deadline = window.next_deadline()
        assert deadline is None or deadline == min(r.deadline for r in window)
    still_open = list(window)
    assert sorted(map(id, closed + still_open)) == sorted(map(id, opened))


# --- FANUC RMI ---------------------------------------------------------------------------------
_COMMANDS = ("FRC_GetStatus", "FRC_ReadJointAngles")


def _rmi_packet(op: str, arg: int) -> rmi.Packet:
    if op == "r":
        return rmi.Packet("Instruction", "FRC_JointMotionJRep", {"SequenceID": arg, "ErrorID": 0})
    if arg % 3 == 0:
        return rmi.Packet("Communication", "FRC_SystemFault", {"SequenceID": arg})
    if arg % 3 == 1:
        return rmi.Packet("Command", _COMMANDS[arg % 2], {"ErrorID": 0})
    return rmi.Packet("Communication", "FRC_Heartbeat", {})


@settings(max_examples=200, deadline=None)
@given(steps=_steps)
def test_rmi_matches_each_request_at_most_once_and_discards_late_replies(steps):
    session = RmiSession()
    now = 0.0
    answered: set[int] = set()
    gone: set[int] = set()  # requests timed out, faulted or cleared
    held: list[object] = []  # keeps every request seen alive, so no id() is reused
    sent_seqs: list[int] = []
    for op, arg, dt in steps:
        now += dt
        if op == "s":
            if arg % 2 and not session.commands.full:
                session.command(_COMMANDS[arg % 2], now + 1.0)
            elif not arg % 2 and not session.instructions.full:
                sent_seqs.append(session.instruction("FRC_JointMotionJRep", now + 1.0).key)
        elif op in "rg":
            receipt = session.receive(_rmi_packet(op, arg))
            if receipt.kind == "reply":
                assert receipt.request is not None
                assert id(receipt.request) not in answered | gone
                answered.add(id(receipt.request))
                held.append(receipt.request)
            elif op == "r":
                assert receipt.kind == "unmatched"
            held.extend(receipt.failed)
            gone.update(map(id, receipt.failed))
        elif op == "t":
            held.extend(expired := session.timeout(now))
            gone.update(map(id, expired))
        elif op == "c":
            held.extend(cleared := session.clear())
            gone.update(map(id, cleared))
        assert len(session.commands) <= 1
        assert len(session.instructions) <= rmi.MAX_IN_FLIGHT
    assert sent_seqs == list(range(1, len(sent_seqs) + 1))


def test_rmi_late_instruction_reply_after_timeout_is_discarded():
    session = RmiSession()
    req = session.instruction("FRC_JointMotionJRep", deadline=1.0)
    assert session.timeout(0.5) == []
    assert session.timeout(1.0) == [req]
    late = rmi.Packet("Instruction", "FRC_JointMotionJRep", {"SequenceID": req.key})
    assert session.receive(late).kind == "unmatched"


def test_rmi_withdrawn_instruction_gives_its_sequence_id_back():
    session = RmiSession()
    session.resync(41)
    req = session.instruction("FRC_JointMotionJRep", deadline=1.0)
    session.withdraw(req)
    assert session.next_seq == 41 and len(session.instructions) == 0
    session.resync(rmi.MAX_SEQUENCE_ID + 1)
    assert session.next_seq == 1


# --- LTP/1 -------------------------------------------------------------------------------------
_VERBS = ("MEAS", "STOP", "STATUS?")


@settings(max_examples=200, deadline=None)
@given(steps=_steps)
def test_ltp_never_has_two_requests_outstanding_and_settles_in_order(steps):
    session = LtpSession(late_grace_s=1.0)
    now = 0.0
    sent: list[Request[str]] = []
    resolved: set[str] = set()
    for op, arg, dt in steps:
        now += dt
        verb = _VERBS[arg % 3]
        if op == "s":
            if session.owed(verb):
                with pytest.raises(RequestPending):
                    session.send(verb, now + 1.0)
            else:
                sent.append(session.send(verb, now + 1.0))
        elif op in "rg" and sent:
            # A reply to some request ever sent (late, current or long gone), or BUSY.
            tag = sent[arg % len(sent)].key
            reply = ltp.Err(tag, 14, "BUSY") if op == "g" else ltp.Ok(tag)
            before = list(session)
            receipt = session.receive(reply)
            if receipt.request is None:
                assert tag in resolved and list(session) == before
            else:
                assert receipt.request.key == tag and tag not in resolved
                # Exactly the requests sent before it are settled (none if BUSY).
                earlier = before[: before.index(receipt.request)]
                assert list(receipt.lost) == ([] if op == "g" else earlier)
                resolved.update(r.key for r in (receipt.request, *receipt.lost))
        elif op == "t":
            for r in session.timeout(now):
                assert r.late and r.deadline <= now and session.owed_until == now + 1.0
        outstanding = list(session)
        assert len(outstanding) <= 2
        if len(outstanding) == 2:
            assert [r.name for r in outstanding] == ["MEAS", "STOP"]
    assert [int(r.key) for r in sent] == list(range(1, len(sent) + 1))


def test_ltp_late_reply_keeps_the_next_request_waiting_until_it_comes():
    session = LtpSession(late_grace_s=5.0)
    meas = session.send("MEAS", deadline=1.0)
    assert session.timeout(1.0) == [meas] and session.owed_until == 6.0
    with pytest.raises(RequestPending, match="MEAS"):
        session.send("STATUS?", deadline=2.0)
    stop = session.send("STOP", deadline=2.0)  # STOP may join a running MEAS
    receipt = session.receive(ltp.Ok(stop.key))
    assert receipt.request is stop and receipt.lost == (meas,)
    assert session.receive(ltp.Ok(meas.key)).request is None  # discarded late
    assert session.send("STATUS?", deadline=3.0).key == "3"


# --- emScon ------------------------------------------------------------------------------------
_START = int(emscon.Cmd.START_MEASUREMENT)
_OTHER = int(emscon.Cmd.GET_UNITS)


def _emscon_packet(op: str, arg: int) -> emscon.Packet | BadFrame:
    kinds: list[emscon.Packet | BadFrame] = [
        emscon.Reply(_START, 0),
        emscon.Reply(_START, 10004),
        emscon.Reply(_OTHER, 0),
        emscon.SingleMeasResult(),
        emscon.SingleMeasResult2(),
        emscon.ErrorResponse(_START, 37),
        emscon.ErrorResponse(_OTHER, 1),
        emscon.StatusChange(int(emscon.Event.MEAS_STATUS_NOT_READY)),
        emscon.StatusChange(2),
        BadFrame(int(emscon.DataType.SYSTEM_STATUS_CHANGE), 0, ValueError("garbage")),
        BadFrame(int(emscon.DataType.COMMAND), _OTHER, ValueError("garbage")),
    ]
    return kinds[arg % len(kinds)] if op == "r" else kinds[(arg + 5) % len(kinds)]


@settings(max_examples=300, deadline=None)
@given(order=st.sampled_from(["any", "reply_first", "result_first"]), steps=_steps)
def test_emscon_one_command_in_flight_and_consistent_outcomes(order, steps):
    session = EmsconSession(result_order=order, not_ready_grace_s=0.5)
    now = 0.0
    for op, arg, dt in steps:
        now += dt
        x = session.pending
        if op == "s":
            if x is not None and not x.done:
                with pytest.raises(RequestPending):
                    session.send(_START, now + 1.0, measurement=True)
            else:
                session.send(_START if arg % 2 else _OTHER, now + 1.0, measurement=bool(arg % 2))
        elif op in "rg":
            p = _emscon_packet(op, arg)
            was_done = x is None or x.done
            reply_before = None if x is None else x.reply
            result_before = None if x is None else x.result
            try:
                disposition = session.receive(p, now)
            except UnexpectedReply:
                assert x is not None and not was_done
                session.abandon()
                continue
            if was_done:
                assert disposition is not Disposition.ANSWER
            if x is not None and disposition is not Disposition.ANSWER:
                # Nothing but an answer changes what the command has received.
                assert x.reply is reply_before and x.result is result_before
            if isinstance(p, emscon.Reply) and x is not None and p.command != x.command:
                assert disposition is Disposition.STALE
        elif op == "t" and x is not None and not x.done:
            ended = session.timeout(now)
            if now < session_wait_until(x, 0.5):
                assert ended is None and session.pending is x
            else:
                assert ended in ("expired", "not_ready") and session.pending is None
                assert (ended == "not_ready") == (x.not_ready_at is not None and now < x.deadline)
        x = session.pending
        if x is not None:
            assert x.done == (x.failed or (x.reply is not None and (
                not x.measurement or x.reply.status != 0 or x.result is not None)))
            if x.result is not None:
                assert x.measurement


def session_wait_until(x, grace: float) -> float:
    return x.deadline if x.not_ready_at is None else min(x.deadline, x.not_ready_at + grace)


def test_emscon_result_before_reply_refused_when_reply_first():
    session = EmsconSession(result_order="reply_first")
    session.send(_START, 10.0, measurement=True)
    with pytest.raises(UnexpectedReply, match="before the StartMeasurement reply"):
        session.receive(emscon.SingleMeasResult(), 0.0)


def test_emscon_event_25_then_grace_reports_not_ready():
    session = EmsconSession(not_ready_grace_s=0.2)
    x = session.send(_START, 10.0, measurement=True)
    assert session.receive(emscon.Reply(_START, 0), 0.0) is Disposition.ANSWER
    event = emscon.StatusChange(int(emscon.Event.MEAS_STATUS_NOT_READY))
    assert session.receive(event, 1.0) is Disposition.UNSOLICITED
    assert session.wait_until() == pytest.approx(1.2)
    assert session.timeout(1.1) is None
    assert session.timeout(1.2) == "not_ready" and not x.done
    assert session.receive(emscon.SingleMeasResult(), 1.3) is Disposition.STALE
