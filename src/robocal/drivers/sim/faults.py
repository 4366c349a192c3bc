"""Fault injection settings shared by the simulators."""

from __future__ import annotations

import random
from typing import Generic, TypeVar

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["FaultConfig", "FaultInjector", "RateInjector"]

R = TypeVar("R", bound=BaseModel)

_P = Field(default=0.0, ge=0.0, le=1.0)


class FaultConfig(BaseModel):
    """Probabilities of injected faults (each drawn independently per opportunity).

    Attributes
    ----------
    beam_break_rate, unstable_rate, glitch_rate
        Per tracker ``MEAS``: beam broken (``ERR 10``), stability not reached (``ERR 12``),
        and a wrong-but-OK reading displaced by a few mm (undetectable by the driver).
    garbage_rate
        Per reply line: a line of garbage bytes is sent first (sometimes over-long).
    slow_rate, slow_s
        Per reply: the reply is delayed by ``slow_s`` seconds.
    drop_rate
        Per received request: the simulator closes the connection instead of answering.
    alarm_rate
        Per motion: the controller raises an alarm (RMI: ``FRC_SystemFault`` and HOLD;
        Modbus: ``STATUS=3``, ``ERROR_CODE=MOTION_FAULT``).
    seed
        Seed of the fault generator (independent of the world's noise).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    beam_break_rate: float = _P
    unstable_rate: float = _P
    glitch_rate: float = _P
    garbage_rate: float = _P
    slow_rate: float = _P
    slow_s: float = Field(default=0.2, ge=0.0, le=60.0)
    drop_rate: float = _P
    alarm_rate: float = _P
    seed: int = 0

    @classmethod
    def uniform(cls, rate: float, *, seed: int = 0) -> FaultConfig:
        """Spread a total fault rate: half beam breaks, half unstable, plus light garbage.

        This is what ``robocal sim --fault-rate F`` uses; dropped connections, glitches and
        alarms stay off because a run cannot recover from them without operator action.
        """
        return cls(
            beam_break_rate=rate / 2, unstable_rate=rate / 2, garbage_rate=rate / 5, seed=seed
        )


class RateInjector(Generic[R]):
    """Draw named faults at the rates of a settings model, with its own seeded generator.

    ``fire("x")`` uses the model's ``x_rate`` field; :attr:`rates` may be replaced at any time
    (tests switch faults on and off), :attr:`counts` counts the faults fired by name.
    """

    def __init__(self, rates: R, seed: int) -> None:
        self.rates = rates
        self._rng = random.Random(seed)
        self.counts: dict[str, int] = {}

    def fire(self, name: str) -> bool:
        """Return True (and count it) with probability ``rates.<name>_rate``."""
        rate: float = getattr(self.rates, f"{name}_rate")
        if rate > 0.0 and self._rng.random() < rate:
            self.counts[name] = self.counts.get(name, 0) + 1
            return True
        return False


class FaultInjector(RateInjector[FaultConfig]):
    """Draw the shared faults of a :class:`FaultConfig`, seeded with its ``seed``."""

    def __init__(self, config: FaultConfig | None = None) -> None:
        config = config or FaultConfig()
        super().__init__(config, config.seed)

    @property
    def config(self) -> FaultConfig:
        """The fault settings (the same object as :attr:`rates`; assignable)."""
        return self.rates

    @config.setter
    def config(self, config: FaultConfig) -> None:
        self.rates = config

    def garbage(self) -> bytes:
        """Return one garbage line body (no CR LF); one time in four longer than 4 kB."""
        n = 5000 if self._rng.random() < 0.25 else self._rng.randint(1, 60)
        alphabet = bytes(b for b in range(256) if b not in (0x0A, 0x0D))
        return bytes(self._rng.choice(alphabet) for _ in range(n))
