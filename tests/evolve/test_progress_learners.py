"""The progress display and the learner plumbing (no simulator).

Invariants: progress 1-2, learners 1-3.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest
from evolve_support import PLAN, seeded_registry
from rich.console import Console

from capevo.errors import ErrorCode, Invalid
from capevo.evolve.learners import (
    Proposal,
    RemoteCandidates,
    UpdateRequest,
    make_updater,
    training_seed_window,
    waiting_candidates,
)
from capevo.evolve.progress import RecordingProgress, RichProgress
from capevo.records import EcmVersion


def _drive(progress: RichProgress) -> None:
    progress.run_started(task="pick", total=2, completed=0)
    progress.iteration_started(0)
    progress.phase("live", episodes=3)
    progress.episodes_done(3)
    progress.learner_started(total=4, unit="CEM episodes")
    progress.learner_advance(4)
    progress.message("  gate: reject")
    progress.iteration_finished(0, "success 0/3")
    progress.close()
    progress.close()  # idempotent


@pytest.mark.parametrize("live", [False, True])
def test_rich_progress_draws_and_closes(live: bool) -> None:
    buf = io.StringIO()
    _drive(RichProgress(Console(file=buf, force_terminal=live, width=100), live=live))
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", buf.getvalue())
    assert "iteration 0: success 0/3" in text and "gate: reject" in text
    if not live:
        assert "live: 3 episodes" in text and "learner: 4 CEM episodes" in text


class _Broken(io.StringIO):
    def write(self, s: str) -> int:
        raise OSError("display gone")


def test_a_broken_display_never_stops_the_run() -> None:
    _drive(RichProgress(Console(file=_Broken(), width=80), live=False))
    _drive(RichProgress(Console(file=_Broken(), force_terminal=True, width=80), live=True))


def test_unknown_modality_lists_the_valid_ones(tmp_path: Path) -> None:
    with pytest.raises(Invalid) as info:
        make_updater("telepathy", None)  # type: ignore[arg-type]
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == (
        "unknown modality 'telepathy'; valid: code, hybrid, rl, il, il+rl, hybrid+rl, hybrid+il, hybrid+il+rl"
    )


def test_a_proposal_holds_exactly_one_of_candidate_and_record(tmp_path: Path) -> None:
    with pytest.raises(Invalid):
        Proposal(learner="x")
    registry = seeded_registry(tmp_path)
    record: EcmVersion = registry.get_version("pick.reach")
    assert Proposal(learner="x", record=record).record is record


def test_neural_training_seeds_stay_in_the_training_range() -> None:
    train = PLAN.range("train")
    for iteration in (0, 1, 7, 99, 100, 12345):
        base, offset = training_seed_window(PLAN, iteration)
        # episode k of the update runs seed base + offset + k; 50 000 episodes stay in range
        assert base == train.start
        assert PLAN.purpose_of(base + offset) == "train" and PLAN.purpose_of(base + offset + 50_000) == "train"
    assert training_seed_window(PLAN, 1) != training_seed_window(PLAN, 2)


def test_remote_candidates_wait_then_hand_over_a_published_one(tmp_path: Path) -> None:
    registry = seeded_registry(tmp_path)
    request = UpdateRequest(task="pick", ecm="pick.reach", iteration=0, outcomes=(), plan=PLAN, seed=0)
    progress = RecordingProgress()
    waiting = RemoteCandidates(registry, timeout_s=0.2, poll_s=0.05)
    assert waiting.propose(request, progress) is None  # nobody published within the timeout
    assert any("capevo learner serve --ecm pick.reach" in c[1]["text"] for c in progress.calls)
    parent = registry.get_version("pick.lift")
    from capevo.records import PublishSpec

    spec = PublishSpec(kind=parent.kind, descriptor=parent.descriptor, interface=parent.interface, parent=0)
    published = registry.publish("pick.lift", registry.get_artifact("pick.lift", 0) + b"\n", spec, actor="rl-1")
    assert [v.version for v in waiting_candidates(registry, ["pick.reach", "pick.lift", "nope"])] == [1]
    got = RemoteCandidates(registry, timeout_s=5).propose(request, progress)
    assert got is not None and got.record == published and got.candidate is None
    assert got.notes["published_by"] == "rl-1"
