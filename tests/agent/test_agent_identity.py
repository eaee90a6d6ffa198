"""M_id: the identity YAML, its schema errors and the packaged default.

Identity invariants 1-5; the default's decompositions equal the task specs'.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.agent import Belief, Goal, IdentityMemory, load_identity, parse_identity
from capevo.agent.identity import MAX_IDENTITY_BYTES
from capevo.errors import ErrorCode, Invalid
from capevo.runtime.tasks import all_task_specs

BASE = "version: 1\nname: a\ndecompositions: {pick: [pick.reach, pick.grasp]}\n"


def test_default_decompositions_match_the_task_specs() -> None:
    identity = IdentityMemory.default()
    specs = {s.name: s.ecm_names for s in all_task_specs()}
    assert set(identity.tasks) == set(specs)
    for task, ecms in specs.items():
        assert identity.decomposition(task) == ecms, task


def test_default_has_goals_and_beliefs() -> None:
    identity = IdentityMemory.default()
    assert identity.name == "capevo-default"
    assert {g.id for g in identity.goals} >= {"complete_task", "stay_safe"}
    assert identity.beliefs and all(b.text for b in identity.beliefs)


def test_default_is_a_fresh_copy_each_time() -> None:
    a = IdentityMemory.default()
    object.__setattr__(a, "name", "tampered")
    assert IdentityMemory.default().name == "capevo-default"


def test_yaml_round_trip() -> None:
    identity = IdentityMemory.default()
    assert parse_identity(identity.to_yaml()) == identity
    custom = IdentityMemory(
        name="x",
        description="d",
        goals=(Goal(id="g", text="ü goal"),),
        beliefs=(Belief(id="b", text="b: with colon"),),
        decompositions={"t": ("t.a", "t.b")},
    )
    assert parse_identity(custom.to_yaml()) == custom


def test_parse_and_fields() -> None:
    text = BASE + "goals: [{id: g1, text: Win.}]\nbeliefs: [{id: b1, text: Sky is up.}]\ndescription: hi\n"
    identity = parse_identity(text)
    assert identity == IdentityMemory(
        name="a",
        description="hi",
        goals=(Goal(id="g1", text="Win."),),
        beliefs=(Belief(id="b1", text="Sky is up."),),
        decompositions={"pick": ("pick.reach", "pick.grasp")},
    )
    assert identity.to_dict() == {
        "version": 1,
        "name": "a",
        "description": "hi",
        "goals": [{"id": "g1", "text": "Win."}],
        "beliefs": [{"id": "b1", "text": "Sky is up."}],
        "decompositions": {"pick": ["pick.reach", "pick.grasp"]},
    }


def test_load_identity_from_a_file(tmp_path: Path) -> None:
    path = tmp_path / "id.yaml"
    path.write_text(BASE)
    assert load_identity(path) == parse_identity(BASE)
    assert load_identity(str(path)) == parse_identity(BASE)


def test_records_are_frozen_and_decompositions_read_only() -> None:
    source = {"t": ["t.a"]}
    identity = IdentityMemory(name="x", decompositions=source)  # type: ignore[arg-type]
    source["t"].append("t.b")
    source["u"] = ["u.a"]
    assert dict(identity.decompositions) == {"t": ("t.a",)}
    with pytest.raises(dataclasses.FrozenInstanceError):
        identity.name = "y"  # type: ignore[misc]
    with pytest.raises(TypeError):
        identity.decompositions["t"] = ("t.z",)  # type: ignore[index]
    with pytest.raises(dataclasses.FrozenInstanceError):
        Goal(id="g", text="t").text = "u"  # type: ignore[misc]


SLUG = "must be a slug (lowercase letters, digits, '.', '_', '-'; at most 64), got"


@pytest.mark.parametrize(
    ("text", "field", "message"),
    [
        ("- a", "<document>", "<document>: an identity must be a mapping with version, name and decompositions"),
        ("", "<document>", "<document>: an identity must be a mapping with version, name and decompositions"),
        (
            "name: [",
            "<document>",
            "<document>: not valid YAML at line 1, column 8: expected the node content, but found '<stream end>'",
        ),
        ("name: a\ndecompositions: {pick: [pick.reach]}", "<document>", "<document>: 'version' is a required property"),
        ("version: 2\nname: a\ndecompositions: {pick: [pick.reach]}", "version", "version: 1 was expected"),
        ("version: true\nname: a\ndecompositions: {p: [p.a]}", "version", "version: 1 was expected"),
        (
            BASE + "colour: red\n",
            "<document>",
            "<document>: Additional properties are not allowed ('colour' was unexpected)",
        ),
        ("version: 1\nname: Agent\ndecompositions: {p: [p.a]}", "name", f"name: {SLUG} 'Agent'"),
        ("version: 1\nname: a\ndecompositions: {}", "decompositions", "decompositions: {} should be non-empty"),
        (
            "version: 1\nname: a\ndecompositions: {pick: []}",
            "decompositions.pick",
            "decompositions.pick: [] should be non-empty",
        ),
        (
            "version: 1\nname: a\ndecompositions: {Pick: [p.a]}",
            "decompositions.Pick",
            f"decompositions.Pick: {SLUG} 'Pick'",
        ),
        (
            "version: 1\nname: a\ndecompositions: {pick: [3]}",
            "decompositions.pick[0]",
            "decompositions.pick[0]: 3 is not of type 'string'",
        ),
        (
            "version: 1\nname: a\ndecompositions: {pick: [pick.reach, Pick.Grasp]}",
            "decompositions.pick[1]",
            "decompositions.pick[1]: ECM name 'Pick.Grasp' is not a slug: use lowercase letters, digits, '.', '_' "
            "and '-', starting with a letter or digit, with no '..'",
        ),
        (
            "version: 1\nname: a\ndecompositions: {pick: [pick.reach, pick.grasp, pick.reach]}",
            "decompositions.pick[2]",
            "decompositions.pick[2]: step 'pick.reach' appears twice; each ECM runs at one place in a decomposition",
        ),
        (BASE + "goals: [{id: a, text: x}, {id: a, text: y}]", "goals[1].id", "goals[1].id: duplicate id 'a'"),
        (BASE + "goals: [{id: a}]", "goals[0]", "goals[0]: 'text' is a required property"),
        (BASE + "goals: [{id: A, text: x}]", "goals[0].id", f"goals[0].id: {SLUG} 'A'"),
        (BASE + "beliefs: [{id: a, text: ''}]", "beliefs[0].text", "beliefs[0].text: '' should be non-empty"),
        (BASE + "beliefs: [{id: b, text: x}, {id: b, text: y}]", "beliefs[1].id", "beliefs[1].id: duplicate id 'b'"),
        (BASE + "goals: {id: a, text: x}", "goals", "goals: {'id': 'a', 'text': 'x'} is not of type 'array'"),
    ],
)
def test_identity_errors(text: str, field: str, message: str) -> None:
    with pytest.raises(Invalid) as info:
        parse_identity(text)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == message
    assert info.value.details["field"] == field


def test_oversize_identity_is_refused() -> None:
    text = BASE + "#" * MAX_IDENTITY_BYTES
    with pytest.raises(Invalid) as info:
        parse_identity(text)
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == f"<document>: identity is {len(text)} bytes; the limit is {MAX_IDENTITY_BYTES}"


def test_unreadable_file_is_invalid(tmp_path: Path) -> None:
    with pytest.raises(Invalid) as info:
        load_identity(tmp_path / "missing.yaml")
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == f"<document>: cannot read {tmp_path / 'missing.yaml'}: No such file or directory"


def test_unknown_task_lists_known_ones() -> None:
    with pytest.raises(Invalid) as info:
        parse_identity(BASE).decomposition("stack")
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == "identity 'a' has no decomposition for task 'stack'; known: pick"
    assert info.value.details["valid"] == ["pick"]


def test_task_ids_resolve_to_names() -> None:
    assert IdentityMemory.default().decomposition("T3") == IdentityMemory.default().decomposition("stack")


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=300) | st.binary(max_size=300))
def test_any_input_raises_only_invalid(text: str | bytes) -> None:
    try:
        parse_identity(text)
    except Invalid as exc:
        assert exc.message.startswith(f"{exc.details['field']}: ")


_yaml_scalar = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=12))
_yaml_value = st.recursive(
    _yaml_scalar,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@settings(max_examples=200, deadline=None)
@given(
    st.fixed_dictionaries(
        {"version": st.sampled_from([1, 2, "1"]), "name": st.sampled_from(["a", "A", 3])},
        optional={"decompositions": _yaml_value, "goals": _yaml_value, "beliefs": _yaml_value, "x": _yaml_value},
    )
)
def test_any_document_shape_raises_only_invalid(doc: dict[str, object]) -> None:
    from capevo.agent.identity import identity_from_document

    try:
        identity_from_document(doc)
    except Invalid as exc:
        assert exc.message.startswith(f"{exc.details['field']}: ")
