"""``capevo runtime gate``: a candidate published outside an evolve run gets the same decision.

Real T1 episodes in a real registry on disk, through the command as a user runs it. The
candidates are the hand-set ``pick.reach`` (v0's listed weaknesses fixed by hand: it reaches the
can, v0 does not) and an unchanged copy of ``pick.lift`` v0.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_support import run_capevo

from capevo.cli import EXIT_CODES
from capevo.errors import ErrorCode
from capevo.learner.skills import seed_registry, seed_specs
from capevo.learner.skills.hand_set import hand_set_specs
from capevo.records import State
from capevo.registry.local import LocalRegistry
from capevo.runtime.gate import SeedPlan

pytestmark = pytest.mark.slow


@pytest.fixture
def root(tmp_path: Path) -> Path:
    root = tmp_path / "data"
    with LocalRegistry(root, actor="test") as registry:
        seed_registry(registry, "T1", reason="v0")
        reach = next((source, spec) for name, source, spec in hand_set_specs("T1") if name == "pick.reach")
        registry.publish("pick.reach", reach[0].encode(), reach[1])
        lift = next((source, spec) for name, source, spec in seed_specs("T1") if name == "pick.lift")
        registry.publish("pick.lift", lift[0].encode(), lift[1])
    return root


def gate(root: Path, name: str, version: int, *extra: str) -> tuple[int, str, str]:
    proc = run_capevo(["runtime", "gate", name, version, "--root", root, "--json", *extra], timeout=600)
    return proc.returncode, proc.stdout, proc.stderr


def test_the_gate_promotes_a_better_candidate_and_rejects_an_equal_one(root: Path) -> None:
    code, out, err = gate(root, "pick.reach", 1, "--round", "3")
    assert code == 0, err[-2000:]
    decision = json.loads(out)
    assert decision["promoted"] is True, decision["reason"]
    # the preset's paired seeds, batch 3 of the plan's held-out gate range
    assert decision["seeds"][:10] == SeedPlan(base_seed=0).gate(10, round=3)

    code, out, err = gate(root, "pick.lift", 1, "--round", "3")
    assert code == 0, err[-2000:]
    assert json.loads(out)["promoted"] is False

    with LocalRegistry(root, actor="reader") as registry:
        assert registry.get_version("pick.reach").version == 1
        assert registry.get_version("pick.reach", 1).gate_evidence
        assert registry.get_version("pick.lift").version == 0
        assert registry.get_version("pick.lift", 1).state is State.REJECTED

    code, _, err = gate(root, "pick.lift", 1, "--round", "4")
    assert code == EXIT_CODES[ErrorCode.ILLEGAL_TRANSITION] and "only a candidate can be gated" in err


def test_candidates_named_with_are_decided_together(root: Path) -> None:
    # the hand-set reach and an unchanged copy of lift, as one set: the set with both reaches
    # the can where the active set does not, so both are promoted on that one decision
    code, out, err = gate(root, "pick.reach", 1, "--round", "3", "--with", "pick.lift=1")
    assert code == 0, err[-2000:]
    decision = json.loads(out)
    assert decision["promoted"] is True, decision["reason"]
    assert "decided together with pick.lift v1" in decision["reason"]
    assert [m["name"] for m in decision["members"]] == ["pick.lift"]
    with LocalRegistry(root, actor="reader") as registry:
        assert registry.get_version("pick.reach").version == 1
        assert registry.get_version("pick.lift").version == 1
        lift = registry.get_version("pick.lift", 1).gate_evidence
        reach = registry.get_version("pick.reach", 1).gate_evidence
    assert lift["chain"] == {"pick.reach": 1, "pick.lift": 1} and lift["name"] == "pick.lift"
    assert lift["outcomes"] == reach["outcomes"]
    assert reach["capability_set"]["candidate"]["pick.lift"] == 1
    assert reach["capability_set"]["active"]["pick.lift"] == 0


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (("pick.reach", 1, "--round", "0", "--root", "{root}", "--with", "pick.lift"), ErrorCode.INVALID, "--with"),
        (
            ("pick.reach", 1, "--round", "0", "--root", "{root}", "--with", "stack.reach=1"),
            ErrorCode.INVALID,
            "another task",
        ),
        (
            ("pick.reach", 1, "--round", "0", "--root", "{root}", "--with", "pick.reach=1"),
            ErrorCode.INVALID,
            "names the gated ECM",
        ),
        (("pick.reach", 1, "--round", "0"), ErrorCode.INVALID, "give --root DIR or --connect ENDPOINT"),
        (("pick.nothing", 1, "--round", "0", "--root", "{root}"), ErrorCode.INVALID, "has no ECM 'pick.nothing'"),
        (("pick.reach", 9, "--round", "0", "--root", "{root}"), ErrorCode.NOT_FOUND, "9"),
    ],
)
def test_bad_input_is_a_clear_error_before_any_episode(
    root: Path, args: tuple[object, ...], code: ErrorCode, message: str
) -> None:
    proc = run_capevo(["runtime", "gate", *(str(a).format(root=root) for a in args)], env={"CAPEVO_ROOT": ""})
    assert proc.returncode == EXIT_CODES[code], proc.stderr
    assert message in proc.stderr
