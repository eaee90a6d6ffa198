"""Artifacts published in parts over Zenoh, against a registry server in its own process.

The client sends an artifact above ``PART_BYTES`` as a run of ``publish`` parts, so the server
never holds the GIL for a whole payload (issue 21; capevo.registry.uploads says why).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from procs import start_server
from zenoh_fixtures import raw_query, raw_session, unique_name

from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.local import LocalRegistry
from capevo.registry.uploads import PART_BYTES
from capevo.registry.wire import UploadPart

SPEC = parse_publish_spec("kind: neural\ndescription: a policy big enough to go in parts\n")
UPLOAD = "5" * 32


def _staged(root: Path) -> list[Path]:
    """The blob writers' temporary files: where parts go until the last one arrives."""
    return sorted((root / "blobs" / "incoming").glob(".tmp-*"))


def test_a_large_artifact_goes_in_parts_and_comes_back_whole(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    server = start_server(root)
    data = os.urandom(2 * PART_BYTES + 12345)  # three parts, the last short
    name = unique_name("big")
    try:
        with server.client() as client:
            record = client.publish(name, data, SPEC)
            assert record.version == 0 and record.artifact.size == len(data)
            assert record.artifact.sha256 == hashlib.sha256(data).hexdigest()
            assert client.get_artifact(name, 0) == data
            assert [e.action for e in client.history(name)] == ["publish"]  # one version, one event
            small = client.publish(name, b"small", SPEC)  # one payload, as before parts existed
            assert client.get_artifact(name, small.version) == b"small"
        assert _staged(root) == []
    finally:
        assert server.stop() == 0, server.log_text()


def _part(session: object, name: str, part: UploadPart, payload: bytes) -> tuple[bool, dict[str, object]]:
    fields = {"name": name, "part": part.to_dict(), **({"spec": SPEC.to_dict()} if part.first else {})}
    header = json.dumps(fields).encode()
    (reply,) = raw_query(session, "capevo/cmd/publish", attachment=header, payload=payload)  # type: ignore[arg-type]
    if reply.ok is not None:
        return True, json.loads(reply.ok.payload.to_bytes())
    return False, json.loads(reply.err.payload.to_bytes())["error"]


def test_sigkill_mid_upload_publishes_nothing_and_the_restarted_server_clears_the_parts(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    name = unique_name("killed")
    server = start_server(root)
    session = raw_session(server.endpoint)
    try:
        ok, ack = _part(session, name, UploadPart(UPLOAD, 0, 3 * PART_BYTES), b"\1" * PART_BYTES)
        assert ok and ack == {"upload": UPLOAD, "received": PART_BYTES}
        assert len(_staged(root)) == 1
    finally:
        session.close()
    server.kill()  # SIGKILL with a part staged: no handler runs
    restarted = start_server(root)
    session = raw_session(restarted.endpoint)
    try:
        assert _staged(root) == []  # the restarted registry swept the killed writer's file
        ok, err = _part(session, name, UploadPart(UPLOAD, PART_BYTES, 3 * PART_BYTES), b"\2" * PART_BYTES)
        assert not ok and err["code"] == "not_found" and "send the artifact again from offset 0" in str(err["message"])
        with restarted.client() as client:
            assert client.list_ecms() == []  # nothing of the killed upload was published
            data = os.urandom(3 * PART_BYTES)
            assert client.get_artifact(name, client.publish(name, data, SPEC).version) == data
    finally:
        session.close()
        assert restarted.stop() == 0, restarted.log_text()
    with LocalRegistry(root) as local:
        assert local.verify().ok
