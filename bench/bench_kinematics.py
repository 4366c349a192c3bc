"""Benchmark: forward kinematics and the full parameter Jacobian, 10,000 poses, ~300 parameters.

The model is the LR Mate 200i with a rich joint-dependent structure: per joint and error
component a constant, a linear (Legendre) term and Fourier harmonics 1-3, plus strain-wave
ripple (m = 1, 2) on the joint rotation: 321 parameters. Also timed: the whitened normal
equations as identification accumulates them (chunks of 2,048 poses).

Run from the repository root::

    /work/venv/bin/python bench/bench_kinematics.py [--n 10000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from robocal._core.threads import blas_threads
from robocal.identification import TrackerSigma, whitening
from robocal.identification._solver import Problem
from robocal.kinematics import ErrorModelSpec, KinematicModel, load_robot


def _best(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    robot = load_robot("fanuc_lrmate200i")
    spec = ErrorModelSpec.build(6, poly=1, fourier=3, strain_wave=(1, 2),
                                gear_ratios=robot.gear_ratios)
    model = KinematicModel(robot, spec)
    rng = np.random.default_rng(0)
    lim = robot.joint_limits
    q = rng.uniform(lim[:, 0], lim[:, 1], (args.n, 6))
    x = model.nominal_params() + rng.normal(0, 1e-5, model.size)
    p = model.positions(q, x)
    W = whitening(p + np.array([1.5, 0.0, 0.0]), TrackerSigma())  # tracker 1.5 m in front
    prob = Problem(model, q, p + rng.normal(0, 1e-5, p.shape), W)
    rows = np.arange(args.n)
    cols = np.arange(model.size)
    with blas_threads(1):
        t_fk = _best(lambda: model.positions(q, x), args.repeat)
        t_jac = _best(lambda: model.jacobian(q, x), args.repeat)
        t_jj = _best(lambda: model.joint_jacobian(q, x), args.repeat)
        t_ne = _best(lambda: prob.normal_equations(x, rows, cols), args.repeat)
    n = args.n
    print(f"robot {robot.name}, {model.size} parameters, {n} poses "
          f"(best of {args.repeat}, single-threaded BLAS)")
    print(f"{'operation':44s}{'total [s]':>12s}{'per pose [us]':>16s}")
    for label, t in [("forward kinematics (positions)", t_fk),
                     ("positions + parameter Jacobian (n,3,P)", t_jac),
                     ("joint Jacobian (n,6,dof)", t_jj),
                     ("whitened normal equations J^T J, J^T r", t_ne)]:
        print(f"{label:44s}{t:12.3f}{t / n * 1e6:16.1f}")


if __name__ == "__main__":
    main()
