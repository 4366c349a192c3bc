"""Error-model structure: which basis functions act on which joint error component.

Per joint i a 6-DoF error transform ``E_i(q) = Tx(dx) Ty(dy) Tz(dz) Rx(ex) Ry(ey) Rz(ez)`` sits
right after the joint rotation. Each component is a linear combination of basis functions:

``const``        1
``poly:k``       Legendre polynomial P_k of the joint value scaled to [-1, 1] over its range
``cos:k/sin:k``  cos(k q), sin(k q) (output-synchronous harmonics)
``swcos:m/swsin:m``  cos(m N q), sin(m N q), N the joint's gear ratio (strain-wave ripple)
``map:j``        periodic cubic B-spline over the joint angle, knot j (joint-angle error map;
                 rotation about the joint axis, ``ez``, only)
``gravity``      gravity torque about the joint axis from the nominal masses (N m); the
                 coefficient is the joint compliance in rad/(N m) (``ez`` only)

Besides the joint terms the model has the tracker <- base transform (6: ``base.dx .. base.ez``
applied after a stored reference pose) and the flange -> reflector point (3: ``tool.x, tool.y,
tool.z``). Parameters are SI: metres for translations, radians for rotations.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from robocal.errors import ConfigError

COMPONENTS = ("dx", "dy", "dz", "ex", "ey", "ez")
FAMILIES = ("const", "poly", "cos", "sin", "swcos", "swsin", "map", "gravity")


@dataclass(frozen=True, order=True)
class Term:
    """One basis function acting on one error component of one joint (0-based ``joint``)."""

    joint: int
    component: str
    family: str
    index: int = 0

    @property
    def name(self) -> str:
        """Parameter name, e.g. ``j2.ez.cos3``, ``j1.dx.const``, ``j4.ez.map017``."""
        if self.family in ("const", "gravity"):
            tail = self.family
        elif self.family == "map":
            tail = f"map{self.index:03d}"
        else:
            tail = f"{self.family}{self.index}"
        return f"j{self.joint + 1}.{self.component}.{tail}"

    @property
    def unit(self) -> str:
        """SI unit of the coefficient."""
        if self.family == "gravity":
            return "rad/(N m)"
        return "m" if self.component.startswith("d") else "rad"

    @classmethod
    def parse(cls, name: str) -> Term:
        """Inverse of :attr:`name`."""
        try:
            j, comp, tail = name.split(".")
            joint = int(j[1:]) - 1
            if tail in ("const", "gravity"):
                return cls(joint, comp, tail, 0)
            if tail.startswith("map"):
                return cls(joint, comp, "map", int(tail[3:]))
            fam = tail.rstrip("0123456789")
            return cls(joint, comp, fam, int(tail[len(fam):]))
        except (ValueError, IndexError) as err:
            raise ConfigError(f"not a parameter name: {name!r}") from err


BASE_NAMES = ("base.dx", "base.dy", "base.dz", "base.ex", "base.ey", "base.ez")
TOOL_NAMES = ("tool.x", "tool.y", "tool.z")


@dataclass(frozen=True)
class ErrorModelSpec:
    """The ordered list of joint error terms plus per-joint map resolutions.

    ``map_knots[i]`` is the number of uniformly spaced knots of joint i's periodic angle map
    over one revolution (0 = no map).
    """

    dof: int
    terms: tuple[Term, ...]
    map_knots: tuple[int, ...] = ()
    label: str = "custom"

    def __post_init__(self) -> None:
        knots = self.map_knots or (0,) * self.dof
        object.__setattr__(self, "map_knots", tuple(knots))
        if len(self.map_knots) != self.dof:
            raise ConfigError(f"map_knots needs {self.dof} entries")
        if any(k != 0 and k < 8 for k in self.map_knots):
            raise ConfigError("a joint-angle map needs at least 8 knots per revolution")
        seen = set()
        for t in self.terms:
            if not 0 <= t.joint < self.dof:
                raise ConfigError(f"term {t.name}: joint out of range 1..{self.dof}")
            if t.component not in COMPONENTS:
                raise ConfigError(f"term {t.name}: unknown component {t.component!r}")
            if t.family not in FAMILIES:
                raise ConfigError(f"term {t.name}: unknown family {t.family!r}")
            if t.family in ("map", "gravity") and t.component != "ez":
                raise ConfigError(f"term {t.name}: {t.family} terms act on ez only")
            if t.family == "map" and not 0 <= t.index < self.map_knots[t.joint]:
                raise ConfigError(f"term {t.name}: map index outside "
                                  f"0..{self.map_knots[t.joint] - 1}")
            if t.family in ("poly", "cos", "sin", "swcos", "swsin") and t.index < 1:
                raise ConfigError(f"term {t.name}: order must be >= 1")
            if t in seen:
                raise ConfigError(f"term {t.name} appears twice")
            seen.add(t)

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names of the joint terms, in order."""
        return tuple(t.name for t in self.terms)

    def __len__(self) -> int:
        return len(self.terms)

    # -- builders ---------------------------------------------------------------------------
    @classmethod
    def build(
        cls,
        dof: int,
        *,
        constant: bool = True,
        poly: int | Sequence[int] = 0,
        fourier: int | Sequence[int] = 0,
        fourier_components: Iterable[str] = COMPONENTS,
        strain_wave: Sequence[int] = (),
        gear_ratios: Sequence[float | None] = (),
        map_spacing_deg: float | Sequence[float | None] | None = None,
        gravity: bool | Sequence[bool] = False,
        label: str = "custom",
    ) -> ErrorModelSpec:
        """Build a spec with the same structure on every joint (per-joint sequences allowed).

        ``poly`` / ``fourier``: highest order per joint. ``strain_wave``: multiples m of the
        gear ratio, used on ``ez`` of joints whose ratio is known. ``map_spacing_deg``: knot
        spacing of the joint-angle map (None = no map).
        """

        def per_joint(v: Any, default: Any) -> list[Any]:
            if isinstance(v, list | tuple):
                if len(v) != dof:
                    raise ConfigError(f"per-joint setting needs {dof} entries, got {len(v)}")
                return list(v)
            return [default if v is None else v] * dof

        polys = per_joint(poly, 0)
        fours = per_joint(fourier, 0)
        maps = per_joint(map_spacing_deg, None)
        gravs = per_joint(gravity, False)
        fcomps = tuple(fourier_components)
        terms: list[Term] = []
        knots: list[int] = []
        for j in range(dof):
            for c in COMPONENTS:
                if constant:
                    terms.append(Term(j, c, "const"))
                for k in range(1, int(polys[j]) + 1):
                    terms.append(Term(j, c, "poly", k))
                if c in fcomps:
                    for k in range(1, int(fours[j]) + 1):
                        terms.append(Term(j, c, "cos", k))
                        terms.append(Term(j, c, "sin", k))
            gr = gear_ratios[j] if j < len(gear_ratios) else None
            if gr:
                for m in strain_wave:
                    terms.append(Term(j, "ez", "swcos", int(m)))
                    terms.append(Term(j, "ez", "swsin", int(m)))
            n_knots = 0
            if maps[j]:
                n_knots = max(8, round(360.0 / float(maps[j])))
                terms.extend(Term(j, "ez", "map", i) for i in range(n_knots))
            knots.append(n_knots)
            if gravs[j]:
                terms.append(Term(j, "ez", "gravity"))
        return cls(dof=dof, terms=tuple(terms), map_knots=tuple(knots), label=label)

    @classmethod
    def constant(cls, dof: int) -> ErrorModelSpec:
        """The traditional model: a constant 6-DoF error per joint."""
        return cls.build(dof, label="constant")

    def with_terms(self, extra: Iterable[Term], *, map_knots: Mapping[int, int] | None = None,
                   label: str | None = None) -> ErrorModelSpec:
        """Return a spec with ``extra`` terms appended (duplicates skipped)."""
        have = set(self.terms)
        knots = list(self.map_knots)
        for j, k in (map_knots or {}).items():
            knots[j] = k
        new = [*self.terms, *(t for t in extra if t not in have)]
        return ErrorModelSpec(self.dof, tuple(new), tuple(knots), label or self.label)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form."""
        return {"dof": self.dof, "label": self.label, "map_knots": list(self.map_knots),
                "terms": [t.name for t in self.terms]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ErrorModelSpec:
        """Inverse of :meth:`to_dict`."""
        try:
            return cls(dof=int(d["dof"]), terms=tuple(Term.parse(n) for n in d["terms"]),
                       map_knots=tuple(int(k) for k in d.get("map_knots", ())),
                       label=str(d.get("label", "custom")))
        except (KeyError, TypeError) as err:
            raise ConfigError(f"invalid error-model description: {err}") from err


def map_spacing_deg(n_knots: int) -> float:
    """Knot spacing in degrees of a map with ``n_knots`` knots per revolution."""
    return 360.0 / n_knots if n_knots else math.inf


@dataclass(frozen=True)
class ParameterLayout:
    """Names, units and typical magnitudes of the full parameter vector.

    Order: base (6), tool (3), joint terms (in spec order).
    """

    spec: ErrorModelSpec
    names: tuple[str, ...] = field(init=False)
    units: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        names = BASE_NAMES + TOOL_NAMES + self.spec.names
        units = ("m", "m", "m", "rad", "rad", "rad", "m", "m", "m",
                 *(t.unit for t in self.spec.terms))
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "units", units)

    @property
    def size(self) -> int:
        """Total number of parameters."""
        return len(self.names)

    N_BASE = 6
    N_TOOL = 3
    OFFSET = 9
    #: Parts of the parameter vector: the tracker <- base correction (tx, ty, tz m, rx, ry,
    #: rz rad), the tool (reflector) offset in the flange frame (m), the joint terms (term k
    #: of the spec is at ``OFFSET + k``).
    BASE = slice(0, N_BASE)
    TOOL = slice(N_BASE, N_BASE + N_TOOL)
    TERMS = slice(OFFSET, None)
