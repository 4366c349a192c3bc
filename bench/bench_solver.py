"""Benchmark: robocal's own Levenberg-Marquardt solver against ``scipy.optimize.least_squares``.

Same whitened problem, same analytic Jacobian, same free parameters: the virtual LR Mate
200i (``paper`` scenario, planted errors), the ``high-order`` error model (219 parameters,
the identifiable subset from the rank analysis is free), start at the nominal parameters.
scipy gets the residual ``W (y - h(q; x))`` and its Jacobian ``-W dh/dx`` as dense arrays
(MINPACK ``lm`` and ``trf``, both with Jacobian column scaling like the own solver).

The own solver's time includes forming ``J^T J`` chunk by chunk; scipy's includes building
the dense Jacobian. Costs are reported as ``sum r^2`` (scipy's ``cost`` is half of that).
BLAS is limited to one thread, as inside robocal's fits. Best of ``--repeat`` runs.

Run from the repository root::

    .venv/bin/python bench/bench_solver.py [--poses 250,1000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from robocal._core.threads import blas_threads
from robocal.identification._models import high_order_spec
from robocal.identification._solver import Problem, analyse_jacobian, levenberg_marquardt
from robocal.identification._weights import TrackerSigma, whitening
from robocal.kinematics import KinematicModel
from robocal.simulation import VirtualCell

Array = NDArray[np.float64]


def build(n: int, seed: int = 1) -> tuple[Problem, Array, NDArray[np.intp]]:
    """Whitened high-order problem on ``n`` virtual poses, nominal start, identifiable columns."""
    cell = VirtualCell.create("fanuc_lrmate200i", "paper", seed=seed)
    rng = np.random.default_rng(seed)
    q, p, _, _ = cell.simulate(cell.random_joints(n, rng), rng)
    model = KinematicModel(cell.robot, high_order_spec(cell.robot), cell.T_tracker_base)
    prob = Problem(model, q, p, whitening(p, TrackerSigma()))
    x0 = model.nominal_params()
    rows = np.arange(n)
    _, keep, _ = analyse_jacobian(prob, x0, rows, np.arange(model.size), tol=3e-4)
    return prob, x0, np.flatnonzero(keep).astype(np.intp)


def scipy_solve(prob: Problem, x0: Array, free: NDArray[np.intp], method: str
                ) -> tuple[Array, float, int]:
    """``least_squares`` over the free columns; returns x, sum r^2 and Jacobian evaluations."""
    rows = np.arange(prob.n)

    def full(z: Array) -> Array:
        x = x0.copy()
        x[free] = z
        return x

    def fun(z: Array) -> Array:
        return prob.residuals(full(z), rows).ravel()

    def jac(z: Array) -> Array:
        Jw, _ = prob.whitened_jacobian(full(z), rows, free)
        return -Jw

    res = least_squares(fun, x0[free], jac=jac, method=method, x_scale="jac",
                        ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=2000)
    return full(res.x), 2.0 * float(res.cost), int(res.njev)


def best_of(f: Callable[[], tuple[float, int]], repeat: int) -> tuple[float, float, int]:
    """Best wall time of ``repeat`` calls of ``f`` (returning cost and Jacobian count)."""
    best = np.inf
    cost, njev = np.nan, 0
    for _ in range(repeat):
        t = time.perf_counter()
        cost, njev = f()
        best = min(best, time.perf_counter() - t)
    return best, cost, njev


def compare(n: int, repeat: int) -> None:
    """Print one row per solver for ``n`` poses."""
    prob, x0, free = build(n)
    rows = np.arange(n)

    def own() -> tuple[float, int]:
        prob.n_jacobians = 0
        info = levenberg_marquardt(prob, x0, free, rows, max_iter=200)
        assert info.converged, info.message
        return info.cost, prob.n_jacobians

    def scipy_run(method: str) -> Callable[[], tuple[float, int]]:
        def run() -> tuple[float, int]:
            _, c, njev = scipy_solve(prob, x0, free, method)
            return c, njev
        return run

    runs = {"robocal LM": own, "scipy lm": scipy_run("lm"), "scipy trf": scipy_run("trf")}
    for label, f in runs.items():
        secs, cost, njev = best_of(f, repeat)
        print(f"{n:6d} {len(free):5d} {label:18s}{secs:10.3f}{cost:16.6f}{njev:11d}",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", default="250,1000", help="comma-separated pose counts")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"{'poses':>6s} {'free':>5s} {'solver':18s}{'time [s]':>10s}{'cost sum r^2':>16s}"
          f"{'Jacobians':>11s}")
    with blas_threads(1):
        for n in (int(s) for s in args.poses.split(",")):
            compare(n, args.repeat)


if __name__ == "__main__":
    main()
