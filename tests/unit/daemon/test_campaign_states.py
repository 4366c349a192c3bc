"""The campaign state machine: the written table, illegal transitions, the ADR copy."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from robocal.daemon.campaign import (
    FINAL,
    TRANSITIONS,
    CampaignState,
    check_transition,
    transition_table_markdown,
)
from robocal.errors import InvalidTransition

S = CampaignState
ADR = Path(__file__).resolve().parents[3] / "docs" / "adr" / "0006-daemon.md"


def test_happy_path_is_allowed():
    path = [S.CREATED, S.RUNNING, S.PAUSED, S.RUNNING, S.FAULTED, S.RUNNING, S.MEASURED,
            S.FITTED, S.APPROVED, S.PUSHED]
    for a, b in itertools.pairwise(path):
        check_transition(a, b)


@pytest.mark.parametrize("src", [s for s in S if s not in FINAL])
def test_abort_from_every_non_final_state(src):
    check_transition(src, S.ABORTED)


@pytest.mark.parametrize(("src", "dst"), [
    (S.CREATED, S.MEASURED), (S.RUNNING, S.FITTED), (S.FITTED, S.PUSHED),
    (S.MEASURED, S.APPROVED), (S.PUSHED, S.RUNNING), (S.ABORTED, S.RUNNING),
    (S.PAUSED, S.MEASURED), (S.APPROVED, S.FITTED),
])
def test_illegal_transitions_raise(src, dst):
    with pytest.raises(InvalidTransition) as info:
        check_transition(src, dst)
    assert info.value.from_state == src.value and info.value.to_state == dst.value


def test_push_only_through_approval():
    into_pushed = {s for s, nxt in TRANSITIONS.items() if S.PUSHED in nxt}
    assert into_pushed == {S.APPROVED}
    into_approved = {s for s, nxt in TRANSITIONS.items() if S.APPROVED in nxt}
    assert into_approved == {S.FITTED}


def test_unknown_state_is_an_invalid_transition():
    with pytest.raises(InvalidTransition, match="unknown state"):
        check_transition("created", "flying")


def test_adr_holds_the_current_table():
    assert transition_table_markdown() in ADR.read_text()
