"""Planted warm-up drift of the virtual robot: joints heat while moving, links grow with heat.

Each joint's temperature follows a first-order lag (time constant ``tau_s``, about 10 min)
toward ``ambient_c + rise_c[j]`` while the robot moves and toward ``ambient_c +
holding * rise_c[j]`` while it stands powered (motors holding the arm against gravity).
Link j grows along its dominant DH length (``a_j`` through the ``dx`` error component, else
``d_j`` through ``dz``) by ``growth_m_per_c[j]`` per °C of joint j above ambient. Time is
simulated: the world advances it by each move's duration and each measurement's dwell, never
by the wall clock, so a 30 min warm-up runs in milliseconds.

Kept apart from the other planted errors: it changes nothing of a cell built without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.thermal import thermal_components
from robocal.kinematics import KinematicModel, ParameterLayout, RobotDescription, Term

__all__ = ["WarmUpDrift"]

Array = NDArray[np.float64]


@dataclass
class WarmUpDrift:
    """First-order joint heating and linear link growth (the planted thermal truth).

    ``rise_c`` (dof,) °C steady-state rise while moving; ``growth_m_per_c`` (dof,) m/°C;
    ``temps_c`` (dof,) the current joint temperatures; ``time_s`` simulated seconds.
    """

    ambient_c: float
    rise_c: Array
    tau_s: float
    growth_m_per_c: Array
    temps_c: Array
    time_s: float = 0.0
    holding: float = 0.5
    _chain: tuple[KinematicModel, Array, NDArray[np.intp]] | None = field(default=None,
                                                                    repr=False)

    @classmethod
    def planted(cls, robot: RobotDescription, *, drift_m: float = 1e-4, over_s: float = 1800.0,
                tau_s: float = 600.0, ambient_c: float = 20.0) -> WarmUpDrift:
        """A drift whose links grow by ``drift_m`` in all (sum of |growth|) after ``over_s``
        of continuous motion from cold; growth per link proportional to its length."""
        dof = robot.dof
        rise = np.linspace(12.0, 6.0, dof)  # base joints carry more load: they warm more
        lengths = np.array([max(abs(j.a), abs(j.d)) for j in robot.joints], dtype=float)
        heated = rise * (1.0 - math.exp(-over_s / tau_s))
        alpha = drift_m / max(float(lengths @ heated), 1e-12)
        return cls(ambient_c=ambient_c, rise_c=rise, tau_s=tau_s,
                   growth_m_per_c=alpha * lengths, temps_c=np.full(dof, ambient_c))

    def advance(self, seconds: float, *, moving: bool) -> None:
        """Let ``seconds`` of simulated time pass, the robot moving or standing."""
        if seconds <= 0:
            return
        target = self.ambient_c + self.rise_c * (1.0 if moving else self.holding)
        self.temps_c = target + (self.temps_c - target) * math.exp(-seconds / self.tau_s)
        self.time_s += seconds

    def growth_m(self, temps_c: Array) -> Array:
        """Link length changes (..., dof) m at joint temperatures ``temps_c`` (..., dof) °C."""
        return self.growth_m_per_c * (np.asarray(temps_c, dtype=float) - self.ambient_c)

    def _model(self, cell: Any) -> tuple[KinematicModel, Array, NDArray[np.intp]]:
        """The truth model with a constant length term on every link, its parameters and
        the indices of those terms (built once)."""
        if self._chain is None:
            truth: KinematicModel = cell.truth_model
            comps = thermal_components(cell.robot.joints)
            extra = [Term(j, c, "const") for j, c in enumerate(comps)]
            model = truth.with_spec(truth.spec.with_terms(extra))
            x = truth.transfer(np.asarray(cell.truth_params, dtype=float), model)
            names = {n: i for i, n in enumerate(model.names)}
            idx = np.array([names[t.name] for t in extra], dtype=np.intp)
            assert idx.min() >= ParameterLayout.OFFSET
            self._chain = (model, x, idx)
        return self._chain

    def positions(self, cell: Any, q: Array, temps_c: Array) -> Array:
        """True reflector positions (n, 3) m of ``cell`` at joints ``q`` (n, dof) and joint
        temperatures ``temps_c`` (dof,) or (n, dof) °C."""
        model, x0, idx = self._model(cell)
        q = np.atleast_2d(np.asarray(q, dtype=float))
        temps = np.broadcast_to(np.asarray(temps_c, dtype=float), q.shape)
        out = np.empty((q.shape[0], 3))
        keys, inverse = np.unique(temps, axis=0, return_inverse=True)
        for k, t in enumerate(keys):
            rows = np.flatnonzero(inverse.ravel() == k)
            x = x0.copy()
            x[idx] += self.growth_m(t)
            out[rows] = model.positions(q[rows], x)
        return out
