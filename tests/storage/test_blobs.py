"""BlobStore; invariant numbers refer to the docstring of :mod:`capevo.storage.blobs`."""

from __future__ import annotations

import hashlib
import io
import os
import time
from pathlib import Path

import pytest
from procs import run_in_threads

from capevo.errors import Corrupt, ErrorCode, Invalid, NotFound, TooLarge, Unavailable
from capevo.storage.blobs import BlobStore, validate_sha256


@pytest.fixture
def store(tmp_path: Path) -> BlobStore:
    return BlobStore(tmp_path / "blobs")


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file())


def test_inv1_put_writes_one_complete_file_at_its_address(store: BlobStore) -> None:
    sha, size = store.put(b"hello")
    assert (sha, size) == (_sha(b"hello"), 5)
    assert _files(store.root) == [store.root / sha[:2] / sha[2:]]
    assert (store.root / sha[:2] / sha[2:]).read_bytes() == b"hello"
    assert store.exists(sha) and store.get(sha) == b"hello"


def test_inv1_put_stream_matches_put_and_leaves_no_temp_files(store: BlobStore) -> None:
    data = bytes(range(256)) * 10_000
    assert store.put_stream(io.BytesIO(data)) == (_sha(data), len(data))
    assert store.put_stream([data[:7], data[7:]]) == (_sha(data), len(data))
    assert [p.name for p in _files(store.root)] == [_sha(data)[2:]]
    assert store.get(_sha(data)) == data


def test_inv1_a_writer_shows_nothing_until_finished_and_discards_cleanly(store: BlobStore) -> None:
    writer = store.writer()
    writer.write(b"hel")
    writer.write(memoryview(b"lo"))
    assert list(store) == [] and writer.size == 5
    assert writer.finish() == (_sha(b"hello"), 5)
    assert list(store) == [_sha(b"hello")] and [p.name for p in _files(store.root)] == [_sha(b"hello")[2:]]
    writer.discard()  # after finish: nothing to drop
    with pytest.raises(Unavailable, match="finished or discarded"):
        writer.write(b"more")
    again = store.writer()
    again.write(b"hello")
    assert again.finish() == (_sha(b"hello"), 5)  # already stored: one file still
    dropped = store.writer(max_bytes=4)
    dropped.write(b"abc")
    with pytest.raises(TooLarge):
        dropped.write(b"de")
    with pytest.raises(Unavailable):
        dropped.finish()
    assert [p.name for p in _files(store.root)] == [_sha(b"hello")[2:]]


def test_inv1_64mb_stream(store: BlobStore) -> None:
    chunk = hashlib.sha256(b"x").digest() * 32768  # 1 MiB
    expected = hashlib.sha256()
    for _ in range(64):
        expected.update(chunk)
    sha, size = store.put_stream(chunk for _ in range(64))
    assert (sha, size) == (expected.hexdigest(), 64 * 2**20)
    assert store.verify(sha) is None


def test_inv1_stream_over_limit_stores_nothing(store: BlobStore) -> None:
    with pytest.raises(TooLarge) as info:
        store.put_stream(io.BytesIO(b"x" * 100), max_bytes=99)
    assert info.value.code is ErrorCode.TOO_LARGE
    assert info.value.message == "artifact exceeds the limit of 99 bytes"
    assert _files(store.root) == [] and list(store) == []


def test_inv2_tampered_bytes_are_never_returned(store: BlobStore) -> None:
    sha, _ = store.put(b"original")
    (store.root / sha[:2] / sha[2:]).write_bytes(b"originaL")
    with pytest.raises(Corrupt) as info:
        store.get(sha)
    assert info.value.code is ErrorCode.CORRUPT
    assert info.value.message == f"blob {sha} is corrupt: its content hashes to {_sha(b'originaL')}"
    assert store.verify(sha) == f"blob {sha}: content hashes to {_sha(b'originaL')} (corrupt or tampered)"


def test_inv2_missing_is_not_found(store: BlobStore) -> None:
    sha = _sha(b"never stored")
    with pytest.raises(NotFound) as info:
        store.get(sha)
    assert info.value.code is ErrorCode.NOT_FOUND and info.value.message == f"blob {sha} is not stored"
    assert store.verify(sha) == f"blob {sha}: missing (expected at {store.root / sha[:2] / sha[2:]})"
    assert not store.exists(sha)


@pytest.mark.parametrize(
    "address",
    [
        "../" + "a" * 61,
        "a" * 62 + "/.",
        "/etc/passwd",
        "A" * 64,
        "a" * 63,
        "a" * 65,
        "g" * 64,
        "a" * 63 + "\n",
        "",
        None,
        b"a" * 64,
    ],
)
def test_inv3_only_hex_addresses_are_accepted(store: BlobStore, address: object) -> None:
    for fn in (store.get, store.verify, store.exists, store.path_for, validate_sha256):
        with pytest.raises(Invalid) as info:
            fn(address)  # type: ignore[arg-type]
        assert info.value.code is ErrorCode.INVALID
        assert info.value.message.startswith("blob address must be 64 lowercase hex digits, got ")


def test_inv4_put_is_idempotent_and_repairs_a_corrupt_copy(store: BlobStore) -> None:
    sha, _ = store.put(b"data")
    path = store.root / sha[:2] / sha[2:]
    mtime = path.stat().st_mtime_ns
    assert store.put(bytearray(b"data")) == (sha, 4)
    assert path.stat().st_mtime_ns == mtime  # intact copy left alone
    path.write_bytes(b"dat")
    assert store.put(memoryview(b"data")) == (sha, 4)
    assert store.get(sha) == b"data"
    path.write_bytes(b"DATA")
    assert store.put_stream([b"da", b"ta"]) == (sha, 4)
    assert store.get(sha) == b"data" and len(_files(store.root)) == 1


def test_inv4_concurrent_puts_of_the_same_bytes(store: BlobStore) -> None:
    data = b"z" * 200_000

    def put(_: int) -> None:
        for _ in range(5):
            assert store.put(data) == (_sha(data), len(data))

    run_in_threads(put, 8)
    assert [p.name for p in _files(store.root)] == [_sha(data)[2:]]


def test_inv5_temp_files_are_not_blobs(store: BlobStore) -> None:
    sha, _ = store.put(b"kept")
    (store.root / sha[:2] / ".tmp-123-abc").write_bytes(b"half written")
    (store.root / "incoming").mkdir(exist_ok=True)
    (store.root / "incoming" / ".tmp-9-x").write_bytes(b"half")
    assert list(store) == [sha]


def test_put_refuses_non_bytes(store: BlobStore) -> None:
    with pytest.raises(Invalid, match="blob data must be bytes, got str"):
        store.put("text")  # type: ignore[arg-type]


def test_inv5_sweep_removes_only_old_temp_files(store: BlobStore) -> None:
    sha, _ = store.put(b"kept")
    shard = store.root / sha[:2]
    old, fresh = shard / ".tmp-1-old", shard / ".tmp-2-fresh"
    old.write_bytes(b"left by a killed writer")
    fresh.write_bytes(b"a writer still at work")
    os.utime(old, (time.time() - 7200, time.time() - 7200))
    assert store.sweep_temp(older_than_s=3600) == 1
    assert not old.exists() and fresh.exists()
    assert store.get(sha) == b"kept"
