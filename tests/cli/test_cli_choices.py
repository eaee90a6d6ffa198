"""``capevo evolve``'s --preset and --modality choices are the evolve layer's own, and a combined
modality runs end to end from the command line.

The CLI spells the choices out so that ``--help`` does not import scipy; these tests hold the two
lists equal. Before they did, ``--modality hybrid+il`` (documented in docs/evolve.md) was refused.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_support import run_capevo

from capevo.cli.evolve import MODALITIES, PRESETS
from capevo.evolve import config
from capevo.records import Kind
from capevo.registry.local import LocalRegistry


def test_the_cli_offers_every_modality_and_preset_the_evolve_layer_has() -> None:
    assert MODALITIES == config.MODALITIES
    assert set(PRESETS) == set(config.config_names())


@pytest.mark.slow
def test_hybrid_then_il_from_the_command_line_clones_the_code_skill_into_a_neural_candidate(tmp_path: Path) -> None:
    """Two iterations at ``tiny`` on T1: CEM's turn on the code skill, then behaviour cloning's."""
    proc = run_capevo(
        [
            "evolve",
            "--task",
            "T1",
            "--preset",
            "tiny",
            "--iterations",
            "2",
            "--modality",
            "hybrid+il",
            "--root",
            tmp_path / "data",
            "--report-dir",
            tmp_path / "report",
            "--json",
        ],
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    assert json.loads((tmp_path / "report" / "run.json").read_text())["modality"] == "hybrid+il"
    with LocalRegistry(tmp_path / "data", actor="reader") as registry:
        assert registry.get_version("pick.reach", 0).kind is Kind.CODE
        neural = [
            v
            for ecm in ("pick.reach", "pick.grasp", "pick.lift")
            for v in registry.get_ecm(ecm).versions
            if v.kind is Kind.NEURAL
        ]
    # iteration 0 is CEM's turn (it may find nothing better); iteration 1 is il's, whose candidate
    # is a neural version of a code ECM, published for the gate whatever it decides
    assert len(neural) == 1 and neural[0].origin.value == "il", [(v.name, v.version, v.origin) for v in neural]
    assert [g["candidate_version"] for g in summary["gate"]][-1] == neural[0].version
