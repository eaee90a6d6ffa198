"""Key space, wire codec, Zenoh config and server config: the parts that need no network."""

from __future__ import annotations

import contextlib
import json
import math
import os
import stat
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import CapevoError, Invalid, TooLarge
from capevo.records import AuditEvent, EcmVersion
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.keys import COMMANDS, READ_ENDPOINTS, Keys, Route, validate_namespace
from capevo.registry.server_config import (
    ROLES,
    ServerConfig,
    access_control_for,
    make_role,
    parse_server_config,
    write_dictionary,
)
from capevo.registry.service import COMMAND_HANDLERS, READ_HANDLERS
from capevo.registry.wire import (
    MAX_JSON_BYTES,
    UploadPart,
    decode_command,
    decode_event,
    decode_reply,
    encode_command,
    encode_event,
    list_of,
    loads,
    read_parameters,
    spec_from_wire,
)
from capevo.registry.zconfig import client_config, config_from_flags, router_config, split_endpoints

SPEC = parse_publish_spec(
    """
kind: code
description: unit skill
applicability: {text: t, all: [{signal: h, op: "<", value: 0.05}]}
interface: {inputs: [{name: eef_pos, shape: [3]}], outputs: [{name: action, shape: [7], low: -1, high: 1}]}
parent: 2
provenance: {learner_id: sac, traces: [a.mcap]}
"""
)
NAMES = st.from_regex(r"[a-z0-9][a-z0-9_-]{0,20}", fullmatch=True).filter(lambda n: n not in {"active", "history"})
VERSIONS = st.integers(min_value=0, max_value=10**17)


# --- keys --------------------------------------------------------------------------------------
@given(name=NAMES, version=st.one_of(st.none(), VERSIONS))
def test_keys_parse_back_to_what_was_built(name: str, version: int | None) -> None:  # keys invariant 1
    keys = Keys("lab/robot-1")
    assert keys.parse_read_key(keys.ecm_list()) == Route(endpoint="list")
    assert keys.parse_read_key(keys.ecm(name)) == Route(endpoint="ecm", name=name)
    assert keys.parse_read_key(keys.version(name, version)) == Route(endpoint="version", name=name, version=version)
    assert keys.parse_read_key(keys.artifact(name, version)) == Route(endpoint="artifact", name=name, version=version)
    assert keys.parse_read_key(keys.history(name)) == Route(endpoint="history", name=name)
    assert keys.parse_read_key(keys.history_all()) == Route(endpoint="history")
    for endpoint, key in (("set", keys.capability_set()), ("verify", keys.verify()), ("info", keys.info())):
        assert keys.parse_read_key(key) == Route(endpoint=endpoint)
    for op in COMMANDS:
        assert keys.parse_cmd_key(keys.cmd(op)) == op


@settings(max_examples=300)
@given(key=st.text(max_size=80))
def test_parsing_any_key_raises_only_invalid(key: str) -> None:  # keys invariant 2
    keys = Keys()
    for parse in (keys.parse_read_key, keys.parse_cmd_key):
        with contextlib.suppress(Invalid):
            parse(key)


@pytest.mark.parametrize(
    "key",
    [
        "capevo/ecm/reach/007",
        "capevo/ecm/reach/+7",
        "capevo/ecm/reach/٧",
        "capevo/ecm/reach/1234567890123456789",
        "capevo/ecm/reach/0/blob",
        "capevo/ecm/reach/history/x",
        "capevo/ecm/../0",
        "capevo/ecm/Reach",
        "capevo/ecm/*",
        "capevo/ecm/**",
        "capevo/ecm/$*",
        "other/ecm/reach",
        "capevo",
        "capevo/set/x",
    ],
)
def test_refused_keys(key: str) -> None:  # keys invariant 2
    with pytest.raises(Invalid):
        Keys().parse_read_key(key)


