"""The runtime's on-disk artifact cache: verified reads, atomic writes, safe keys."""

from __future__ import annotations

import hashlib
import multiprocessing as mp
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capevo.errors import Corrupt, Invalid, Unavailable
from capevo.runtime.artifact_cache import ArtifactCache, MemoryArtifactCache, check_sha256


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.fixture(params=["disk", "memory"])
def cache(request: pytest.FixtureRequest, tmp_path: Path) -> ArtifactCache | MemoryArtifactCache:
    return ArtifactCache(tmp_path / "cache") if request.param == "disk" else MemoryArtifactCache()


def test_put_then_get_returns_the_bytes(cache: ArtifactCache | MemoryArtifactCache) -> None:
    data = b"def act(obs, params):\n    return [0.0] * 7\n"
    assert cache.get(sha(data)) is None
    cache.put(sha(data), data)
    assert cache.get(sha(data)) == data
    assert cache.stats["hits"] == 1 and cache.stats["misses"] == 1 and cache.stats["stored"] == 1


def test_put_refuses_bytes_that_do_not_hash_to_the_key(cache: ArtifactCache | MemoryArtifactCache) -> None:
    with pytest.raises(Corrupt) as err:
        cache.put(sha(b"one"), b"two")
    assert err.value.code.value == "corrupt"
    assert err.value.message == f"artifact bytes hash to {sha(b'two')}, not to their key {sha(b'one')}"
    assert cache.get(sha(b"one")) is None


def test_fetch_calls_the_loader_only_on_a_miss(cache: ArtifactCache | MemoryArtifactCache) -> None:
    data = b"x" * 1000
    calls: list[int] = []

    def load() -> bytes:
        calls.append(1)
        return data

    assert cache.fetch(sha(data), load) == data
    assert cache.fetch(sha(data), load) == data
    assert len(calls) == 1


def test_fetch_propagates_the_loader_error_and_stores_nothing(cache: ArtifactCache | MemoryArtifactCache) -> None:
    def down() -> bytes:
        raise Unavailable("registry is away")

    with pytest.raises(Unavailable):
        cache.fetch(sha(b"abc"), down)
    assert cache.get(sha(b"abc")) is None


def test_fetch_refuses_a_loader_returning_other_bytes(cache: ArtifactCache | MemoryArtifactCache) -> None:
    with pytest.raises(Corrupt):
        cache.fetch(sha(b"wanted"), lambda: b"something else")
    assert cache.get(sha(b"wanted")) is None


def test_corrupt_entry_on_disk_is_deleted_and_read_as_a_miss(tmp_path: Path) -> None:
    cache = ArtifactCache(tmp_path / "cache")
    data = b"good bytes"
    cache.put(sha(data), data)
    path = cache.path_for(sha(data))
    path.write_bytes(b"bit rot")
    assert cache.get(sha(data)) is None
    assert not path.exists()
    assert cache.stats["corrupt"] == 1


def test_writes_leave_no_temporary_files(tmp_path: Path) -> None:
    cache = ArtifactCache(tmp_path / "cache")
    for i in range(5):
        data = f"artifact {i}".encode()
        cache.put(sha(data), data)
    files = [p for p in (tmp_path / "cache").rglob("*") if p.is_file()]
    assert len(files) == 5
    assert not any(p.name.startswith(".tmp-") for p in files)
    assert all(p.name == sha(p.read_bytes()) and p.parent.name == p.name[:2] for p in files)


def _put_many(root: str, n: int) -> None:
    cache = ArtifactCache(root)
    for i in range(n):
        data = f"shared {i % 7}".encode() * 1000
        cache.put(sha(data), data)


def test_processes_sharing_a_cache_never_see_partial_entries(tmp_path: Path) -> None:
    root = str(tmp_path / "cache")
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_put_many, args=(root, 40)) for _ in range(2)]
    for p in procs:
        p.start()
    reader = ArtifactCache(root, fsync=False)
    seen = 0
    while any(p.is_alive() for p in procs):
        for i in range(7):
            data = f"shared {i}".encode() * 1000
            got = reader.get(sha(data))
            assert got is None or got == data
            seen += got is not None
    for p in procs:
        p.join(30)
        assert p.exitcode == 0
    assert reader.stats["corrupt"] == 0
    assert all(reader.get(sha(f"shared {i}".encode() * 1000)) is not None for i in range(7))


@pytest.mark.parametrize("key", ["../../etc/passwd", "ab" * 32 + "/x", "AB" * 32, "a" * 63, "", "*" * 64])
def test_malformed_keys_are_refused(tmp_path: Path, key: str) -> None:
    cache = ArtifactCache(tmp_path / "cache")
    with pytest.raises(Invalid) as err:
        cache.get(key)
    assert err.value.message == f"artifact key must be 64 lowercase hex digits, got {key!r}"


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=80))
def test_any_key_is_accepted_only_if_it_is_sha256_hex(key: str) -> None:
    try:
        assert check_sha256(key) == key
    except Invalid:
        assert not (len(key) == 64 and all(c in "0123456789abcdef" for c in key))
    else:
        assert len(key) == 64 and all(c in "0123456789abcdef" for c in key)
