"""Sessions of third-party clients against the simulators: run the steps, keep the failures."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any


def run_steps(steps: Sequence[tuple[str, Callable[[], Any]]]) -> tuple[int, int, list[str]]:
    """Run every step (a step passes when it returns something true; one that raises fails
    with its error in its name, and the session goes on); return passed, tried, failures."""
    passed, failures = 0, []
    for name, step in steps:
        try:
            ok = bool(step())
        except Exception as err:  # a step that raises failed; the session goes on
            ok, name = False, f"{name}: {err!r}"
        passed += ok
        if not ok:
            failures.append(name)
    return passed, len(steps), failures