@given(name=NAMES, version=st.one_of(st.none(), VERSIONS))
def test_built_keys_are_concrete_key_expressions(name: str, version: int | None) -> None:  # keys invariant 3
    keys = Keys()
    built = [keys.ecm_list(), keys.ecm(name), keys.version(name, version), keys.artifact(name, version)]
    built += [keys.history(name), keys.capability_set(), keys.verify(), keys.events(name), keys.alive()]
    built += [keys.cmd(op) for op in COMMANDS]
    for key in built:
        assert str(zenoh.KeyExpr(key)) == key and "*" not in key
    assert keys.events("*") == "capevo/events/*"


@pytest.mark.parametrize("namespace", ["", "a/", "/a", "a//b", "a/*", "a/**", "a/$*", "a b", "a/..", "x" * 129, 7])
def test_bad_namespaces(namespace: Any) -> None:
    with pytest.raises(Invalid) as info:
        validate_namespace(namespace)
    assert info.value.details["field"] == "namespace"


def test_every_endpoint_and_command_has_a_handler() -> None:
    assert set(READ_HANDLERS) == set(READ_ENDPOINTS)
    assert set(COMMAND_HANDLERS) == set(COMMANDS)


# --- wire --------------------------------------------------------------------------------------
VALID_FIELDS: dict[str, dict[str, Any]] = {
    "publish": {"name": "reach", "spec": SPEC, "actor": "me", "part": UploadPart("0a" * 16, 0, 3 * 2**20)},
    "promote": {"name": "reach", "version": 3, "expected_active": 2, "reason": "better", "actor": None},
    "rollback": {"name": "reach", "to": None, "expected_active": 4, "reason": "", "actor": "op"},
    "deprecate": {"name": "reach", "version": 1, "reason": "old", "actor": None},
    "reject": {"name": "reach", "version": 1, "reason": "failed", "actor": "gate"},
    "gate": {"name": "reach", "version": 1, "evidence": {"sr": 0.9, "curve": [1, 2]}, "reason": "", "actor": None},
}


@pytest.mark.parametrize("op", COMMANDS)
def test_commands_round_trip(op: str) -> None:  # wire invariant 1
    assert decode_command(op, encode_command(op, **VALID_FIELDS[op])) == VALID_FIELDS[op]


def test_a_publish_without_part_is_one_payload() -> None:
    fields = {"name": "reach", "spec": SPEC, "actor": None}
    assert decode_command("publish", encode_command("publish", **fields)) == {**fields, "part": None}


def test_only_the_first_part_carries_the_spec() -> None:
    later = {"name": "reach", "spec": None, "actor": None, "part": UploadPart("0a" * 16, 2**20, 3 * 2**20)}
    assert decode_command("publish", encode_command("publish", **later)) == later
    with pytest.raises(Invalid, match="'spec' goes in the first part's header only"):
        encode_command("publish", **{**later, "spec": SPEC})
    with pytest.raises(Invalid, match="missing field 'spec'"):
        encode_command("publish", **{**later, "part": UploadPart("0a" * 16, 0, 3)})
    with pytest.raises(Invalid, match="missing field 'spec'"):
        decode_command("publish", b'{"name": "reach"}')


def test_optional_fields_default() -> None:
    assert decode_command("promote", b'{"name": "reach", "version": 0}') == {
        "name": "reach",
        "version": 0,
        "expected_active": None,
        "reason": "",
        "actor": None,
    }


