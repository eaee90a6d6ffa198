"""The hand-set parameters (issue 19's "best hand-set parameters" row) stay honest: each one is a
declared parameter inside its declared range, and the hand-set versions differ from v0 in
``PARAMS`` alone."""

from __future__ import annotations

from pathlib import Path

import pytest

from capevo.errors import ErrorCode, Invalid
from capevo.learner.search import read_ranges
from capevo.learner.skills import seed_registry, seed_specs
from capevo.learner.skills.hand_set import HAND_SET, hand_set_overrides, hand_set_specs, seed_hand_set
from capevo.registry.local import LocalRegistry
from capevo.runtime.ecm.code import read_params


@pytest.mark.parametrize("task", [*sorted(HAND_SET), "peg_in_hole"])
def test_every_override_is_a_declared_parameter_inside_its_range(task: str) -> None:
    changed = 0
    for (name, v0, _), (_, hand, _) in zip(seed_specs(task), hand_set_specs(task), strict=True):
        before, after, ranges = read_params(v0), read_params(hand), read_ranges(v0)
        assert before.keys() == after.keys()
        for key, value in hand_set_overrides(task)[name].items():
            assert after[key] == value
            low, high = ranges[key].low, ranges[key].high
            assert low <= value <= high, (name, key, value, (low, high))
            changed += value != before[key]
        # invariant 2: only the PARAMS literal differs
        strip = [line for line in hand.splitlines() if not line.startswith("    '")]
        assert strip == [line for line in v0.splitlines() if not line.startswith("    '")]
    assert changed > 0


def test_hand_set_versions_need_a_registry_of_their_own(tmp_path: Path) -> None:
    with LocalRegistry(tmp_path / "hand", actor="tests") as reg:
        records = seed_hand_set(reg, "T1")
        assert [r.name for r in records] == ["pick.reach", "pick.grasp", "pick.lift"]
        assert read_params(reg.get_artifact("pick.reach").decode())["grasp_dz"] == 0.0
    with LocalRegistry(tmp_path / "v0", actor="tests") as reg:
        seed_registry(reg, "T1")
        with pytest.raises(Invalid) as info:
            seed_hand_set(reg, "T1")
        assert info.value.code is ErrorCode.INVALID and info.value.details["field"] == "registry"
