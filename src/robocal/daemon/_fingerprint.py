"""The controller's own calibration around a campaign and a push (ADR 0033).

At campaign start the robot driver reads what the controller already applies of its own
calibration (:class:`robocal.drivers.ControllerCalibrationReadable`); the reading, its
fingerprint and whether a vendor absolute-accuracy option is active are kept per campaign (a
table of this module in the daemon's store), shown in the campaign status and written into
the ``data.controller_calibration`` section of the campaign's MODEL.json files. A driver
whose interface shows nothing is recorded ``unavailable`` with the reason.

Before a push the controller is read again. The push is refused, unless forced, when the
fingerprint differs from the campaign's (the fitted model describes a robot the controller
no longer computes with) or when a vendor absolute-accuracy option is active (robocal's
compensation would be stacked on the vendor's). Every check is audited.
"""

from __future__ import annotations

import json
from typing import Any

import structlog

from robocal.daemon.hub import DriverHub
from robocal.daemon.store import Store, now_iso
from robocal.drivers import ControllerCalibration, ControllerCalibrationReadable
from robocal.errors import CompensationError

__all__ = ["campaign_calibration", "check_push", "model_data", "record_campaign_start"]

_log = structlog.get_logger(__name__)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS controller_calibrations(
    campaign TEXT PRIMARY KEY REFERENCES campaigns(id),
    read_at TEXT NOT NULL,
    state TEXT NOT NULL CHECK(state IN ('read', 'unavailable')),
    fingerprint TEXT,
    absolute_accuracy INTEGER,
    source TEXT,
    facts TEXT NOT NULL DEFAULT '{}',
    reason TEXT NOT NULL DEFAULT ''
)
"""


async def _read(hub: DriverHub) -> ControllerCalibration | str:
    """The controller's calibration now, or why the driver cannot say.

    Raises
    ------
    ConnectFailed
        The robot does not answer (the hub is reset).
    """
    async def read(robot: object) -> ControllerCalibration | str:
        if not isinstance(robot, ControllerCalibrationReadable):
            return (f"the {hub.config.robot.kind} driver's interface does not show the "
                    "controller's own calibration")
        return await robot.controller_calibration()

    return await hub.read_robot(read, what="the controller's own calibration",
                                short="controller calibration")


def _summary(now: ControllerCalibration | str, read_at: str) -> dict[str, Any]:
    if isinstance(now, str):
        return {"state": "unavailable", "read_at": read_at, "fingerprint": None,
                "absolute_accuracy": None, "source": None, "facts": {}, "reason": now}
    return {"state": "read", "read_at": read_at, **now.to_json(), "reason": ""}


async def record_campaign_start(hub: DriverHub, store: Store, cid: str, *,
                                actor: str) -> dict[str, Any]:
    """Read the controller's calibration and keep it as campaign ``cid``'s (audited).

    Raises
    ------
    ConnectFailed
        The robot does not answer; nothing is recorded.
    """
    rec = _summary(await _read(hub), now_iso())
    with store.transaction() as db:
        db.execute(_SCHEMA)
        db.execute(
            "INSERT OR REPLACE INTO controller_calibrations(campaign, read_at, state, "
            "fingerprint, absolute_accuracy, source, facts, reason) VALUES(?,?,?,?,?,?,?,?)",
            (cid, rec["read_at"], rec["state"], rec["fingerprint"],
             None if rec["absolute_accuracy"] is None else int(rec["absolute_accuracy"]),
             rec["source"], json.dumps(rec["facts"], sort_keys=True), rec["reason"]))
    store.audit(actor=actor, action="controller.calibration-read", campaign=cid,
                detail={k: v for k, v in rec.items() if k != "facts"})
    _log.info("controller calibration", campaign=cid, state=rec["state"],
              fingerprint=rec["fingerprint"], absolute_accuracy=rec["absolute_accuracy"])
    return rec


def campaign_calibration(store: Store, cid: str) -> dict[str, Any] | None:
    """What campaign ``cid`` recorded at its start (None: started before it was recorded)."""
    store.db.execute(_SCHEMA)
    row = store.db.execute("SELECT * FROM controller_calibrations WHERE campaign=?",
                           (cid,)).fetchone()
    if row is None:
        return None
    aa = row["absolute_accuracy"]
    return {"state": row["state"], "read_at": row["read_at"], "fingerprint": row["fingerprint"],
            "absolute_accuracy": None if aa is None else bool(aa), "source": row["source"],
            "facts": json.loads(row["facts"]), "reason": row["reason"]}


def model_data(store: Store, cid: str) -> dict[str, Any]:
    """The ``data`` entries the campaign's MODEL.json files carry (none if not recorded)."""
    rec = campaign_calibration(store, cid)
    return {} if rec is None else {"controller_calibration": rec}


def _changed(before: dict[str, Any], after: dict[str, Any]) -> list[str]:
    return sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))


async def check_push(hub: DriverHub, store: Store, cid: str, *, force: bool,
                     actor: str) -> dict[str, Any]:
    """Read the controller again before pushing campaign ``cid``'s table; refuse (unless
    ``force``) a changed fingerprint or an active vendor absolute-accuracy option.

    Returns the check as audited (``controller.calibration-checked``).

    Raises
    ------
    CompensationError
        Refused (audited as ``compensation.push-refused``); nothing written.
    ConnectFailed
        The robot does not answer; nothing written.
    """
    then = campaign_calibration(store, cid)
    now = _summary(await _read(hub), now_iso())
    refusals: list[str] = []
    if then is not None and then["state"] == "read":
        if now["state"] != "read":
            refusals.append(f"the controller's own calibration cannot be read now "
                            f"({now['reason']}), campaign {cid} measured under fingerprint "
                            f"{then['fingerprint']}")
        elif now["fingerprint"] != then["fingerprint"]:
            what = ", ".join(_changed(then["facts"], now["facts"])) or now["source"]
            refusals.append(
                f"the controller's own calibration changed since campaign {cid} started "
                f"(fingerprint {then['fingerprint']} then, {now['fingerprint']} now; changed: "
                f"{what}): the fitted model describes the robot as the controller computed it "
                "then; measure a new campaign")
    if now["absolute_accuracy"]:
        refusals.append(f"a vendor absolute-accuracy option is active on the controller "
                        f"({now['source']}): robocal's compensation would be stacked on the "
                        "vendor's; switch it off and measure again, or force")
    detail = {"campaign_fingerprint": None if then is None else then["fingerprint"],
              "controller_fingerprint": now["fingerprint"], "state": now["state"],
              "absolute_accuracy": now["absolute_accuracy"], "source": now["source"],
              "refusals": refusals, "forced": bool(refusals) and force}
    if refusals and not force:
        store.audit(actor=actor, action="compensation.push-refused", campaign=cid,
                    detail={"refusal": "; ".join(refusals), "controller_calibration": detail})
        raise CompensationError("push refused: " + "; ".join(refusals) + ". Nothing written; "
                                "an operator may force it (recorded in the audit log)")
    store.audit(actor=actor, action="controller.calibration-checked", campaign=cid,
                detail=detail)
    if refusals:
        _log.warning("push forced over the controller calibration check", campaign=cid,
                     refusals=refusals, actor=actor)
    return detail
