"""Property tests: malformed keys, parameters, payloads, names and descriptors at every
queryable and command key each get one clear error reply, and the registry keeps serving.

Requests are sent on a bare Zenoh session (not the Client, which would refuse to build
them) to a server in another process.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from procs import ServerProcess, start_server
from zenoh_fixtures import raw_query, raw_session, unique_name

from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.keys import COMMANDS

pytestmark = pytest.mark.zenoh

NS = "fuzz"
SPEC = parse_publish_spec("kind: code\ndescription: fuzz target\n")
FUZZ = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much]
)
MAX_ARTIFACT = 64 * 1024

# Anything, as JSON would carry it.
JUNK = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=False, allow_infinity=False),
    st.text(max_size=40),
    st.lists(st.integers(), max_size=3),
    st.dictionaries(st.text(max_size=6), st.integers(), max_size=3),
)
KEY_CHUNK = st.text(
    alphabet=st.characters(blacklist_characters="/*$#?", blacklist_categories=("Cs", "Cc")), min_size=1, max_size=24
)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    srv = start_server(tmp_path_factory.mktemp("fuzz") / "registry", namespace=NS, max_artifact_bytes=MAX_ARTIFACT)
    yield srv
    assert srv.stop() == 0, srv.log_text()


@pytest.fixture(scope="module")
def session(server: ServerProcess) -> Iterator[zenoh.Session]:
    s = raw_session(server.endpoint)
    yield s
    s.close()


@pytest.fixture(scope="module")
def known(server: ServerProcess) -> str:
    """An ECM with an active v0, so good reads have something to find."""
    name = unique_name("known")
    with server.client() as c:
        c.publish(name, b"known artifact", SPEC)
        c.promote(name, 0)
    return name


def _one_reply(session: zenoh.Session, selector: str, **kw: Any) -> tuple[bool, Any]:
    """(ok, body): the single reply; an error body is the decoded error envelope."""
    replies = raw_query(session, selector, timeout=10.0, **kw)
    assert len(replies) == 1, f"{selector}: {len(replies)} replies"
    reply = replies[0]
    if reply.ok is not None:
        return True, reply.ok
    body = json.loads(reply.err.payload.to_bytes())["error"]
    assert set(body) == {"code", "message", "details"}
    assert isinstance(body["message"], str) and body["message"]
    return False, body


def _error(session: zenoh.Session, selector: str, codes: set[str], **kw: Any) -> dict[str, Any]:
    ok, body = _one_reply(session, selector, **kw)
    assert not ok, f"{selector} unexpectedly succeeded"
    assert body["code"] in codes, body
    return body


def _still_serving(session: zenoh.Session, known: str) -> None:
    ok, sample = _one_reply(session, f"{NS}/ecm/{known}/active")
    assert ok and json.loads(sample.payload.to_bytes())["name"] == known


def _valid_key(key: str) -> bool:
    """A key Zenoh accepts and routes to the registry's ``**`` queryables.

    Chunks starting with ``@`` are Zenoh "verbatim" chunks that ``**`` never matches, so
    such a query reaches no queryable at all (zero replies) -- Zenoh routing, not the registry.
    """
    if any(chunk.startswith("@") for chunk in key.split("/")):
        return False
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError:
        return False
    return True


# --- read keys ---------------------------------------------------------------------------------
@FUZZ
@given(chunks=st.lists(KEY_CHUNK, min_size=1, max_size=4))
def test_any_key_under_ecm_gets_one_clear_reply(session: zenoh.Session, known: str, chunks: list[str]) -> None:
    key = f"{NS}/ecm/" + "/".join(chunks)
    assume(_valid_key(key))
    ok, body = _one_reply(session, key)
    if not ok:
        assert body["code"] in {"invalid", "not_found"}, body
    _still_serving(session, known)


@FUZZ
@given(suffix=st.sampled_from(["", "/active", "/0", "/history", "/active/artifact", "/0/artifact"]), name=KEY_CHUNK)
def test_bad_names_at_every_read_key_are_invalid(session: zenoh.Session, known: str, suffix: str, name: str) -> None:
    from capevo.records.names import NAME_PATTERN, RESERVED

    assume(not NAME_PATTERN.fullmatch(name) or ".." in name or name in RESERVED)
    key = f"{NS}/ecm/{name}{suffix}"
    assume(_valid_key(key))
    body = _error(session, key, {"invalid"})
    assert "ECM name" in body["message"]
    _still_serving(session, known)


@FUZZ
@given(version=st.text(min_size=1, max_size=20).filter(lambda v: "/" not in v))
def test_bad_version_chunks_are_invalid(session: zenoh.Session, known: str, version: str) -> None:
    assume(version not in ("active", "history") and not (version.isascii() and version.isdigit() and len(version) < 10))
    key = f"{NS}/ecm/{known}/{version}"
    assume(_valid_key(key))
    _error(session, key, {"invalid"})
    _still_serving(session, known)


READ_KEYS = ["ecm", "ecm/{known}", "ecm/{known}/active", "ecm/{known}/0", "ecm/{known}/0/artifact"]
READ_KEYS += ["ecm/{known}/active/artifact", "ecm/{known}/history", "set", "verify", "history", "info"]


@pytest.mark.parametrize("template", READ_KEYS)
@FUZZ
@given(
    params=st.dictionaries(
        st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=10),
        st.text(alphabet=st.characters(blacklist_characters=";=&#", blacklist_categories=("Cs", "Cc")), max_size=12),
        min_size=1,
        max_size=3,
    ),
    payload=st.one_of(st.none(), st.binary(min_size=1, max_size=64)),
)
def test_every_read_key_refuses_unknown_parameters_and_payloads(
    session: zenoh.Session, known: str, template: str, params: dict[str, str], payload: bytes | None
) -> None:
    visible = {k: v for k, v in params.items() if not k.startswith("_")}
    assume(visible or payload)
    if template == "set" and payload is None and set(visible) == {"revision"}:
        assume(not (visible["revision"].isascii() and visible["revision"].isdigit()))
    selector = zenoh.Selector(f"{NS}/{template.format(known=known)}", params)
    _error(session, str(selector), {"invalid"}, payload=payload)
    _still_serving(session, known)


@FUZZ
@given(revision=st.one_of(st.integers(min_value=-5, max_value=10**20).map(str), st.text(max_size=8)))
def test_set_revision_parameter(session: zenoh.Session, known: str, revision: str) -> None:
    assume(all(c not in revision for c in ";=&#"))
    ok, body = _one_reply(session, str(zenoh.Selector(f"{NS}/set", {"revision": revision})))
    if ok:
        assert json.loads(body.payload.to_bytes())["revision"] == int(revision)
    else:
        assert body["code"] in {"invalid", "not_found"}, body
    _still_serving(session, known)


# --- command keys ------------------------------------------------------------------------------
def _base_body(op: str, name: str) -> dict[str, Any]:
    base: dict[str, Any] = {"name": name, "reason": "fuzz", "actor": "fuzzer"}
    if op in ("promote", "deprecate", "reject", "gate"):
        base["version"] = 0
    if op in ("promote", "rollback"):
        base["expected_active"] = None
    if op == "rollback":
        base["to"] = None
    if op == "gate":
        base["evidence"] = {"ok": True}
    return base


NON_PUBLISH = [op for op in COMMANDS if op != "publish"]


@pytest.mark.parametrize("op", NON_PUBLISH)
@FUZZ
@given(data=st.data())
def test_command_bodies_with_a_junk_field_get_a_clear_error(
    session: zenoh.Session, known: str, op: str, data: st.DataObject
) -> None:
    body = _base_body(op, unique_name("ghost"))  # valid as a request, but the ECM does not exist
    field = data.draw(st.sampled_from([*body, "unknown_field"]), label="field")
    body[field] = data.draw(JUNK, label="value")
    result = _error(session, f"{NS}/cmd/{op}", {"invalid", "not_found", "too_large"}, payload=json.dumps(body).encode())
    if field == "unknown_field":
        assert result["code"] == "invalid" and "unknown field 'unknown_field'" in result["message"]
    _still_serving(session, known)


@pytest.mark.parametrize("op", list(COMMANDS))
@FUZZ
@given(
    payload=st.one_of(
        st.binary(max_size=256), st.text(max_size=64).map(str.encode), JUNK.map(lambda v: json.dumps(v).encode())
    )
)
def test_command_keys_refuse_malformed_payloads(session: zenoh.Session, known: str, op: str, payload: bytes) -> None:
    if op == "publish":
        _error(session, f"{NS}/cmd/{op}", {"invalid"}, attachment=payload or None, payload=b"artifact")
    else:
        _error(session, f"{NS}/cmd/{op}", {"invalid"}, payload=payload or None)
    _still_serving(session, known)


SPEC_PATHS = [
    ("kind",),
    ("descriptor",),
    ("descriptor", "description"),
    ("descriptor", "applicability"),
    ("descriptor", "applicability", "all"),
    ("descriptor", "termination", "text"),
    ("interface",),
    ("interface", "inputs"),
    ("media_type",),
    ("parent",),
    ("origin",),
    ("provenance",),
    ("provenance", "traces"),
    ("bogus",),
    ("descriptor", "bogus"),
]


@FUZZ
@given(path=st.sampled_from(SPEC_PATHS), value=JUNK, name=st.one_of(st.none(), KEY_CHUNK))
def test_publish_with_junk_descriptors_and_names(
    session: zenoh.Session, known: str, path: tuple[str, ...], value: Any, name: str | None
) -> None:
    spec = SPEC.to_dict()
    target = spec
    for part in path[:-1]:
        target = target[part]
    target[path[-1]] = value
    header = {"name": name if name is not None else unique_name("pub"), "spec": spec, "actor": "fuzzer"}
    ok, body = _one_reply(
        session, f"{NS}/cmd/publish", attachment=json.dumps(header).encode(), payload=b"fuzz artifact"
    )
    if ok:
        record = json.loads(body.payload.to_bytes())
        assert record["name"] == header["name"] and record["state"] == "candidate"
    else:
        assert body["code"] in {"invalid", "not_found"}, body  # not_found: a junk int parent
        if path[-1] == "bogus" and name is None:
            assert body["code"] == "invalid" and "bogus: unknown field" in body["message"]
    _still_serving(session, known)


@pytest.mark.parametrize(
    ("payload", "fragment"),
    [
        (b'{"name": "x", "version": 0', "not valid JSON"),
        (b'{"name": "x", "version": NaN}', "not valid JSON"),
        (b'{"name": "x", "version": 1e999}', "not valid JSON"),
        (b"[" * 100_000 + b"]" * 100_000, "not valid JSON"),
        (b"\xff\xfe{}", "not UTF-8"),
        ('{"name": "x"}'.encode("utf-16"), "not UTF-8"),
        (b'{"name": "x", "version": ' + b"9" * 5000 + b"}", "not valid JSON"),
        (b'"just a string"', "must be a JSON object"),
        (b'{"name": "../etc", "version": 0}', "ECM name"),
        (b'{"name": "x", "version": true}', "version must be a non-negative integer"),
        (b'{"name": "x", "version": 0, "reason": 5}', "reason must be a string"),
        (b'{"name": "x", "version": 0, "actor": ""}', "actor must not be empty"),
        (b'{"version": 0}', "missing field 'name'"),
    ],
    ids=[
        "truncated",
        "nan",
        "inf",
        "deep",
        "not-utf8",
        "utf16",
        "huge-int",
        "not-object",
        "traversal",
        "bool-version",
        "reason-type",
        "empty-actor",
        "missing-name",
    ],
)
def test_malformed_promote_requests(session: zenoh.Session, known: str, payload: bytes, fragment: str) -> None:
    body = _error(session, f"{NS}/cmd/promote", {"invalid"}, payload=payload)
    assert fragment in body["message"], body
    _still_serving(session, known)


# A publish in parts: (upload 0 or 1, offset, total, bytes carried). Offsets and totals are
# drawn near where an upload of a few small parts stands, so that the model meets every case.
PART_STEPS = st.lists(
    st.tuples(st.integers(0, 1), st.integers(0, 12), st.integers(1, 12), st.integers(0, 6)), min_size=1, max_size=10
)


@FUZZ
@given(steps=PART_STEPS)
def test_parts_in_any_order_publish_exactly_what_was_staged_in_order(
    session: zenoh.Session, known: str, steps: list[tuple[int, int, int, int]]
) -> None:
    """Model-based: every part gets the reply the staging rules predict (uploads.py invariants
    1-2), and a completed upload publishes exactly the bytes its accepted parts carried."""
    name = unique_name("parts")
    upload_ids = (uuid.uuid4().hex, uuid.uuid4().hex)  # fresh per example: the server outlives it
    staged: dict[int, tuple[int, bytes]] = {}  # upload -> (total, bytes accepted so far)
    for i, (u, offset, total, size) in enumerate(steps):
        payload = bytes([i]) * size
        header = {"name": name, "part": {"upload": upload_ids[u], "offset": offset, "total": total}}
        if offset == 0:
            header["spec"] = SPEC.to_dict()
        ok, body = _one_reply(session, f"{NS}/cmd/publish", attachment=json.dumps(header).encode(), payload=payload)
        have = staged.get(u)
        if offset >= total or size == 0 or offset + size > total:
            assert not ok and body["code"] == "invalid", (steps, i, body)
        elif offset == 0 or (have is not None and have[0] == total and len(have[1]) == offset):
            data = payload if offset == 0 else have[1] + payload  # type: ignore[index]
            assert ok, (steps, i, body)
            if len(data) < total:
                assert json.loads(body.payload.to_bytes()) == {"upload": upload_ids[u], "received": len(data)}
                staged[u] = (total, data)
                continue
            record = json.loads(body.payload.to_bytes())
            ok_art, art = _one_reply(session, f"{NS}/ecm/{name}/{record['version']}/artifact")
            assert ok_art and art.payload.to_bytes() == data, (steps, i)
            staged.pop(u, None)
        else:
            assert not ok and body["code"] == ("not_found" if have is None else "conflict"), (steps, i, body)
    _still_serving(session, known)


@FUZZ
@given(part=JUNK)
def test_a_junk_part_is_invalid(session: zenoh.Session, known: str, part: Any) -> None:
    header = {"name": unique_name("junk"), "spec": SPEC.to_dict(), "part": part}
    ok, body = _one_reply(session, f"{NS}/cmd/publish", attachment=json.dumps(header).encode(), payload=b"x")
    if part is None:  # no part: an ordinary publish
        assert ok
    else:
        assert not ok and body["code"] == "invalid" and body["details"]["field"].startswith("part"), body
    _still_serving(session, known)


def test_oversize_requests_are_too_large(session: zenoh.Session, known: str) -> None:
    header = json.dumps({"name": unique_name("big"), "spec": SPEC.to_dict()}).encode()
    body = _error(session, f"{NS}/cmd/publish", {"too_large"}, attachment=header, payload=b"\0" * (MAX_ARTIFACT + 1))
    assert body["message"] == f"artifact is {MAX_ARTIFACT + 1} bytes; the limit is {MAX_ARTIFACT}"
    part = {"upload": "c" * 32, "offset": 0, "total": MAX_ARTIFACT + 1}
    header = json.dumps({"name": unique_name("big"), "spec": SPEC.to_dict(), "part": part}).encode()
    body = _error(session, f"{NS}/cmd/publish", {"too_large"}, attachment=header, payload=b"\0")
    assert body["message"] == f"artifact is {MAX_ARTIFACT + 1} bytes; the limit is {MAX_ARTIFACT}"
    body = _error(session, f"{NS}/cmd/promote", {"too_large"}, payload=b" " * (4 * 2**20 + 1))
    assert body["message"].startswith("promote request: 4194305 bytes; the limit is 4194304")
    _still_serving(session, known)


def test_wildcard_and_foreign_keys(session: zenoh.Session, known: str) -> None:
    body = _error(session, f"{NS}/ecm/*", {"invalid"})
    assert "wildcard" in body["message"]
    body = _error(session, f"{NS}/cmd/frobnicate", {"invalid"}, payload=b"{}")
    assert body["message"].startswith("unknown command 'frobnicate'; valid commands: publish, promote")
    body = _error(session, f"{NS}/cmd/promote/extra", {"invalid"}, payload=b"{}")
    assert "unknown registry key" in body["message"]
    _still_serving(session, known)


def test_publish_without_header_and_with_stray_attachment(session: zenoh.Session, known: str) -> None:
    body = _error(session, f"{NS}/cmd/publish", {"invalid"}, payload=b"artifact")
    assert "missing header" in body["message"]
    body = _error(session, f"{NS}/cmd/promote", {"invalid"}, payload=b"{}", attachment=b"{}")
    assert "unexpected attachment" in body["message"]
    _still_serving(session, known)


def test_requests_beyond_zenohs_reassembly_limit_are_dropped_and_the_server_survives(
    session: zenoh.Session, known: str
) -> None:
    """Zenoh itself drops messages over ``transport/link/rx/max_message_size`` (the server sets it
    to twice the artifact limit + 9 MiB): the querier gets Zenoh's own "Timeout" error reply."""
    from capevo.registry.service import zenoh_max_message_size

    size = zenoh_max_message_size(MAX_ARTIFACT) + 4 * 2**20
    header = json.dumps({"name": unique_name("huge"), "spec": SPEC.to_dict()}).encode()
    replies = raw_query(session, f"{NS}/cmd/publish", attachment=header, payload=b"\0" * size, timeout=2.0)
    # Zenoh either drops the oversize message (the querier times out) or, when it reassembles it
    # after all, the registry refuses it as too_large; both leave the server serving.
    outcomes = [(r.ok, r.err.payload.to_bytes() if r.err else None) for r in replies]
    assert len(outcomes) == 1 and outcomes[0][0] is None
    assert outcomes[0][1] == b"Timeout" or b'"code": "too_large"' in outcomes[0][1]
    _still_serving(session, known)
