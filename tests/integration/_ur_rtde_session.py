"""A realistic ur-rtde session against a UR controller; run as a separate process.

ur-rtde's calls hold the GIL while they block on the socket, so the session cannot share a
process with the asyncio simulator. Usage::

    python _ur_rtde_session.py HOST EXPECTED_Q_JSON

Prints one JSON line per step: ``{"step": ..., "ok": bool, "detail": ...}``.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import dashboard_client
import rtde_control
import rtde_io
import rtde_receive

HOST = sys.argv[1]
EXPECTED_Q = json.loads(sys.argv[2])


def step(name: str, fn: Callable[[], Any], check: Callable[[Any], bool]) -> Any:
    try:
        value = fn()
        ok = bool(check(value))
        detail = repr(value)[:200]
    except Exception as err:
        value, ok, detail = None, False, f"{type(err).__name__}: {err}"
    print(json.dumps({"step": name, "ok": ok, "detail": detail}), flush=True)
    return value


def near(q: list[float]) -> bool:
    """``q`` is the expected pose within 1 mrad per joint."""
    return len(q) == 6 and max(abs(a - b) for a, b in zip(q, EXPECTED_Q, strict=True)) < 1e-3


def until(fn: Callable[[], Any], check: Callable[[Any], bool], timeout: float = 5.0) -> Any:
    """Poll ``fn`` until ``check`` holds (bounded); return the last value."""
    deadline = time.monotonic() + timeout
    value = fn()
    while not check(value) and time.monotonic() < deadline:
        time.sleep(0.01)
        value = fn()
    return value


def becomes(name: str, fn: Callable[[], Any], value: bool) -> Any:
    """A step that polls ``fn`` (bounded) until it returns ``value``."""
    return step(name, lambda: until(fn, lambda v: v is value), lambda v: v is value)


d = dashboard_client.DashboardClient(HOST, 29999, False)
step("dashboard.connect", d.connect, lambda v: d.isConnected())
step("dashboard.polyscopeVersion", d.polyscopeVersion, lambda v: v.startswith("5."))
step("dashboard.isInRemoteControl", d.isInRemoteControl, lambda v: v is True)
step("dashboard.getRobotModel", d.getRobotModel, lambda v: v == "UR10")
step("dashboard.robotmode (off)", d.robotmode, lambda v: v == "Robotmode: POWER_OFF")
step("dashboard.powerOn", d.powerOn, lambda v: True)
step("dashboard.robotmode (idle)", lambda: until(d.robotmode, lambda m: "IDLE" in m),
     lambda v: v == "Robotmode: IDLE")
step("dashboard.brakeRelease", d.brakeRelease, lambda v: True)
step("dashboard.robotmode (running)", lambda: until(d.robotmode, lambda m: "RUNNING" in m),
     lambda v: v == "Robotmode: RUNNING")
step("dashboard.safetystatus", d.safetystatus, lambda v: v == "Safetystatus: NORMAL")
step("dashboard.safetymode", d.safetymode, lambda v: v == "Safetymode: NORMAL")
step("dashboard.loadURP", lambda: d.loadURP("calibration.urp"), lambda v: True)
step("dashboard.getLoadedProgram", d.getLoadedProgram,
     lambda v: v == "Loaded program: /programs/calibration.urp")
step("dashboard.play", d.play, lambda v: True)
step("dashboard.running (playing)", d.running, lambda v: v is True)
step("dashboard.programState (playing)", d.programState,
     lambda v: v.startswith("PLAYING calibration.urp"))
step("dashboard.pause", d.pause, lambda v: True)
step("dashboard.programState (paused)", d.programState, lambda v: v.startswith("PAUSED"))
step("dashboard.stop", d.stop, lambda v: True)
step("dashboard.running (stopped)", d.running, lambda v: v is False)

r = step("rtde_receive.RTDEReceiveInterface", lambda: rtde_receive.RTDEReceiveInterface(HOST),
         lambda v: v.isConnected())
if r is not None:
    step("rtde_receive.getActualQ", r.getActualQ,
         near)
    step("rtde_receive.getTargetQ", r.getTargetQ,
         near)
    step("rtde_receive.getRobotMode", r.getRobotMode, lambda v: v == 7)
    step("rtde_receive.getSafetyMode", r.getSafetyMode, lambda v: v == 1)
    step("rtde_receive.getRuntimeState", r.getRuntimeState, lambda v: v == 1)
    step("rtde_receive.isProtectiveStopped", r.isProtectiveStopped, lambda v: v is False)
    step("rtde_receive.isEmergencyStopped", r.isEmergencyStopped, lambda v: v is False)
    step("rtde_receive.getRobotStatus", r.getRobotStatus, lambda v: v & 1 == 1)
    step("rtde_receive.getOutputIntRegister", lambda: r.getOutputIntRegister(12),
         lambda v: v == 4242)
    step("rtde_receive.getOutputDoubleRegister", lambda: r.getOutputDoubleRegister(12),
         lambda v: v == 2.5)
    step("rtde_receive.getTimestamp", r.getTimestamp, lambda v: v > 0.0)

io = step("rtde_io.RTDEIOInterface", lambda: rtde_io.RTDEIOInterface(HOST),
          lambda v: v.isConnected())
if io is not None and r is not None:
    step("rtde_io.setStandardDigitalOut(3, True)", lambda: io.setStandardDigitalOut(3, True),
         lambda v: v is True)
    step("rtde_receive.getDigitalOutState(3) (on)",
         lambda: until(lambda: r.getDigitalOutState(3), lambda s: s is True),
         lambda v: v is True)
    step("rtde_io.setStandardDigitalOut(3, False)", lambda: io.setStandardDigitalOut(3, False),
         lambda v: v is True)
    step("rtde_receive.getDigitalOutState(3) (off)",
         lambda: until(lambda: r.getDigitalOutState(3), lambda s: s is False),
         lambda v: v is False)
    step("rtde_io.setInputIntRegister(18, 42)", lambda: io.setInputIntRegister(18, 42),
         lambda v: v is True)
    step("rtde_io.setInputDoubleRegister(19, 1.25)",
         lambda: io.setInputDoubleRegister(19, 1.25), lambda v: v is True)
    step("rtde_io.setSpeedSlider(0.5)", lambda: io.setSpeedSlider(0.5), lambda v: v is True)
    step("rtde_receive.getSpeedScaling",
         lambda: until(r.getSpeedScaling, lambda s: abs(s - 0.5) < 1e-9),
         lambda v: abs(v - 0.5) < 1e-9)
    io.disconnect()

# RTDEControlInterface: uploads ur-rtde's control program (port 30003) and commands it through
# RTDE registers; moves run at the speed slider's 50 % set above
Q_A = [v + 0.1 for v in EXPECTED_Q]
Q_B = [v - 0.1 for v in EXPECTED_Q]


def close_to(target: list[float]) -> Callable[[list[float]], bool]:
    return lambda q: len(q) == 6 and max(abs(a - b) for a, b in zip(q, target, strict=True)) < 1e-3


c = step("rtde_control.RTDEControlInterface", lambda: rtde_control.RTDEControlInterface(HOST),
         lambda v: v.isConnected() and v.isProgramRunning())
if c is not None and r is not None:
    step("rtde_control.moveJ (A)", lambda: c.moveJ(Q_A, 1.0, 1.4), lambda v: v is True)
    # the receive interface's own stream may be a cycle behind the control interface's
    step("rtde_receive.getActualQ (at A)", lambda: until(r.getActualQ, close_to(Q_A)),
         close_to(Q_A))
    step("rtde_control.moveJ (B, asynchronous)", lambda: c.moveJ(Q_B, 0.01, 1.4, True),
         lambda v: v is True)
    step("rtde_control.getAsyncOperationProgressEx (running)",
         c.getAsyncOperationProgressEx, lambda v: v.isAsyncOperationRunning())
    step("rtde_control.getAsyncOperationProgressEx (finished)",
         lambda: until(c.getAsyncOperationProgressEx,
                       lambda st: not st.isAsyncOperationRunning(), timeout=10.0),
         lambda v: not v.isAsyncOperationRunning() and v.operationId() >= 1)
    step("rtde_receive.getActualQ (at B)", lambda: until(r.getActualQ, close_to(Q_B)),
         close_to(Q_B))
    step("rtde_control.moveJ (A, asynchronous, slow)", lambda: c.moveJ(Q_A, 0.005, 1.4, True),
         lambda v: v is True)
    time.sleep(0.05)
    step("rtde_control.stopJ", lambda: c.stopJ(2.0), lambda v: True)
    step("rtde_receive.getActualQ (stopped between B and A)", r.getActualQ,
         lambda q: all(b + 1e-4 < x < a - 1e-4 for x, a, b in zip(q, Q_A, Q_B, strict=True)))
    # the controller's kinematics: the receive interface's TCP pose is its forward
    # kinematics; a TCP offset along the flange's z moves the point, not the orientation
    fk = step("rtde_control.getForwardKinematics ()", c.getForwardKinematics,
              lambda p: close_to(p)(until(r.getActualTCPPose, close_to(p))))
    shifted = step("rtde_control.getForwardKinematics (q, tcp 0.1 m along z)",
                   lambda: c.getForwardKinematics(r.getActualQ(), [0, 0, 0.1, 0, 0, 0]),
                   lambda p: fk is not None and abs(math.dist(p[:3], fk[:3]) - 0.1) < 1e-9
                   and math.dist(p[3:], fk[3:]) < 1e-9)
    step("rtde_control.setTcp (0.1 m along z)", lambda: c.setTcp([0, 0, 0.1, 0, 0, 0]),
         lambda v: v is True)
    step("rtde_receive.getActualTCPPose (with the TCP)",
         lambda: until(r.getActualTCPPose, close_to(shifted or [])),
         lambda p: shifted is not None and close_to(shifted)(p))
    step("rtde_control.setTcp (back to the flange)", lambda: c.setTcp([0.0] * 6),
         lambda v: v is True)
    step("rtde_control.setPayload", lambda: c.setPayload(1.5, [0.0, 0.0, 0.05]),
         lambda v: v is True)
    step("rtde_control.isJointsWithinSafetyLimits",
         lambda: (c.isJointsWithinSafetyLimits(Q_A), c.isJointsWithinSafetyLimits([9.0, *Q_A[1:]])),
         lambda v: v == (True, False))
    step("rtde_control.isSteady", c.isSteady, lambda v: v is True)
    step("rtde_control.moveJ (outside the joint limits)",
         lambda: c.moveJ([9.0, *Q_A[1:]], 1.0, 1.4), lambda v: v is False)
    step("rtde_control.isProgramRunning (ended by the error)", c.isProgramRunning,
         lambda v: v is False)
    step("rtde_control.reuploadScript", c.reuploadScript, lambda v: v is True)
    becomes("rtde_control.isProgramRunning (uploaded again)", c.isProgramRunning, True)
    step("rtde_control.triggerProtectiveStop", c.triggerProtectiveStop, lambda v: True)
    becomes("rtde_receive.isProtectiveStopped", r.isProtectiveStopped, True)
    becomes("rtde_control.isProgramRunning (ended by the protective stop)", c.isProgramRunning,
            False)
    step("dashboard.unlockProtectiveStop", d.unlockProtectiveStop, lambda v: True)
    becomes("rtde_receive.isProtectiveStopped (unlocked)", r.isProtectiveStopped, False)
    step("rtde_control.reuploadScript (after the stop)", c.reuploadScript, lambda v: v is True)
    becomes("rtde_control.isProgramRunning (uploaded a third time)", c.isProgramRunning, True)
    step("rtde_control.stopScript", c.stopScript, lambda v: True)
    becomes("rtde_control.isProgramRunning (stopped)", c.isProgramRunning, False)
    step("rtde_receive.getRuntimeState (stopped)",
         lambda: until(r.getRuntimeState, lambda s: s == 1), lambda v: v == 1)
    c.disconnect()
if r is not None:
    r.disconnect()
step("dashboard.powerOff", d.powerOff, lambda v: True)
step("dashboard.robotmode (off again)", d.robotmode, lambda v: v == "Robotmode: POWER_OFF")
d.disconnect()