@pytest.mark.parametrize(
    ("op", "fields", "message"),
    [
        ("promote", {"name": "reach", "version": 2**63}, "version must be at most 9223372036854775807"),
        ("promote", {"name": "reach", "version": 0, "expected_active": -1}, "version must be a non-negative"),
        ("gate", {"name": "reach", "version": 0, "evidence": {"x": math.nan}}, "evidence.x: must be a finite number"),
        ("reject", {"name": "reach", "version": 0, "reason": "r" * 4097}, "reason is 4097 characters"),
        ("deprecate", {"name": "reach", "version": 0, "actor": 3}, "actor must be a string"),
        ("promote", {"name": "reach", "version": 0, "extra": 1}, "promote request: unknown field 'extra'"),
        ("publish", {"name": "reach", "spec": {"kind": "code"}}, "spec.descriptor: must be a JSON object"),
        ("publish", {"name": "reach", "spec": SPEC, "part": []}, "part: must be a JSON object"),
        ("publish", {"name": "reach", "spec": SPEC, "part": {"upload": "0" * 32, "offset": 0}}, "part.total: missing"),
        ("publish", {"name": "reach", "spec": SPEC, "part": {"upload": "A" * 32, "offset": 0, "total": 1}}, "hex"),
        (
            "publish",
            {"name": "reach", "spec": SPEC, "part": {"upload": "0" * 32, "offset": 5, "total": 5}},
            "not below",
        ),
        ("publish", {"name": "reach", "spec": SPEC, "part": {"upload": "0" * 32, "offset": 0, "total": 0}}, "from 1"),
        (
            "publish",
            {"name": "reach", "spec": SPEC, "part": {"upload": "0" * 32, "offset": True, "total": 2}},
            "offset",
        ),
    ],
)
def test_encode_runs_the_server_checks(op: str, fields: dict[str, Any], message: str) -> None:  # wire invariant 1
    with pytest.raises(Invalid) as info:
        encode_command(op, **fields)
    assert message in info.value.message


def test_spec_from_wire_is_the_inverse_of_to_dict() -> None:
    assert spec_from_wire(SPEC.to_dict()) == SPEC
    bad = SPEC.to_dict()
    bad["interface"]["inputs"][0]["shape"] = [0]
    with pytest.raises(Invalid) as info:
        spec_from_wire(bad)
    assert info.value.message.startswith("spec: interface.inputs[0].shape[0]")
    assert info.value.details["field"] == "spec.interface.inputs[0].shape[0]"


@settings(max_examples=300)
@given(data=st.binary(max_size=200), op=st.sampled_from(COMMANDS))
def test_decoding_untrusted_bytes_raises_only_invalid(data: bytes, op: str) -> None:  # wire invariant 2
    with contextlib.suppress(Invalid, TooLarge):
        decode_command(op, data)


@settings(max_examples=200)
@given(
    doc=st.recursive(
        st.none() | st.booleans() | st.integers() | st.text(max_size=5),
        lambda c: st.lists(c) | st.dictionaries(st.text(max_size=5), c),
        max_leaves=10,
    ),
    op=st.sampled_from(COMMANDS),
)
def test_decoding_any_json_raises_only_invalid(doc: Any, op: str) -> None:  # wire invariant 2
    with contextlib.suppress(Invalid):
        decode_command(op, json.dumps(doc).encode())


def test_loads_limits() -> None:
    with pytest.raises(TooLarge):
        loads(b" " * (MAX_JSON_BYTES + 1), what="x")
    with pytest.raises(Invalid, match="empty body"):
        loads(None, what="x")


def test_read_parameters() -> None:
    assert read_parameters("set", [("revision", "3"), ("_anyke", "")]) == {"revision": 3}
    for pairs in ([("revision", "03")], [("revision", "-1")], [("rev", "1")], [("revision", "1"), ("revision", "1")]):
        with pytest.raises(Invalid):
            read_parameters("set", pairs)
    with pytest.raises(Invalid, match="allowed: none"):
        read_parameters("ecm", [("revision", "1")])


def _record_and_event() -> tuple[AuditEvent, EcmVersion]:
    record = EcmVersion.from_dict(
        {
            "name": "reach",
            "version": 0,
            "kind": "code",
            "state": "candidate",
            "artifact": {"sha256": "a" * 64, "size": 1, "media_type": "text/x-python"},
            "descriptor": SPEC.descriptor.to_dict(),
            "interface": SPEC.interface.to_dict(),
            "parent": None,
            "origin": "manual",
            "provenance": {},
            "gate_evidence": None,
            "created_at": 1.5,
            "created_by": "me",
        }
    )
    event = AuditEvent.from_dict(
        {
            "seq": 1,
            "name": "reach",
            "action": "publish",
            "version": 0,
            "from_state": None,
            "to_state": "candidate",
            "from_version": None,
            "to_version": None,
            "actor": "me",
            "reason": "",
            "at": 1.5,
            "data": {"sha256": "a" * 64},
            "revision": None,
            "prev_hash": "0" * 64,
            "hash": "b" * 64,
        }
    )
    return event, record


