"""Real SIGSTOP/SIGCONT: the process stands still while the reply arrives, longer than the
request timeout; once continued, the request succeeds with that reply (issue 25, item 7).

The peer is a scripted LTP/1 bridge in a child process. On the chosen request it stops this
process, sends the reply, waits past the timeout and continues it (always, in ``finally``).
``tests/unit/drivers/test_stalled_loop.py`` reproduces the same stall deterministically for
every driver.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys

from robocal.drivers.ltp import LtpTracker

PEER = r"""
import os, signal, socket, sys, time
victim, stall, stop_on, skip = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3], int(sys.argv[4])
answers = {
    "HELLO": "OK proto=LTP/1 vendor=script model=SIG serial=1 fw=1 bridge=script",
    "STATUS?": "OK ready=1 beam=LOCKED init=1 smr=RRR15 units=mm frame=tracker",
    "SMR": "OK type=RRR15 offset_mm=0.000", "UNITS": "OK len=mm ang=deg",
    "FRAME": "OK name=tracker", "STOP": "OK", "BYE": "OK",
    "MEAS": "OK id=P1 x=1000 y=2000 z=-500 n=1",
}
srv = socket.create_server(("127.0.0.1", 0))
print(srv.getsockname()[1], flush=True)
srv.settimeout(20)
conn, _ = srv.accept()
conn.settimeout(20)
buf, stopped, seen = b"", 0, 0
while True:
    data = conn.recv(4096)
    if not data:
        break
    buf += data
    while b"\r\n" in buf:
        line, buf = buf.split(b"\r\n", 1)
        tag, verb = line.decode().split(" ")[:2]
        reply = f"{tag} {answers[verb]}\r\n".encode()
        seen += verb == stop_on
        if verb == stop_on and seen > skip and stopped < 2:
            stopped += 1
            os.kill(victim, signal.SIGSTOP)
            try:
                conn.sendall(reply)
                time.sleep(stall)
            finally:
                os.kill(victim, signal.SIGCONT)
            print("stalled", flush=True)
        else:
            conn.sendall(reply)
"""


async def _run(stop_on: str) -> None:
    skip = 2 if stop_on == "STATUS?" else 0  # connecting asks STATUS? twice
    peer = subprocess.Popen([sys.executable, "-c", PEER, str(os.getpid()), "0.5", stop_on,
                             str(skip)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert peer.stdout is not None
        port = int(peer.stdout.readline())
        t = LtpTracker({"url": f"tcp://127.0.0.1:{port}", "request_timeout_s": 0.2,
                        "reply_margin_s": 0.0})
        await t.connect(timeout=5)
        try:
            for _ in range(2):  # stopped on two requests in a row
                if stop_on == "MEAS":
                    reading = await t.measure(samples=1, timeout=0.2, point_id="P1")
                    assert reading.position_m[0] == 1.0
                else:
                    assert (await t.status())["ready"] == "1"
        finally:
            await t.close()
        assert peer.stdout.readline().strip() == "stalled"
    finally:
        peer.kill()
        peer.wait(10)
        if peer.stdout is not None:
            peer.stdout.close()


async def test_status_reply_that_arrived_while_stopped_is_taken() -> None:
    await asyncio.wait_for(_run("STATUS?"), 20)


async def test_measurement_reply_that_arrived_while_stopped_is_taken() -> None:
    await asyncio.wait_for(_run("MEAS"), 20)
