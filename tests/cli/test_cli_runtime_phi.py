"""``capevo runtime serve --phi``: a YAML file, ``task`` (the per-task envelope) or the paper's by default."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from capevo.cli.runtime import _phi
from capevo.errors import ErrorCode, Invalid
from capevo.runtime.governance import Phi


def test_default_is_the_papers_envelope() -> None:
    assert _phi(None, "T3").hash == Phi.default().hash


def test_task_selects_the_per_task_envelope() -> None:
    phi = _phi(Path("task"), "stack")
    assert phi.hash == Phi.for_task("stack").hash != Phi.default().hash
    assert phi.reads_proximity


def test_a_yaml_file_is_loaded(tmp_path: Path) -> None:
    path = tmp_path / "phi.yaml"
    path.write_text(yaml.safe_dump({"version": 1, "constraints": [{"kind": "velocity_cap", "max_norm": 1.0}]}))
    phi = _phi(path, "T1")
    assert phi.labels == ("velocity_cap",) and not phi.reads_proximity


def test_an_unknown_task_is_invalid() -> None:
    with pytest.raises(Invalid) as e:
        _phi(Path("task"), "T9")
    assert e.value.code is ErrorCode.INVALID
