"""The campaign state machine: states and the written transition table.

::

    created  -> running | aborted
    running  -> paused | faulted | measured | aborted
    paused   -> running | aborted
    faulted  -> running | aborted                 # the operator resumes after a fault
    measured -> fitted | faulted | aborted        # the fit runs while "measured"
    fitted   -> approved | aborted                # an operator approves the fit (or aborts)
    approved -> pushed | aborted                  # a failed push leaves it "approved"
    pushed, aborted: final

``running`` is the only state in which the robot moves. A crash leaves the state as it was;
on restart ``running`` campaigns resume at their first unmeasured pose and ``measured``
campaigns are fitted again. Compensation reaches the robot only through ``approved``.
Measure-only campaigns (verification runs) end in ``measured``.
"""

from __future__ import annotations

from enum import StrEnum

from robocal.errors import InvalidTransition

__all__ = [
    "ACTIVE",
    "FINAL",
    "TRANSITIONS",
    "CampaignState",
    "check_transition",
    "transition_table_markdown",
]


class CampaignState(StrEnum):
    """States of a calibration campaign."""

    CREATED = "created"
    RUNNING = "running"
    PAUSED = "paused"
    FAULTED = "faulted"
    MEASURED = "measured"
    FITTED = "fitted"
    APPROVED = "approved"
    PUSHED = "pushed"
    ABORTED = "aborted"


S = CampaignState

#: The transition table; anything not listed raises :class:`InvalidTransition`.
TRANSITIONS: dict[CampaignState, frozenset[CampaignState]] = {
    S.CREATED: frozenset({S.RUNNING, S.ABORTED}),
    S.RUNNING: frozenset({S.PAUSED, S.FAULTED, S.MEASURED, S.ABORTED}),
    S.PAUSED: frozenset({S.RUNNING, S.ABORTED}),
    S.FAULTED: frozenset({S.RUNNING, S.ABORTED}),
    S.MEASURED: frozenset({S.FITTED, S.FAULTED, S.ABORTED}),
    S.FITTED: frozenset({S.APPROVED, S.ABORTED}),
    S.APPROVED: frozenset({S.PUSHED, S.ABORTED}),
    S.PUSHED: frozenset(),
    S.ABORTED: frozenset(),
}

#: States with no way out.
FINAL: frozenset[CampaignState] = frozenset(s for s, nxt in TRANSITIONS.items() if not nxt)
#: States in which the daemon is working on the campaign by itself.
ACTIVE: frozenset[CampaignState] = frozenset({S.RUNNING, S.MEASURED})


def check_transition(src: CampaignState | str, dst: CampaignState | str) -> None:
    """Raise :class:`InvalidTransition` unless ``src -> dst`` is in :data:`TRANSITIONS`.

    Raises
    ------
    InvalidTransition
        With ``from_state`` and ``to_state`` set; unknown state names raise it as well.
    """
    try:
        a, b = CampaignState(src), CampaignState(dst)
    except ValueError as err:
        raise InvalidTransition(str(src), str(dst), "unknown state") from err
    if b not in TRANSITIONS[a]:
        nxt = sorted(s.value for s in TRANSITIONS[a])
        raise InvalidTransition(a.value, b.value,
                                f"it can become {' or '.join(nxt)}" if nxt
                                else "it is finished; start a new campaign")


def transition_table_markdown() -> str:
    """Render :data:`TRANSITIONS` as a Markdown table (the ADR embeds it; a test compares)."""
    lines = ["| from | to |", "|---|---|"]
    for state in CampaignState:
        nxt = ", ".join(s.value for s in CampaignState if s in TRANSITIONS[state])
        lines.append(f"| {state.value} | {nxt or '(final)'} |")
    return "\n".join(lines)