def test_events_round_trip_and_junk_replies_are_capevo_errors() -> None:  # wire invariant 3
    event, record = _record_and_event()
    assert decode_event(encode_event(event, record)) == (event, record)
    for junk in (b"", b"\xff", b"[]", b'{"event": {}}', b"null"):
        with pytest.raises(CapevoError) as info:
            decode_event(junk)
        assert type(info.value) is CapevoError and info.value.message.startswith("malformed event reply")
    with pytest.raises(CapevoError, match="malformed list reply"):
        decode_reply(b"{}", list_of(EcmVersion.from_dict), what="list")


# --- zenoh config ------------------------------------------------------------------------------
def test_router_and_client_configs() -> None:  # zconfig invariants 1, 3
    router = router_config(listen=["tcp/127.0.0.1:7447"])
    assert json.loads(router.get_json("mode")) == "router"
    assert json.loads(router.get_json("scouting/multicast/enabled")) is False
    assert json.loads(router.get_json("scouting/delay")) == 0
    client = client_config(connect="tcp/127.0.0.1:7447", user="u", password="p w")
    assert json.loads(client.get_json("mode")) == "client"
    assert json.loads(client.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(client.get_json("scouting/multicast/enabled")) is False
    with pytest.raises(Invalid):
        client_config(connect=[])
    flags = config_from_flags(mode="peer", listen=["tcp/127.0.0.1:1,tcp/127.0.0.1:2"], multicast_scouting=True)
    assert json.loads(flags.get_json("listen/endpoints")) == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"]
    assert split_endpoints([" a/b , ", "c/d"]) == ("a/b", "c/d")


def test_bad_endpoints_and_credentials_are_invalid_without_leaking_passwords() -> None:  # zconfig invariants 2, 4
    with pytest.raises(Invalid) as info:
        router_config(listen=["nonsense"])
    assert info.value.message.startswith("bad listen endpoint ['nonsense']")
    with pytest.raises(Invalid, match="both user and password"):
        client_config(connect=["tcp/127.0.0.1:1"], user="u")
    with pytest.raises(Invalid):
        config_from_flags(mode="satellite")


# --- server config -----------------------------------------------------------------------------
EXAMPLE = """
namespace: lab/robot-1
listen: [tcp/0.0.0.0:7447]
connect: [tcp/10.0.0.2:7447]
max_artifact_bytes: 1048576
users:
  alice:     {password: "change me", roles: [operator]}
  learner-1: {password_env: LEARNER_PW, roles: [learner, reader]}
  dash:      {password_file: dash.pw, roles: [reader]}
trusted_nodes:
  - {zid: 1f2e3d4c5b6a7980, roles: [reader]}
credentials: {user: registry, password: "join me"}
"""


def test_example_config_parses(tmp_path: Path) -> None:
    (tmp_path / "dash.pw").write_text("dash-pw\n")
    cfg = parse_server_config(EXAMPLE, env={"LEARNER_PW": "lp"}, base_dir=tmp_path)
    assert (cfg.namespace, cfg.listen, cfg.connect, cfg.max_artifact_bytes) == (
        "lab/robot-1",
        ("tcp/0.0.0.0:7447",),
        ("tcp/10.0.0.2:7447",),
        1048576,
    )
    assert {u.name: (u.password, u.roles) for u in cfg.users} == {
        "alice": ("change me", ("operator",)),
        "learner-1": ("lp", ("learner", "reader")),
        "dash": ("dash-pw", ("reader",)),
    }
    assert cfg.credentials is not None and cfg.credentials.user == "registry"
    assert "change me" not in repr(cfg) and "join me" not in repr(cfg)  # server_config invariant 4


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("users: {bob: {password: x, roles: [admin]}}", "users.bob.roles[0]"),
        ("users: {bob: {password: x}}", "users.bob.roles"),
        ("users: {bob: {password: x, password_env: Y, roles: [reader]}}", "users.bob"),
        ("users: {'b:ob': {password: x, roles: [reader]}}", "users.b:ob"),
        ("users: {bob: {password: ' x', roles: [reader]}}", "users.bob.password"),
        ("users: {bob: {password_env: NOPE_NOT_SET, roles: [reader]}}", "users.bob.password_env"),
        ("users: {bob: {password: x, roles: [reader], extra: 1}}", "users.bob.extra"),
        ("namespace: 'a/*'", "namespace"),
        ("listen: [nonsense]", "listen[0]"),
        ("listen: []", "listen"),
        ("max_artifact_bytes: -1", "max_artifact_bytes"),
        ("multicast_scouting: yes please", "multicast_scouting"),
        ("trusted_nodes: [{zid: 1f2e, roles: [reader]}]", "trusted_nodes"),
        ("colour: blue", "colour"),
        ("[1, 2]", "<config>"),
        ("a: [", "<config>"),
    ],
)
def test_config_errors_name_the_field(text: str, field: str) -> None:  # server_config invariant 1
    with pytest.raises(Invalid) as info:
        parse_server_config(text, env={})
    assert info.value.message.startswith(f"{field}:"), info.value.message
    assert info.value.details["field"] == field


