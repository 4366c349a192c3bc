"""Fault injection settings shared by the simulators."""

from __future__ import annotations

import random

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["FaultConfig", "FaultInjector"]

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


class FaultInjector:
    """Draw faults from a :class:`FaultConfig` with its own seeded generator."""

    def __init__(self, config: FaultConfig | None = None) -> None:
        self.config = config or FaultConfig()
        self._rng = random.Random(self.config.seed)
        self.counts: dict[str, int] = {}

    def fire(self, name: str) -> bool:
        """Return True (and count it) with probability ``config.<name>_rate``."""
        rate: float = getattr(self.config, f"{name}_rate")
        if rate > 0.0 and self._rng.random() < rate:
            self.counts[name] = self.counts.get(name, 0) + 1
            return True
        return False

    def garbage(self) -> bytes:
        """Return one garbage line body (no CR LF); one time in four longer than 4 kB."""
        n = 5000 if self._rng.random() < 0.25 else self._rng.randint(1, 60)
        alphabet = bytes(b for b in range(256) if b not in (0x0A, 0x0D))
        return bytes(self._rng.choice(alphabet) for _ in range(n))
