"""Run inside ``unshare -rm``: a 4 MiB tmpfs as the daemon's data directory, filled to the
last byte while a campaign measures; prints a JSON summary for test_storage_faults.py."""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from tests.unit.daemon.conftest import base_config, random_plan


async def _until(cond, timeout: float) -> None:  # type: ignore[no-untyped-def]
    async with asyncio.timeout(timeout):
        while not cond():
            await asyncio.sleep(0.01)


async def main(work: Path) -> dict[str, object]:
    state = work / "state"
    state.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(state)], check=True)
    cfg = parse_config(base_config(work))
    svc = CalibrationService(cfg)
    await svc.start()
    out: dict[str, object] = {}
    try:
        cid = (await svc.create(random_plan(30, validation=4), actor="op"))["id"]
        await _until(lambda: len(svc.store.measured_indices(cid)) >= 4, 60)
        filler = state / "filler"
        with contextlib.suppress(OSError), open(filler, "wb", buffering=0) as fh:
            while True:  # every last block of the filesystem
                fh.write(b"\0" * 4096)
        await _until(lambda: svc.store.campaign(cid).state == "paused", 60)
        rec = svc.store.campaign(cid)
        out["paused_reason"] = rec.reason
        out["measured_at_pause"] = sorted(svc.store.measured_indices(cid))
        out["health"] = svc.health()["status"]
        filler.unlink()  # space is back
        await _until(lambda: not svc.store.pending, 10)
        with contextlib.closing(__import__("sqlite3").connect(cfg.db_path)) as db:
            out["state_on_disk"] = db.execute("SELECT state FROM campaigns WHERE id=?",
                                              (cid,)).fetchone()[0]
        await svc.resume(cid, actor="op")
        st = await svc.wait(cid, ["fitted"], timeout=120)
        out["final_state"] = st["state"]
        rows = [r.pose_idx for r in svc.store.measurements(cid)]
        out["measured"] = len(rows)
        out["distinct"] = len(set(rows))
        out["integrity"] = svc.store.db.execute("PRAGMA integrity_check").fetchone()[0]
    finally:
        await svc.stop()
        subprocess.run(["umount", str(state)], check=False)
    return out


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as d:
        summary = asyncio.run(main(Path(d)))
    sys.stdout.write("SUMMARY " + json.dumps(summary) + "\n")
