"""The best hand-set parameters: what a person gets by fixing v0's listed weaknesses by hand.

Issue 19 asks every evolution report for this row, so the report shows what search adds beyond
the obvious. Version 0 of each skill is deliberately mis-set, and its docstring lists its
"known weaknesses". The values here are those fixes, written once by reading the docstrings,
with round numbers and *without* running or searching anything. They are not tuned on any
seeds, held-out or otherwise, and were not changed after seeing a result. Each value says which
weakness it answers.

Steps are keyed by the last part of the ECM name (``reach``, ``grasp``, ...), so T5's objects share
them. A task or step missing here keeps its v0 parameters (the report says so).

Invariants:
1. Every override names a parameter the step's v0 declares, with a value inside its ``PARAM_RANGES``.
2. :func:`hand_set_specs` differs from :func:`~capevo.learner.skills.seed_specs` only in ``PARAMS``.
"""

from __future__ import annotations

from collections.abc import Mapping

from capevo.errors import Invalid
from capevo.learner.skills import seed_specs
from capevo.records import EcmVersion, PublishSpec
from capevo.registry.api import Registry
from capevo.runtime.ecm.code import with_params
from capevo.runtime.tasks import task_spec

_GRASPING: Mapping[str, Mapping[str, float]] = {
    # "aims grasp_dz = 3 cm above the object origin ... its gain is low": aim at the origin, gain 10
    "reach": {"grasp_dz": 0.0, "gain": 10.0},
    # "same too-high grasp_dz as reach, low gain, closes late": origin, gain 10, close within 2 cm
    "grasp": {"grasp_dz": 0.0, "gain": 10.0, "close_above": 0.02},
    # "lift rises slowly (0.2 of full speed)": half speed
    "lift": {"lift_speed": 0.5},
}

HAND_SET: Mapping[str, Mapping[str, Mapping[str, float]]] = {
    "pick": _GRASPING,
    "place": {
        **_GRASPING,
        # "carries too low for the rims (5 cm), low gain": 15 cm above the goal, gain 10
        "move": {"carry_dz": 0.15, "gain": 10.0},
        # "lets go from 10 cm, low gain": 3 cm, gain 10
        "release": {"release_dz": 0.03, "gain": 10.0},
    },
    "stack": {
        **_GRASPING,
        # "high carry, low gain, direct A-to-B observation mostly ignored": 5 cm, gain 10, and
        # the 2/3 weight the module docstring says halves the variance
        "align": {"carry_dz": 0.05, "gain": 10.0, "rel_weight": 0.67},
        # "aims 1 cm too high, low gain": the touching height 4.5 cm, gain 10, the same weight
        "lower": {"stack_dz": 0.045, "gain": 10.0, "rel_weight": 0.67},
    },
}
HAND_SET["pick_place_multi"] = HAND_SET["place"]
HAND_SET["nut_assembly"] = {
    # "reach and grasp aim grasp_dz = 3 cm above the handle, with a low gain (3)": the handle, gain 10
    "reach": {"grasp_dz": 0.0, "gain": 10.0},
    "grasp": {"grasp_dz": 0.0, "gain": 10.0, "close_above": 0.02},
    # "the lift is slow (0.2 of full speed)": half speed
    "lift": {"lift_speed": 0.5},
    # "carries the nut only 10 cm above its seated height: the peg's top is 13 cm above it": 18 cm
    "align": {"carry_dz": 0.18, "gain": 10.0},
    # "insert's gain is low"
    "insert": {"gain": 10.0},
}


def _peg_gains(v0: Mapping[str, float]) -> dict[str, float]:
    """T6: "the gains are low (0.2-0.3 per radian, 1-2 per metre)": every gain v0 uses (non-zero)
    becomes 1 per radian or 5 per metre; a gain v0 leaves at 0 stays 0 (that arm holds still)."""
    out = {}
    for name, value in v0.items():
        if name.endswith("_rot_gain") and value:
            out[name] = 1.0
        elif name.endswith("_gain") and value:
            out[name] = 5.0
    return out


def hand_set_overrides(task: str) -> dict[str, dict[str, float]]:
    """The hand-set parameter overrides of each ECM of ``task`` (empty for a step left at v0)."""
    spec = task_spec(task)
    if spec.name == "peg_in_hole":
        from capevo.learner.skills import seed_params

        return {ecm: _peg_gains(seed_params(spec.name, ecm)) for ecm in spec.ecm_names}
    table = HAND_SET.get(spec.name, {})
    return {ecm: dict(table.get(ecm.split(".")[-1], {})) for ecm in spec.ecm_names}


def hand_set_specs(task: str) -> list[tuple[str, str, PublishSpec]]:
    """``(ecm, source, publish spec)`` of the hand-set version of every ECM of ``task``, in plan order.

    Raises:
        Invalid: an override of a parameter the skill does not declare.
    """
    overrides = hand_set_overrides(task)
    out = []
    for name, source, spec in seed_specs(task):
        values = overrides[name]
        out.append((name, with_params(source, values, filename=name) if values else source, spec))
    return out


def seed_hand_set(registry: Registry, task: str, *, reason: str = "hand-set parameters") -> list[EcmVersion]:
    """Publish and promote the hand-set version of every ECM of ``task`` in an empty registry.

    Raises:
        Invalid: the registry already holds an ECM of the task (the hand-set row needs its own).
    """
    existing = {s.name for s in registry.list_ecms()}
    names = task_spec(task).ecm_names
    if existing & set(names):
        raise Invalid(
            f"the registry already has {sorted(existing & set(names))}; hand-set versions need a registry of their own",
            details={"field": "registry"},
        )
    out = []
    for name, source, spec in hand_set_specs(task):
        record = registry.publish(name, source.encode(), spec)
        out.append(registry.promote(name, record.version, reason=reason))
    return out
