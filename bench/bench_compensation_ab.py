"""Benchmark: compensation of 10,000 targets, this checkout against another one (issue 28).

Both runs use the same saved model and targets: the reference checkout (``--against SRC``,
its ``src`` directory, e.g. an ``git archive`` of an earlier commit) fits the ``paper``
model of bench_compensation.py, saves MODEL.json, the targets and its solutions; this
checkout loads them, times :func:`robocal.compensation.compensate` (CPU, best of 3) and
reports the largest difference of the solutions (joints, and the model's reflector position
at them). Acceptance: <= 30 us per target with the same solutions to 1e-9 mm.

Run from the repository root::

    .venv/bin/python bench/bench_compensation_ab.py --against /tmp/old/src
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(work: Path, role: str) -> None:
    import numpy as np

    from robocal.compensation import compensate
    from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel

    if role == "reference":
        sys.path.insert(0, str(ROOT))
        from tests.unit.compensation._helpers import fitted_model

        cell, cal = fitted_model("fanuc_lrmate200i", "paper", 7)
        cal.save(work / "MODEL.json")
        rng = np.random.default_rng(2024)
        cov = cal.coverage if cal.coverage is not None else cell.robot.joint_limits
        q = rng.uniform(cov[:, 0] + 0.05, cov[:, 1] - 0.05, (10_000, cell.robot.dof))
        nom = KinematicModel(cell.robot, ErrorModelSpec(cell.robot.dof, ()),
                             cell.T_tracker_base)
        xn = nom.nominal_params()
        xn[6:9] = cell.truth_params[6:9]
        np.savez(work / "targets.npz", q=q, p=nom.positions(q, xn))
    cal = CalibratedModel.load(work / "MODEL.json")
    t = np.load(work / "targets.npz")
    compensate(cal, t["p"][:200], t["q"][:200])                    # warm-up
    best = float("inf")
    for _ in range(3):
        c0 = time.process_time()
        res = compensate(cal, t["p"], t["q"])
        best = min(best, time.process_time() - c0)
    n = len(t["q"])
    print(f"{role:9s}: cpu {best:.3f} s, {best / n * 1e6:.1f} us/target, {res.counts()}")
    if role == "reference":
        np.save(work / "q_ref.npy", res.q)
        return
    q_ref = np.load(work / "q_ref.npy")
    ok = ~np.isnan(q_ref).any(axis=1)
    same = bool(np.array_equal(ok, ~np.isnan(res.q).any(axis=1)))
    dq = float(np.abs(q_ref[ok] - res.q[ok]).max())
    dp = float(np.linalg.norm(cal.predict(q_ref[ok]) - cal.predict(res.q[ok]), axis=1).max())
    print(f"same status: {same}; largest joint difference {dq:.2e} rad; largest difference "
          f"of the predicted reflector positions {dp * 1e3:.2e} mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", help="src directory of the reference checkout")
    ap.add_argument("--role", choices=("reference", "this"), help=argparse.SUPPRESS)
    ap.add_argument("--work", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.role is not None:
        _run(Path(a.work), a.role)
        return
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _machine import header

    print(header())
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        ref_env = dict(env, PYTHONPATH=os.pathsep.join([a.against, str(ROOT)]))
        subprocess.run([sys.executable, __file__, "--role", "reference", "--work", tmp],
                       env=ref_env, check=True)
        subprocess.run([sys.executable, __file__, "--role", "this", "--work", tmp], env=env,
                       check=True)


if __name__ == "__main__":
    main()
