"""Combined modalities (the paper's Table 8 rows RL + IL, RL + LLM, IL + LLM, all three): the named
modalities take turns, one iteration each (:class:`capevo.evolve.learners.TurnUpdater`).

Invariants of ``TurnUpdater``: turn order (1) and no code part on a neural version (2), over a real
registry with recording updaters; then a real ``hybrid+rl`` evolution at ``tiny`` in which CEM tunes
the code skill and SAC distils and fine-tunes it on the next turn.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from evolve_support import PLAN, TASK, make_agent, seeded_registry

from capevo.errors import Invalid
from capevo.evolve.config import COMBINED_MODALITIES, MODALITIES, NEURAL_MODALITIES, make_config
from capevo.evolve.learners import Proposal, TurnUpdater, UpdaterContext, UpdateRequest, modality_names
from capevo.evolve.loop import ensure_v0
from capevo.evolve.progress import RecordingProgress
from capevo.evolve.run import EvolveOptions, run_evolution
from capevo.experiment.methods import knowledge_of
from capevo.experiment.paper import paper_ablation_row
from capevo.learner.base import Candidate
from capevo.learner.rl import check_note
from capevo.records import Kind
from capevo.registry.local import LocalRegistry
from capevo.runtime.tasks import Perturbations


class Recording:
    """An updater that records being asked and proposes a placeholder candidate."""

    def __init__(self, name: str, asked: list[str]) -> None:
        self.name, self.asked, self.closed = name, asked, False

    def propose(self, request: UpdateRequest, progress: Any) -> Proposal | None:
        self.asked.append(self.name)
        return Proposal(learner=self.name, candidate=Candidate(ecm=request.ecm, artifact=b"x", spec=None))  # type: ignore[arg-type]

    def close(self) -> None:
        self.closed = True


def turns(registry: LocalRegistry, tmp_path: Path, parts: tuple[str, ...]) -> tuple[TurnUpdater, list[str]]:
    context = UpdaterContext(
        registry=registry,
        task=TASK,
        config=make_config("tiny"),
        policy=make_agent(tmp_path / "report").policy,
        agent_identity_hash="0" * 64,
        perturbations=Perturbations(),
        trace_dir=tmp_path / "traces",
        state_dir=tmp_path / "state",
    )
    updater = TurnUpdater(context, parts)
    asked: list[str] = []
    updater._updaters = {p: Recording(p, asked) for p in parts}
    return updater, asked


def request(iteration: int, ecm: str = "pick.reach") -> UpdateRequest:
    return UpdateRequest(task=TASK, ecm=ecm, iteration=iteration, outcomes=(), plan=PLAN, seed=0)


def test_the_modalities_take_turns_in_the_order_written(tmp_path: Path) -> None:
    updater, asked = turns(seeded_registry(tmp_path), tmp_path, ("hybrid", "il", "rl"))
    made = [updater.propose(request(i), RecordingProgress()) for i in range(5)]
    assert asked == ["hybrid", "il", "rl", "hybrid", "il"]
    assert [p.notes["turn"] for p in made if p] == asked
    assert [p.learner for p in made if p] == [f"{a}/{a}" for a in asked]
    assert updater.turn_order(4) == ("il", "rl", "hybrid")
    updater.close()
    assert all(u.closed for u in updater._updaters.values())


def test_a_code_part_passes_its_turn_on_a_neural_version(tmp_path: Path) -> None:
    registry = LocalRegistry(tmp_path / "registry", actor="tester")
    ensure_v0(registry, TASK, modality="il+rl")
    assert registry.get_version("pick.reach").kind is Kind.NEURAL
    updater, asked = turns(registry, tmp_path, ("hybrid", "il"))
    proposal = updater.propose(request(0), RecordingProgress())
    assert asked == ["il"] and proposal is not None and proposal.notes["turn"] == "il"


def test_combinations_are_registered_and_named_like_the_paper() -> None:
    assert set(COMBINED_MODALITIES) <= set(MODALITIES) and set(MODALITIES) <= set(modality_names())
    rows = {m: paper_ablation_row(m) for m in COMBINED_MODALITIES}
    assert rows == {
        "il+rl": "RL + IL",
        "hybrid+rl": "RL + LLM",
        "hybrid+il": "IL + LLM",
        "hybrid+il+rl": "All three (Ours)",
    }
    assert "il+rl" in NEURAL_MODALITIES and "hybrid+rl" not in NEURAL_MODALITIES
    assert knowledge_of("ours", {"modality": "il+rl"}).startswith("random weights")
    assert "take turns" in knowledge_of("ours", {"modality": "hybrid+rl"})
    with pytest.raises(Invalid):
        TurnUpdater(None, ("il",))  # type: ignore[arg-type]


@pytest.mark.slow
def test_hybrid_then_rl_evolves_one_ecm_per_turn(tmp_path: Path) -> None:
    """Two iterations at ``tiny`` on T1: CEM over the code skill, then SAC from the code skill."""
    result = run_evolution(
        EvolveOptions(
            task="T1",
            preset="tiny",
            iterations=2,
            modality="hybrid+rl",
            root=tmp_path / "data",
            report_dir=tmp_path / "report",
        )
    )
    first, second = result.rows
    assert first.learner.startswith("hybrid/") and second.learner.startswith("rl/"), (first.learner, second.learner)
    assert first.learner_steps > 0 and second.learner_steps > 0
    # SAC started from the distilled code skill, so its check ran before and after training
    assert re.search(r"check \d/1 before SAC, \d/1 after: the candidate's actor is ", second.update_note or "")
    registry = LocalRegistry(tmp_path / "data", actor="reader")
    kinds = {
        v.version: v.kind for v in (registry.get_version(second.ecm_updated, n) for n in (0, second.candidate_version))
    }
    registry.close()
    assert kinds[0] is Kind.CODE and kinds[second.candidate_version] is Kind.NEURAL
    assert (tmp_path / "report" / "learner-state" / "rl").is_dir()
    manifest = json.loads((tmp_path / "report" / "run.json").read_text())
    assert manifest["modality"] == "hybrid+rl"


def test_the_check_note_says_which_actor_the_candidate_kept() -> None:
    check = {
        "before": {"successes": 6, "episodes": 10, "env_steps": 900},
        "after": {"successes": 4, "episodes": 10, "env_steps": 1100},
        "actor": "start",
    }
    assert check_note(check) == "check 6/10 before SAC, 4/10 after: the candidate's actor is the one before SAC"
    assert check_note({**check, "actor": "sac"}).endswith("the candidate's actor is SAC's")