@settings(max_examples=200)
@given(
    doc=st.recursive(
        st.none() | st.booleans() | st.integers() | st.text(max_size=8),
        lambda c: (
            st.lists(c, max_size=3)
            | st.dictionaries(
                st.sampled_from(["users", "roles", "password", "listen", "x"]) | st.text(max_size=4), c, max_size=3
            )
        ),
        max_leaves=12,
    )
)
def test_config_parsing_raises_only_invalid(doc: Any) -> None:  # server_config invariant 1
    with contextlib.suppress(Invalid):
        parse_server_config(yaml.safe_dump(doc), env={})


def test_access_control_grants_each_user_exactly_its_roles_commands() -> None:  # server_config invariants 2, 5
    cfg = parse_server_config(EXAMPLE.replace("password_file: dash.pw", "password: d"), env={"LEARNER_PW": "x"})
    acl = access_control_for(cfg)
    assert acl is not None and acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    granted: dict[str, set[str]] = {}
    for policy in acl["policies"]:
        who = {
            w for sid in policy["subjects"] for w in subjects[sid].get("usernames", []) + subjects[sid].get("zids", [])
        }
        if policy["id"].startswith("capevo-role-"):
            assert {"capevo-read-in", "capevo-read-out"} <= set(policy["rules"])
        for name in who:
            granted.setdefault(name, set())
        for rule in (rules[r] for r in policy["rules"]):
            if rule["flows"] == ["ingress"] and "query" in rule["messages"]:
                for name in who:
                    granted[name] |= {k for k in rule["key_exprs"] if "/cmd/" in k}
    keys = Keys("lab/robot-1")
    assert granted == {
        "alice": {keys.cmd(op, "alice") for op in COMMANDS},
        "learner-1": {keys.cmd("publish", "learner-1"), keys.cmd("gate", "learner-1")},
        "dash": set(),
        "1f2e3d4c5b6a7980": set(),
    }
    assert keys.cmd("gate", "learner-1") == "lab/robot-1/cmd/gate/@learner-1"
    router_config(listen=["tcp/127.0.0.1:7447"], access_control=acl)  # Zenoh accepts it


def test_open_config_has_no_acl_and_no_dictionary() -> None:  # server_config invariant 3
    cfg = ServerConfig()
    assert not cfg.secured and access_control_for(cfg) is None
    with pytest.raises(Invalid):
        write_dictionary(cfg)


def test_dictionary_file_is_private(tmp_path: Path) -> None:  # server_config invariant 4
    cfg = parse_server_config(
        "users: {bob: {password: 'p:w d', roles: [reader]}, amy: {password: q, roles: [operator]}}"
    )
    path = write_dictionary(cfg)
    try:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
        assert path.read_text() == "bob:p:w d\namy:q\n"
    finally:
        path.unlink()
        os.rmdir(path.parent)


def test_roles_registry() -> None:
    assert set(ROLES) == {"reader", "learner", "operator", "runtime"}
    with pytest.raises(Invalid, match="valid roles: learner, operator, reader, runtime"):
        make_role("admin")
