"""Which error component a link's thermal growth acts on (shared by identification's thermal
term and the simulator's planted warm-up drift, ADR 0042)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol

__all__ = ["TEMPERATURE_RANGE_C", "thermal_components"]

#: Joint temperatures (°C) a compensation may be asked for (ADR 0054).
TEMPERATURE_RANGE_C = (-40.0, 150.0)


class _Joint(Protocol):
    @property
    def a(self) -> float: ...

    @property
    def d(self) -> float: ...


def thermal_components(joints: Iterable[_Joint]) -> tuple[str, ...]:
    """Per joint, the error component along its link's dominant DH length: ``dx`` (along
    ``a``) when ``|a| >= |d|``, else ``dz`` (along ``d``)."""
    return tuple("dx" if abs(j.a) >= abs(j.d) else "dz" for j in joints)
