"""Verification runs survive any restart (issue 25 item 5, issue 32): the daemon is killed
(kill -9) or stopped (SIGTERM, as ``systemctl restart`` does) right after a push or a rollback
replies; on the next start the re-measurement of the pushed targets is done all the same.

The daemon is a real process against the protocol simulators in another process. The
verification runs are children of their push: never in ``GET /campaigns``, never resumed as
campaigns of their own, found under the push's key.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path
from typing import Any

import pytest
from tests.integration.test_daemon_processes import (
    Daemon,
    simulators,
    small_plan,
    wait_for,
    write_config,
)

EXTRA = """
[limits]
max_joint_correction_deg = 10.0

[compensation]
kind = "targets"
verify_count = 3
"""


def _verification(daemon: Daemon, key: str) -> dict[str, Any] | None:
    for h in daemon.client.request("GET", "/compensation")["history"]:
        if h.get("key") == key:
            return h.get("verification")
    return None


def _stop_now(daemon: Daemon, how: str) -> None:
    """kill -9 or SIGTERM, the instant the reply is in; wait for the process to end."""
    assert daemon.proc is not None
    daemon.proc.send_signal(signal.SIGKILL if how == "kill9" else signal.SIGTERM)
    daemon.proc.wait(60)


def _resumed_as_campaigns(tmp: Path) -> set[str]:
    """Campaign ids every daemon log says it resumed as a campaign after a restart."""
    out = set()
    for log in tmp.glob("daemon-*.log"):
        for line in log.read_text(errors="replace").splitlines():
            if "resuming campaign after restart" in line and line.startswith("{"):
                out.add(json.loads(line).get("campaign"))
    return out


@pytest.mark.slow
def test_verification_runs_survive_kill9_and_sigterm_right_after_push_and_rollback(tmp_path):
    with simulators(tmp_path, time_scale=0.0005) as ports:
        plan = small_plan(tmp_path, count=30, validation=8)
        daemon = Daemon(tmp_path, write_config(tmp_path, ports, extra=EXTRA))
        daemon.start()
        sock = str(tmp_path / "api.sock")
        try:
            cids = []
            for _ in range(2):
                cid = daemon.cli("campaign", "start", "--socket", sock,
                                 "--plan", str(plan)).stdout.strip()
                wait_for(lambda c=cid: daemon.status(c)["state"] in ("fitted", "faulted"),
                         180, f"campaign {cid} fitted")
                assert daemon.status(cid)["state"] == "fitted", daemon.log_tail()
                daemon.client.request("POST", f"/campaigns/{cid}/approve")
                cids.append(cid)
            keys = []
            steps = [("push", cids[0], "kill9"), ("push", cids[1], "sigterm"),
                     ("rollback", None, "sigterm"), ("rollback", None, "kill9")]
            for action, cid, how in steps:
                if action == "push":
                    st = daemon.client.request("POST", f"/campaigns/{cid}/push")
                    key = st["push"]["key"]
                else:
                    comp = daemon.client.request("POST", "/compensation/rollback")
                    key = comp["journal"][-1]["key"]
                    assert comp["journal"][-1]["action"] == "rollback"
                _stop_now(daemon, how)
                daemon.start()
                v = wait_for(lambda k=key: (_verification(daemon, k) or {}).get("state")
                             in ("done", "failed", "skipped") and _verification(daemon, k),
                             180, f"the verification of {action} {key} ({how})")
                assert v["state"] == "done", (action, how, v, daemon.log_tail())
                assert v["after"]["n"] == 3 and v["before"]["n"] == 3
                keys.append(key)
            # children of their push, not campaigns: not listed, not resumed as campaigns
            listed = daemon.client.request("GET", "/campaigns")
            assert [c["id"] for c in listed] == cids
            children = {str(_verification(daemon, k)["campaign"]) for k in keys}
            assert len(children) == 4 and not children & set(cids)
            for child in children:
                assert daemon.status(child)["verifies"] in keys
            assert not children & _resumed_as_campaigns(tmp_path)
        finally:
            daemon.stop()
