"""Experiment grids: YAML parsing and validation, presets, the packaged configs, cell names
(capevo.experiment.config invariants 1-3) and the method registry (methods invariant 1)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from capevo.baselines.base import Budget, CellSpec
from capevo.errors import ErrorCode, Invalid, NotFound
from capevo.evolve.config import make_config
from capevo.experiment.config import (
    ExperimentConfig,
    MethodEntry,
    cell_dir_name,
    load_config,
    make_experiment,
    packaged_configs,
    parse_yaml,
    preset_names,
)
from capevo.experiment.methods import is_available, make_method, method_class, method_names

GOOD = """
name: g
tasks: [T1, place]
seeds: [42, 7]
iterations: 2
budget: {env_steps_per_iteration: 800, eval_episodes: 3, horizon: 40}
methods:
  - s-ecm
  - {method: explorer, governance: false, tasks: [T6], iterations: 1, options: {adversaries: all}}
"""


def _field(text: str) -> str:
    with pytest.raises(Invalid) as info:
        parse_yaml(text)
    assert info.value.code is ErrorCode.INVALID
    return str(info.value.details["field"])


def test_a_grid_lists_its_cells_entry_by_entry_then_task_then_seed() -> None:
    config = parse_yaml(GOOD)
    cells = config.cells()
    assert [(c.method, c.task, c.seed) for c in cells] == [
        ("s-ecm", "T1", 42),
        ("s-ecm", "T1", 7),
        ("s-ecm", "T2", 42),
        ("s-ecm", "T2", 7),
        ("explorer", "T6", 42),
        ("explorer", "T6", 7),
    ]
    assert all(c.budget == Budget(env_steps_per_iteration=800, eval_episodes=3, horizon=40) for c in cells)
    explorer = cells[-1]
    assert explorer.iterations == 1 and not explorer.governance and explorer.options == {"adversaries": "all"}
    assert cells[0].iterations == 2 and cells[0].governance and cells[0].phi == "task"
    assert list(config.cell_names()) == [
        "T1-s-ecm-s42",
        "T1-s-ecm-s7",
        "T2-s-ecm-s42",
        "T2-s-ecm-s7",
        "T6-explorer-s42-gov-off",
        "T6-explorer-s7-gov-off",
    ]
    assert config.yaml_text == GOOD


def test_the_dict_form_round_trips() -> None:
    """Invariant 2."""
    config = parse_yaml(GOOD)
    again = ExperimentConfig.from_dict(config.to_dict())
    assert again == config and again.cells() == config.cells()
    assert again.yaml_text == GOOD


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"tasks": ["T9"]}, "tasks[0]"),
        ({"tasks": []}, "tasks"),
        ({"seeds": [1, -2]}, "seeds[1]"),
        ({"seeds": [3, 3]}, "seeds"),
        ({"iterations": 0}, "iterations"),
        ({"iterations": True}, "iterations"),
        ({"budget": {"env_steps_per_iteration": 0, "eval_episodes": 3}}, "budget.env_steps_per_iteration"),
        ({"budget": {"env_steps_per_iteration": 10, "eval_episodes": 0}}, "budget.eval_episodes"),
        ({"budget": {"env_steps_per_iteration": 10}}, "budget.eval_episodes"),
        ({"budget": {"env_steps_per_iteration": 10, "eval_episodes": 1, "speed": 2}}, "budget.speed"),
        ({"phi": "no-such-envelope"}, "phi"),
        ({"governance": "yes"}, "governance"),
        ({"colour": "red"}, "colour"),
        ({"methods": ["nope"]}, "methods[0].method"),
        ({"methods": []}, "methods"),
        ({"methods": ["s-ecm", {"method": "explorer", "options": [1]}]}, "methods[1].options"),
        ({"methods": [{"method": "s-ecm", "tasks": ["T7"]}]}, "methods[0].tasks[0]"),
        ({"methods": [{"method": "s-ecm", "speed": 1}]}, "methods[0].speed"),
        ({"methods": [{"options": {}}]}, "methods[0].method"),
        ({"methods": ["s-ecm", "s-ecm"]}, "methods"),
    ],
)
def test_every_bad_field_is_named(change: dict, field: str) -> None:
    """Invariant 1 (and 3: the same cell twice would share a directory)."""
    raw = {**yaml.safe_load(GOOD), **change}
    assert _field(yaml.safe_dump(raw)) == field


def test_missing_fields_and_non_mappings_are_named() -> None:
    raw = yaml.safe_load(GOOD)
    for name in ("tasks", "seeds", "iterations", "budget", "methods"):
        assert _field(yaml.safe_dump({k: v for k, v in raw.items() if k != name})) == name
    assert _field("- a\n- b\n") == "config"
    assert _field("tasks: [T1\n") == "yaml"


yaml_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 100_000) | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)
fields = st.sampled_from(
    ["name", "tasks", "seeds", "iterations", "budget", "phi", "governance", "perturbations", "methods", "other"]
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(fields, yaml_values, max_size=9), st.text(max_size=60))
def test_any_yaml_gives_a_config_or_a_named_invalid(raw: dict, noise: str) -> None:
    """Invariant 1 for arbitrary input: a config or Invalid naming a field, never another error."""
    base = yaml.safe_load(GOOD)
    for text in (yaml.safe_dump({**base, **raw}), yaml.safe_dump(raw), noise):
        try:
            config = parse_yaml(text)
        except Invalid as exc:
            assert exc.details.get("field"), exc
        else:
            assert config.cells() and len(config.cell_names()) == len(config.cells())


def test_governance_and_options_keep_cells_apart() -> None:
    """Invariant 3: H3's governance on/off and the ablation's modalities get their own directories."""
    h3 = load_config("h3")
    names = list(h3.cell_names())
    assert "T1-explorer-s42" in names and "T1-explorer-s42-gov-off" in names and len(names) == 12
    ablation = load_config("ablation-t3")
    modalities = ("code", "rl", "il", "hybrid", "il+rl", "hybrid+rl", "hybrid+il", "hybrid+il+rl")
    assert list(ablation.cell_names()) == [f"T3-ours-s42-modality={m}" for m in modalities]
    cell = CellSpec(
        task="T1",
        method="am",
        seed=1,
        iterations=1,
        budget=Budget(env_steps_per_iteration=1, eval_episodes=1),
        phi="paper",
        perturbations=False,
        options={"net_arch": [64, 64, 64, 64, 64, 64, 64, 64, 64]},
    )
    name = cell_dir_name(cell, options=["net_arch"])
    assert name.startswith("T1-am-s1-phi-paper-noperturb-net_arch=") and len(name) < 60


def test_presets_and_packaged_configs_are_valid() -> None:
    assert set(preset_names()) >= {"paper", "cpu-small", "smoke"}
    assert set(packaged_configs()) >= {"h1", "h2", "h3", "ablation-t3"}
    paper = make_experiment("paper")
    assert paper.tasks == ("T1", "T2", "T3", "T4", "T5", "T6") and paper.seeds == (42, 7, 123, 2024)
    assert paper.iterations == 20 and paper.budget.eval_episodes == 30
    assert {"ours-code", "am", "s-ecm", "spirl", "skimo"} <= {m.method for m in paper.methods}
    smoke = make_experiment("smoke")
    assert smoke.tasks == ("T1", "T6") and len(smoke.seeds) == 1 and smoke.iterations == 2
    # every method is in the smoke grid ("ours" is ours-code or ours-neural by option), and every
    # one can be built here
    smoke_methods = {m.method for m in smoke.methods}
    assert smoke_methods == set(method_names()) - {"ours"}
    assert all(is_available(n) for n in method_names())
    h3 = load_config("h3")
    assert h3.budget.eval_episodes == 50
    for name in (*preset_names(), *packaged_configs()):
        config = load_config(name)
        for cell in config.cells():
            if cell.method.startswith("ours"):
                make_method(cell.method).evolve_config(cell)  # type: ignore[attr-defined]
    with pytest.raises(Invalid) as info:
        make_experiment("huge")
    assert "smoke" in info.value.message
    with pytest.raises(NotFound):
        load_config("no-such-config")


def test_load_config_reads_a_file(tmp_path: Path) -> None:
    path = tmp_path / "grid.yaml"
    path.write_text(GOOD, encoding="utf-8")
    assert load_config(path) == parse_yaml(GOOD)
    # a preset with fields on top
    over = parse_yaml("preset: smoke\nseeds: [5]\n")
    assert over.seeds == (5,) and over.tasks == ("T1", "T6")


def test_the_method_registry_names_the_valid_methods() -> None:
    """Methods invariant 1."""
    assert {"ours", "ours-code", "ours-neural", "s-ecm", "explorer", "am", "spirl", "skimo"} <= set(method_names())
    with pytest.raises(Invalid) as info:
        method_class("nope")
    assert "ours-code" in info.value.message and info.value.details["field"] == "method"
    assert method_class("ours-code").name == "ours-code"
    assert make_method("s-ecm") is not make_method("s-ecm")


def test_ours_refuses_governance_off_and_a_budget_below_one_update() -> None:
    budget = Budget(env_steps_per_iteration=100, eval_episodes=1, horizon=40)
    cell = CellSpec(task="T1", method="ours-code", seed=1, iterations=1, budget=budget, options={"preset": "tiny"})
    with pytest.raises(Invalid) as info:
        make_method("ours-code").evolve_config(cell)  # type: ignore[attr-defined]
    assert info.value.details["field"] == "env_steps_per_iteration"
    off = CellSpec(task="T1", method="ours-code", seed=1, iterations=1, budget=budget, governance=False)
    with pytest.raises(Invalid) as info:
        make_method("ours-code").evolve_config(off)  # type: ignore[attr-defined]
    assert info.value.details["field"] == "governance"
    bad = CellSpec(task="T1", method="ours-code", seed=1, iterations=1, budget=budget, options={"speed": 1})
    with pytest.raises(Invalid) as info:
        make_method("ours-code").evolve_config(bad)  # type: ignore[attr-defined]
    assert info.value.details["field"] == "options.speed"


def test_ours_takes_the_gates_size_and_second_look_from_its_options() -> None:
    budget = Budget(env_steps_per_iteration=80_000, eval_episodes=1)
    options = {"preset": "cpu-small", "gate_episodes": 6, "gate_extension": 20}
    cell = CellSpec(task="T6", method="ours-code", seed=1, iterations=1, budget=budget, options=options)
    config = make_method("ours-code").evolve_config(cell)  # type: ignore[attr-defined]
    assert (config.gate_episodes, config.gate.extend_n, config.gate.min_n) == (6, 20, 6)
    assert config.gate_seeds_max == 26
    default = dataclasses.replace(cell, options={"preset": "cpu-small"})
    preset = make_method("ours-code").evolve_config(default)  # type: ignore[attr-defined]
    assert preset.gate.extend_n == make_config("cpu-small").gate.extend_n
    for bad in (-1, True, 2.5):
        wrong = dataclasses.replace(cell, options={**options, "gate_extension": bad})
        with pytest.raises(Invalid) as info:
            make_method("ours-code").evolve_config(wrong)  # type: ignore[attr-defined]
        assert info.value.details["field"] == "options.gate_extension"


def test_method_entry_round_trip() -> None:
    e = MethodEntry(method="explorer", governance=False, tasks=("T1",), options={"adversaries": ["explorer"]})
    assert e.to_dict() == {
        "method": "explorer",
        "tasks": ["T1"],
        "governance": False,
        "options": {"adversaries": ["explorer"]},
    }
