"""Φ from YAML: defaults, the canonical hash, round trips, and every kind of bad input."""

from __future__ import annotations

import contextlib
import hashlib
import json
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.governance import (
    Aabb,
    ContactForce,
    ForbiddenZone,
    Phi,
    VelocityCap,
    WorkspaceBox,
    constraint_kinds,
    load_phi,
    make,
    phi_from_document,
)

PACKAGED = Path(__file__).resolve().parents[3] / "capevo" / "runtime" / "governance" / "default_phi.yaml"


def test_default_phi_is_the_papers_envelope_from_the_packaged_yaml() -> None:
    phi = Phi.default()
    assert phi == Phi((WorkspaceBox(), ContactForce(), VelocityCap()))
    box, force, cap = phi.constraints
    assert (box.low, box.high, box.margin) == ((-0.6, -0.6, 0.6), (0.6, 0.6, 1.3), 0.08)
    assert force.max_force == 20.0 and cap.max_norm == 1.5
    assert load_phi(PACKAGED) == phi and load_phi(str(PACKAGED)).hash == phi.hash
    assert phi.labels == ("workspace_box", "contact_force", "velocity_cap")


def test_hash_is_sha256_of_the_canonical_normalized_config() -> None:
    phi = Phi.default()
    canonical = json.dumps(phi.to_dict(), sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    assert phi.hash == hashlib.sha256(canonical.encode()).hexdigest()
    assert len(phi.hash) == 64


def test_hash_ignores_spelling_and_sees_meaning() -> None:
    base = load_phi("constraints: [{kind: workspace_box}, {kind: velocity_cap}]")
    same = [
        "version: 1\nconstraints:\n  - {kind: workspace_box, margin: 0.08}\n  - {max_norm: 1.5, kind: velocity_cap}\n",
        "# comment\nconstraints: [{kind: workspace_box, low: [-0.6, -0.6, 0.6], high: [0.6, 0.6, 1.3]}, "
        "{kind: velocity_cap, max_norm: 1.50, name: null}]",
        '{"constraints": [{"kind": "workspace_box", "margin": 8.0e-2}, {"kind": "velocity_cap"}]}',
    ]
    for text in same:
        assert load_phi(text).hash == base.hash, text
    different = [
        "constraints: [{kind: workspace_box, margin: 0.07}, {kind: velocity_cap}]",
        "constraints: [{kind: velocity_cap}, {kind: workspace_box}]",  # order matters: R applies in order
        "constraints: [{kind: workspace_box, name: box}, {kind: velocity_cap}]",
        "constraints: [{kind: workspace_box}]",
    ]
    hashes = {load_phi(t).hash for t in different}
    assert base.hash not in hashes and len(hashes) == len(different)


def test_ints_and_floats_normalize_to_the_same_constraint() -> None:
    assert make("velocity_cap", max_norm=2) == VelocityCap(max_norm=2.0) == VelocityCap(max_norm=2)  # type: ignore[arg-type]
    expected = WorkspaceBox(low=(-1.0, -1.0, 0.0), high=(1.0, 1.0, 2.0))
    assert make("workspace_box", low=[-1, -1, 0], high=[1, 1, 2]) == expected
    assert type(VelocityCap(max_norm=2).max_norm) is float  # type: ignore[arg-type]


CONFIGS = st.lists(
    st.one_of(
        st.builds(
            lambda lo, size, m: WorkspaceBox(
                low=lo, high=tuple(a + b for a, b in zip(lo, size, strict=True)), margin=m
            ),
            st.tuples(*[st.floats(-5, 5)] * 3),
            st.tuples(*[st.floats(0.01, 5)] * 3),
            st.floats(0, 1),
        ),
        st.builds(lambda v: VelocityCap(max_norm=v), st.floats(0.001, 100)),
        st.builds(lambda v: ContactForce(max_force=v), st.floats(0.001, 1000)),
        st.builds(
            lambda lo, m: ForbiddenZone(boxes=(Aabb(low=lo, high=tuple(x + 0.5 for x in lo)),), margin=m),
            st.tuples(*[st.floats(-5, 5)] * 3),
            st.floats(0, 1),
        ),
    ),
    max_size=6,
)


@settings(max_examples=150, deadline=None)
@given(constraints=CONFIGS)
def test_yaml_round_trip_keeps_value_and_hash(constraints) -> None:
    named = tuple(
        type(c)(**{**{f: getattr(c, f) for f in c.to_config()}, "name": f"c{i}"}) for i, c in enumerate(constraints)
    )
    phi = Phi(named)
    back = load_phi(phi.to_yaml())
    assert back == phi and back.hash == phi.hash
    assert phi_from_document(json.loads(json.dumps(phi.to_dict()))) == phi


def _invalid(text: str) -> Invalid:
    with pytest.raises(Invalid) as e:
        load_phi(text)
    assert e.value.code is ErrorCode.INVALID
    assert e.value.message.startswith(e.value.details["field"] + ":") or e.value.details["field"] == "<document>"
    return e.value


@pytest.mark.parametrize(
    ("text", "field", "message"),
    [
        (
            "constraints: [{kind: workspace_box, margn: 0.1}]",
            "constraints[0].margn",
            "constraints[0].margn: unknown key; valid keys: high, low, margin, name",
        ),
        (
            "constraints: [{kind: velocity_cap}, {kind: contact_force, max_force: 20, limit: 3}]",
            "constraints[1].limit",
            "constraints[1].limit: unknown key; valid keys: max_force, name",
        ),
        (
            "constraints: [{kind: workspace_bx}]",
            "constraints[0].kind",
            "constraints[0].kind: unknown constraint kind 'workspace_bx'; valid kinds: "
            "arm_separation, closing_grip, contact_approach, contact_force, forbidden_zone, force_ramp, "
            "keep_clear, obstacle_approach, reach_limit, stopping_distance, surface_approach, velocity_cap, "
            "workspace_box, workspace_guard",
        ),
        ("constraints: [{max_norm: 1}]", "constraints[0].kind", "constraints[0].kind: unknown constraint kind None"),
        (
            "constraints: [{kind: velocity_cap, max_norm: fast}]",
            "constraints[0].max_norm",
            "constraints[0].max_norm: expected a number, got str",
        ),
        (
            "constraints: [{kind: velocity_cap, max_norm: true}]",
            "constraints[0].max_norm",
            "constraints[0].max_norm: expected a number, got bool",
        ),
        (
            "constraints: [{kind: velocity_cap, max_norm: .nan}]",
            "constraints[0].max_norm",
            "constraints[0].max_norm: must be a finite number, got nan",
        ),
        (
            "constraints: [{kind: velocity_cap, max_norm: 0}]",
            "constraints[0].max_norm",
            "constraints[0].max_norm: must be > 0, got 0.0",
        ),
        (
            "constraints: [{kind: contact_force, max_force: -1}]",
            "constraints[0].max_force",
            "constraints[0].max_force: must be > 0, got -1.0",
        ),
        (
            "constraints: [{kind: workspace_box, low: [0, 0]}]",
            "constraints[0].low",
            "constraints[0].low: expected a list of 3 values, got 2",
        ),
        (
            "constraints: [{kind: workspace_box, low: [0, 0, .inf]}]",
            "constraints[0].low[2]",
            "constraints[0].low[2]: must be a finite number, got inf",
        ),
        (
            "constraints: [{kind: workspace_box, low: [0, 0, 2]}]",
            "constraints[0].high",
            "constraints[0].high: high.z (1.3) must be above low.z (2.0)",
        ),
        (
            "constraints: [{kind: workspace_box, margin: -0.1}]",
            "constraints[0].margin",
            "constraints[0].margin: must be >= 0, got -0.1",
        ),
        (
            "constraints: [{kind: forbidden_zone}]",
            "constraints[0].boxes",
            "constraints[0].boxes: required key is missing",
        ),
        (
            "constraints: [{kind: forbidden_zone, boxes: []}]",
            "constraints[0].boxes",
            "constraints[0].boxes: at least one box is required",
        ),
        (
            "constraints: [{kind: forbidden_zone, boxes: [{low: [0, 0, 0], high: [1, 1, 1], size: 2}]}]",
            "constraints[0].boxes[0].size",
            "constraints[0].boxes[0].size: unknown key; valid keys: high, low",
        ),
        (
            "constraints: [{kind: forbidden_zone, boxes: [{low: [0, 0, 0], high: [1, 0, 1]}]}]",
            "constraints[0].boxes[0].high",
            "constraints[0].boxes[0].high: high.y (0.0) must be above low.y (0.0)",
        ),
        (
            "constraints: [{kind: forbidden_zone, boxes: [{low: [0, 0, 0]}]}]",
            "constraints[0].boxes[0].high",
            "constraints[0].boxes[0].high: required key is missing",
        ),
        (
            "constraints: [{kind: velocity_cap}, {kind: velocity_cap}]",
            "constraints[1].name",
            "constraints[1].name: label 'velocity_cap' is used twice; give one of them a distinct name",
        ),
        (
            "constraints: [{kind: velocity_cap, name: governor}]",
            "constraints[0].name",
            "constraints[0].name: 'governor' is reserved for the governor's own input checks",
        ),
        (
            "constraints: [{kind: velocity_cap, name: 'has space'}]",
            "constraints[0].name",
            "constraints[0].name: 'has space' is not a label: use 1-64 letters, digits, '_', '.' or '-'",
        ),
        ("constraints: [3]", "constraints[0]", "constraints[0]: expected a mapping with a 'kind'"),
        ("constraints: {kind: velocity_cap}", "constraints", "constraints: expected a list of constraints"),
        ("version: 2\nconstraints: []", "version", "version: unsupported Φ format version 2; expected 1"),
        ("constraints: []\nextra: 1", "extra", "extra: unknown key; valid keys: constraints, version"),
        ("- a\n- b", "<document>", "<document>: Φ must be a mapping with 'version' and 'constraints'"),
        ("constraints: [", "<document>", "<document>: not valid YAML at line 1, column 15: expected the node content"),
        (
            "constraints: [{kind: velocity_cap, max_norm: 15e-1}]",
            "constraints[0].max_norm",
            "constraints[0].max_norm: expected a number, got str '15e-1' (YAML reads an exponent without a '.' "
            "as text; write 1.5)",
        ),
        ("missing_file.yaml", "<document>", "<document>: missing_file.yaml is not a file"),
    ],
)
def test_bad_phi_documents_raise_invalid_naming_the_field(text: str, field: str, message: str) -> None:
    err = _invalid(text)
    assert err.details["field"] == field
    assert err.message.startswith(message), err.message


def test_make_builds_exactly_what_yaml_loads() -> None:
    zone = {"boxes": [{"low": [0, 0, 0], "high": [1, 1, 1]}], "margin": 0.1, "name": "shelf"}
    loaded = load_phi(yaml.safe_dump({"constraints": [{"kind": "forbidden_zone", **zone}]}))
    assert make("forbidden_zone", **zone) == loaded.constraints[0]
    assert make("workspace_box") == WorkspaceBox() == Phi.default().constraints[0]


def test_make_lists_valid_kinds_for_an_unknown_one() -> None:
    with pytest.raises(Invalid) as e:
        make("speed_limit")
    assert e.value.code is ErrorCode.INVALID
    valid = ", ".join(constraint_kinds())
    assert e.value.message == f"kind: unknown constraint kind 'speed_limit'; valid kinds: {valid}"
    assert {"workspace_box", "velocity_cap", "contact_force", "forbidden_zone"} <= set(e.value.details["valid"])
    with pytest.raises(Invalid) as e:
        make("velocity_cap", max_nrom=1.0)
    assert e.value.message == "max_nrom: unknown key; valid keys: max_norm, name"


def test_oversize_and_unreadable_sources_are_invalid(tmp_path: Path) -> None:
    big = "constraints: []\n" + "#" * (64 * 1024)
    assert _invalid(big).message.startswith("<document>: Φ is ")
    (tmp_path / "big.yaml").write_text(big)
    assert "the limit is 65536" in _invalid(str(tmp_path / "big.yaml")).message
    with pytest.raises(Invalid) as e:
        load_phi(tmp_path)  # a directory
    assert e.value.message.startswith("<document>: cannot read")


def test_load_from_path_and_from_bytes(tmp_path: Path) -> None:
    p = tmp_path / "phi.yaml"
    p.write_text(Phi.default().to_yaml())
    assert load_phi(p) == load_phi(str(p)) == load_phi(p.read_bytes()) == Phi.default()


DOCS = st.recursive(
    st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4),
    max_leaves=20,
)
KEYS = st.sampled_from(["kind", "name", "low", "high", "margin", "max_norm", "max_force", "boxes", "x"])
KINDS = st.sampled_from(["workspace_box", "velocity_cap", "contact_force", "forbidden_zone", "nope"])
ENTRIES = st.builds(lambda kind, rest: {**rest, "kind": kind}, KINDS, st.dictionaries(KEYS, DOCS, max_size=4))


@settings(max_examples=300, deadline=None)
@given(doc=st.one_of(DOCS, st.builds(lambda e: {"constraints": e}, st.lists(ENTRIES, max_size=3))))
def test_loading_any_document_raises_only_invalid(doc) -> None:
    try:
        phi = phi_from_document(doc)
    except Invalid as exc:
        assert exc.code is ErrorCode.INVALID
        assert exc.message.startswith(exc.details["field"] + ":")
        return
    assert load_phi(phi.to_yaml()) == phi


@settings(max_examples=200, deadline=None)
@given(text=st.text(max_size=200))
def test_loading_any_text_raises_only_invalid(text) -> None:
    with contextlib.suppress(Invalid):
        load_phi(text)


def test_to_yaml_is_readable_and_omits_unset_names() -> None:
    text = Phi.default().to_yaml()
    assert "name" not in text
    assert yaml.safe_load(text)["constraints"][0] == {
        "kind": "workspace_box",
        "low": [-0.6, -0.6, 0.6],
        "high": [0.6, 0.6, 1.3],
        "margin": 0.08,
    }
