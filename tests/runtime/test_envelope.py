"""Which Φ runs (:mod:`capevo.runtime.envelope`): the per-task envelope by default, the paper's on request."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.envelope import DEFAULT_PHI, PHI_NAMES, check_phi_choice, phi_name, resolve_phi
from capevo.runtime.governance import Phi
from capevo.runtime.tasks import task_spec

TASKS = ("T1", "T2", "T3", "T4", "T5", "T6")


@pytest.mark.parametrize("task", TASKS)
def test_the_default_is_the_scene_aware_envelope_of_the_task(task: str) -> None:
    spec = task_spec(task)
    assert DEFAULT_PHI == "task"
    phi = resolve_phi(None, spec)
    assert phi.hash == resolve_phi("task", spec).hash == Phi.for_task(spec).hash != Phi.default().hash
    assert phi.reads_proximity
    assert phi_name(phi, spec) == "task"


@pytest.mark.parametrize("task", TASKS)
def test_paper_selects_the_papers_envelope(task: str) -> None:
    spec = task_spec(task)
    phi = resolve_phi("paper", spec)
    assert phi.hash == Phi.default().hash
    assert phi_name(phi, spec) == "paper"


def test_a_yaml_file_is_loaded_and_named_custom(tmp_path: Path) -> None:
    path = tmp_path / "phi.yaml"
    path.write_text(yaml.safe_dump({"version": 1, "constraints": [{"kind": "velocity_cap", "max_norm": 1.0}]}))
    phi = resolve_phi(path, task_spec("T1"))
    assert phi.labels == ("velocity_cap",) and not phi.reads_proximity
    assert phi_name(phi, task_spec("T1")) == "custom"
    assert check_phi_choice(str(path)) == str(path)


def test_a_phi_object_is_used_as_given() -> None:
    phi = Phi.default()
    assert resolve_phi(phi, task_spec("T6")) is phi


def test_an_unknown_task_is_invalid() -> None:
    with pytest.raises(Invalid) as e:
        resolve_phi("task", "T9")
    assert e.value.code is ErrorCode.INVALID


@given(st.text(max_size=30).filter(lambda s: s not in PHI_NAMES and not Path(s).is_file()))
def test_any_other_choice_is_invalid_and_names_the_valid_ones(choice: str) -> None:
    for call in (lambda: resolve_phi(choice, task_spec("T1")), lambda: check_phi_choice(choice)):
        with pytest.raises(Invalid) as e:
            call()
        assert e.value.details["valid"] == list(PHI_NAMES)
