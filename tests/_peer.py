"""Sessions of third-party clients against the simulators: run the steps, keep the failures."""

from __future__ import annotations

import asyncio
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


async def session_in_thread(sim: Any, label: str, capsys: Any,
                            session: Callable[..., tuple[int, int, list[str]]], *args: Any,
                            timeout: float = 60.0) -> tuple[int, int, list[str]]:
    """Run a blocking client ``session(*args)`` in a thread against the started ``sim``
    (stopped afterwards, whatever happened); print the count under ``label``."""
    try:
        passed, tried, failures = await asyncio.wait_for(asyncio.to_thread(session, *args),
                                                         timeout)
    finally:
        await sim.stop()
    with capsys.disabled():
        print(f"\n{label} client session: {passed}/{tried} steps passed")
    return passed, tried, failures
