"""Every built-in skill declares a physical search span for each of its parameters (issue 19).

Without a declared span CEM searches v0 ± 3 × |v0| and freezes a parameter that is 0 in v0 (T4 and T6
declared none). These tests read the skills two ways: every :class:`SkillTemplate` defined in any module
of :mod:`capevo.learner.skills` (found by walking the package, so a new module is covered without being
listed here), and the rendered v0 source of every ECM of every task, as CEM reads it.
"""

from __future__ import annotations

import importlib
import math
import pkgutil

import pytest

import capevo.learner.skills as skills_pkg
from capevo.learner.search import param_space, read_ranges
from capevo.learner.skills import seed_specs, skill_tasks
from capevo.learner.skills._lib import SkillTemplate, provenance_note
from capevo.runtime.ecm.code import read_params


def _templates() -> list[tuple[str, SkillTemplate]]:
    """Every SkillTemplate a module of the skills package defines at module level (or builds in a table)."""
    found: dict[int, tuple[str, SkillTemplate]] = {}
    for info in pkgutil.iter_modules(skills_pkg.__path__):
        module = importlib.import_module(f"{skills_pkg.__name__}.{info.name}")
        for attr, value in vars(module).items():
            if isinstance(value, SkillTemplate):
                found.setdefault(id(value), (f"{info.name}.{attr}", value))
            elif isinstance(value, dict) or hasattr(value, "items"):
                try:
                    items = list(value.items())
                except TypeError:
                    continue
                for key, v in items:
                    if isinstance(v, SkillTemplate):
                        found.setdefault(id(v), (f"{info.name}.{attr}[{key!r}]", v))
    return sorted(found.values(), key=lambda x: x[0])


TEMPLATES = _templates()


def test_the_walk_finds_every_family() -> None:
    modules = {name.split(".")[0] for name, _ in TEMPLATES}
    # one module per task family plus the shared grasping steps
    assert {"grasping", "pick_place", "stack", "nut_assembly", "peg_in_hole"} <= modules
    assert len(TEMPLATES) >= 20


@pytest.mark.parametrize(("name", "template"), TEMPLATES, ids=[n for n, _ in TEMPLATES])
def test_every_template_parameter_has_a_range_containing_v0(name: str, template: SkillTemplate) -> None:
    missing = sorted(set(template.params) - set(template.ranges))
    assert not missing, f"{name}: no PARAM_RANGES for {missing}"
    extra = sorted(set(template.ranges) - set(template.params))
    assert not extra, f"{name}: ranges for parameters it does not have: {extra}"
    for key, r in template.ranges.items():
        low, high = float(r[0]), float(r[1])
        assert low < high, f"{name}.{key}: empty range {r}"
        assert low <= float(template.params[key]) <= high, f"{name}.{key}: v0 {template.params[key]} outside {r}"
        if r[2:] == ("log",):
            assert low > 0, f"{name}.{key}: a log range needs low > 0"


@pytest.mark.parametrize("task", skill_tasks())
def test_rendered_sources_declare_what_cem_reads(task: str) -> None:
    for ecm, source, _spec in seed_specs(task):
        params = read_params(source, filename=ecm)
        ranges = read_ranges(source, filename=ecm)
        assert set(ranges) == set(params), f"{ecm}: PARAM_RANGES {sorted(ranges)} != PARAMS {sorted(params)}"
        for key, r in ranges.items():
            assert r.low <= params[key] <= r.high, f"{ecm}.{key}: v0 {params[key]} outside [{r.low}, {r.high}]"
        # CEM's search box: every parameter gets a positive step, so none is frozen (a 0 in v0 included)
        space = param_space(params, ranges=ranges)
        frozen = [n for n, s, lo, hi in zip(space.names, space.scale, space.low, space.high, strict=True) if not s > 0]
        assert not frozen, f"{ecm}: frozen parameters {frozen}"
        assert all(math.isfinite(x) for x in space.low + space.high)


@pytest.mark.parametrize("task", skill_tasks())
def test_rendered_docstrings_say_what_is_learned_and_what_is_hand_written(task: str) -> None:
    for ecm, source, _spec in seed_specs(task):
        doc = source.split('"""')[1]
        assert "Learned:" in doc and "Hand-written:" in doc, ecm
        # the note names exactly this skill's parameters
        for key in read_params(source, filename=ecm):
            assert key in " ".join(doc.split()), f"{ecm}: {key} not named in its docstring"


def test_the_note_lists_the_parameters_in_order() -> None:
    template = SkillTemplate(doc="x", params={"b": 1.0, "a": 2.0}, body="")
    assert "PARAMS (b, a)" in provenance_note(template)
