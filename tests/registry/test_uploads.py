"""Uploads in progress on a server (capevo.registry.uploads), written to a real blob store."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import Conflict, Invalid, NotFound, TooLarge, Unavailable
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.local import LocalRegistry
from capevo.registry.uploads import Upload, Uploads
from capevo.registry.wire import UploadPart

UPLOAD = "0123456789abcdef" * 2
OTHER = "fedcba9876543210" * 2
SPEC = parse_publish_spec("kind: neural\ndescription: staged\n")


@pytest.fixture
def registry(tmp_path: Path) -> Iterator[LocalRegistry]:
    with LocalRegistry(tmp_path / "registry", max_artifact_bytes=1000) as reg:
        yield reg


def _temp_files(reg: LocalRegistry) -> list[Path]:
    return list((reg.root / "blobs" / "incoming").glob(".tmp-*"))


def _published(reg: LocalRegistry, upload: Upload | None) -> bytes:
    assert upload is not None
    record = reg.publish_written(upload.name, upload.writer, upload.spec)
    return reg.get_artifact(record.name, record.version)


def test_parts_in_order_publish_the_artifact_once_and_leave_nothing(registry: LocalRegistry) -> None:  # 1, 2
    uploads = Uploads(registry.artifact_writer, max_artifact_bytes=1000)
    assert uploads.add("alice", "pol", UploadPart(UPLOAD, 0, 10), b"abcd", SPEC) is None
    assert uploads.add("alice", "pol", UploadPart(UPLOAD, 4, 10), b"efg") is None
    assert registry.list_ecms() == []  # nothing is visible before the last part
    done = uploads.add("alice", "pol", UploadPart(UPLOAD, 7, 10), b"hij")
    assert done is not None and (done.name, done.spec) == ("pol", SPEC) and len(uploads) == 0
    assert _published(registry, done) == b"abcdefghij"
    assert _temp_files(registry) == []
    with pytest.raises(NotFound, match="send the artifact again from offset 0"):
        uploads.add("alice", "pol", UploadPart(UPLOAD, 7, 10), b"hij")


def test_out_of_order_foreign_and_oversize_parts_are_refused_and_change_nothing(registry: LocalRegistry) -> None:
    uploads = Uploads(registry.artifact_writer, max_artifact_bytes=1000)
    uploads.add("alice", "pol", UploadPart(UPLOAD, 0, 6), b"ab", SPEC)
    with pytest.raises(Conflict, match="at offset 2 of 6, got one of 'pol' at offset 3 of 6"):
        uploads.add("alice", "pol", UploadPart(UPLOAD, 3, 6), b"d")
    with pytest.raises(Conflict, match="at offset 2 of 7"):
        uploads.add("alice", "pol", UploadPart(UPLOAD, 2, 7), b"c")
    with pytest.raises(Conflict, match="expected the part of 'pol'"):
        uploads.add("alice", "other", UploadPart(UPLOAD, 2, 6), b"cd")
    with pytest.raises(NotFound):  # an upload belongs to the user who began it (invariant 1)
        uploads.add("bob", "pol", UploadPart(UPLOAD, 2, 6), b"cd")
    with pytest.raises(Invalid, match="past its upload's total 6"):
        uploads.add("alice", "pol", UploadPart(UPLOAD, 2, 6), b"cdefg")
    with pytest.raises(Invalid, match="no bytes"):
        uploads.add("alice", "pol", UploadPart(UPLOAD, 2, 6), b"")
    with pytest.raises(Invalid, match="carries the spec"):
        uploads.add("alice", "pol", UploadPart(OTHER, 0, 6), b"ab")
    with pytest.raises(TooLarge, match="the limit is 1000"):
        uploads.add("alice", "pol", UploadPart(OTHER, 0, 1001), b"x", SPEC)
    assert _published(registry, uploads.add("alice", "pol", UploadPart(UPLOAD, 2, 6), b"cdef")) == b"abcdef"


def test_a_first_part_again_starts_the_upload_over(registry: LocalRegistry) -> None:
    uploads = Uploads(registry.artifact_writer, max_artifact_bytes=1000)
    uploads.add("alice", "pol", UploadPart(UPLOAD, 0, 4), b"xy", SPEC)
    uploads.add("alice", "pol", UploadPart(UPLOAD, 0, 4), b"ab", SPEC)
    assert _published(registry, uploads.add("alice", "pol", UploadPart(UPLOAD, 2, 4), b"cd")) == b"abcd"
    assert _temp_files(registry) == []  # the first attempt's file went when it started over


def test_too_many_uploads_are_busy_and_old_or_stale_ones_are_dropped(registry: LocalRegistry) -> None:  # 3, 4
    uploads = Uploads(registry.artifact_writer, max_artifact_bytes=1000, max_uploads=2, per_owner=1)
    uploads.add("alice", "pol", UploadPart(UPLOAD, 0, 4), b"ab", SPEC)
    uploads.add("carol", "pol", UploadPart(UPLOAD, 0, 4), b"ab", SPEC)
    with pytest.raises(Unavailable, match="2 uploads in progress"):
        uploads.add("bob", "pol", UploadPart(OTHER, 0, 4), b"ab", SPEC)
    uploads.add("alice", "pol", UploadPart(OTHER, 0, 4), b"xy", SPEC)  # her next drops her oldest, not carol's
    with pytest.raises(NotFound):
        uploads.add("alice", "pol", UploadPart(UPLOAD, 2, 4), b"cd")
    assert len(_temp_files(registry)) == 2
    assert _published(registry, uploads.add("carol", "pol", UploadPart(UPLOAD, 2, 4), b"cd")) == b"abcd"
    uploads.close()
    assert _temp_files(registry) == []
    stale = Uploads(registry.artifact_writer, max_artifact_bytes=1000, stale_s=0.0)
    stale.add("alice", "pol", UploadPart(UPLOAD, 0, 4), b"ab", SPEC)
    stale.add("bob", "pol", UploadPart(OTHER, 0, 4), b"ab", SPEC)  # drops alice's, idle over 0 s
    with pytest.raises(NotFound, match="0 s idle"):
        stale.add("alice", "pol", UploadPart(UPLOAD, 2, 4), b"cd")
    stale.close()
    assert _temp_files(registry) == []


@settings(max_examples=60, deadline=None)
@given(data=st.binary(min_size=1, max_size=300), cuts=st.lists(st.integers(1, 299), max_size=6))
def test_any_split_in_order_gives_back_the_bytes(
    tmp_path_factory: pytest.TempPathFactory, data: bytes, cuts: list[int]
) -> None:
    with LocalRegistry(tmp_path_factory.mktemp("split") / "registry") as reg:
        uploads = Uploads(reg.artifact_writer, max_artifact_bytes=1000)
        bounds = sorted({c for c in cuts if c < len(data)} | {0, len(data)})
        results = [
            uploads.add("u", "pol", UploadPart(UPLOAD, a, len(data)), data[a:b], SPEC if a == 0 else None)
            for a, b in itertools.pairwise(bounds)
        ]
        assert results[:-1] == [None] * (len(results) - 1)
        assert _published(reg, results[-1]) == data
