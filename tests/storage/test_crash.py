"""SIGKILL a process in the middle of a stream of mutations, then check what survived.

Covers invariant 6 of :mod:`capevo.storage.sqlite` (acknowledged means durable),
invariant 3 (no half-written mutation) and invariant 1 of :mod:`capevo.registry.local`
(no version without its blob).
"""

from __future__ import annotations

import hashlib
import multiprocessing as mp
import os
import random
import signal
import time
from pathlib import Path

from capevo.records import State
from capevo.registry.descriptor import parse_publish_spec
from capevo.registry.local import LocalRegistry

ROUNDS = 4
ACKS_PER_ROUND = 24


def _payload(seed: int) -> bytes:
    # 40 KiB .. 1.2 MiB so a kill often lands inside a blob write as well as a commit.
    block = hashlib.sha256(str(seed).encode()).digest()
    return block * (1280 * (1 + seed % 30))


def _churn(root: str, ack_path: str, seed: int) -> None:
    """Publish, gate and promote forever; log each call only after it returned."""
    spec = parse_publish_spec("kind: neural\ndescription: crash probe\n")
    fd = os.open(ack_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    i = seed * 1_000_000
    with LocalRegistry(root, actor="churn") as reg:
        while True:
            i += 1
            rec = reg.publish("churn", _payload(i), spec)
            # One write() per line: the kernel keeps it even if we die right after.
            os.write(fd, f"publish {rec.version} {rec.artifact.sha256}\n".encode())
            if rec.version % 3 == 0:
                reg.record_gate("churn", rec.version, {"i": i})
                os.write(fd, f"gate {rec.version}\n".encode())
            if rec.version % 2 == 1:
                reg.promote("churn", rec.version)
                os.write(fd, f"promote {rec.version}\n".encode())


def _acks(path: Path) -> list[list[str]]:
    if not path.exists():
        return []
    text = path.read_text()
    # A line without its newline was cut by the kill: that call was not acknowledged.
    return [line.split() for line in text.split("\n")[:-1]]


def test_sigkill_loses_nothing_acknowledged(tmp_path: Path) -> None:
    ctx = mp.get_context("spawn")
    root, ack_path = tmp_path / "reg", tmp_path / "acks.txt"
    rng = random.Random(1234)
    for rnd in range(ROUNDS):
        before = len(_acks(ack_path))
        proc = ctx.Process(target=_churn, args=(str(root), str(ack_path), rnd + 1))
        proc.start()
        deadline = time.monotonic() + 60
        while len(_acks(ack_path)) < before + ACKS_PER_ROUND:
            assert proc.is_alive() and time.monotonic() < deadline, "child died or stalled"
            time.sleep(0.005)
        time.sleep(rng.uniform(0, 0.03))
        os.kill(proc.pid, signal.SIGKILL)
        proc.join(timeout=30)
        assert proc.exitcode == -signal.SIGKILL

        acks = _acks(ack_path)
        published = {int(a[1]): a[2] for a in acks if a[0] == "publish"}
        gated = {int(a[1]) for a in acks if a[0] == "gate"}
        promoted = [int(a[1]) for a in acks if a[0] == "promote"]
        with LocalRegistry(root) as reg:
            detail = reg.get_ecm("churn")
            versions = {v.version: v for v in detail.versions}
            # Gap-free, and per kill at most the one publish in flight went through unacknowledged.
            assert sorted(versions) == list(range(len(versions)))
            assert 0 <= len(versions) - len(published) <= rnd + 1
            for version, sha in published.items():
                assert versions[version].artifact.sha256 == sha
                assert hashlib.sha256(reg.get_artifact("churn", version)).hexdigest() == sha
            for version in gated:
                assert versions[version].gate_evidence is not None
            # Versions are promoted in increasing order, so the pointer is at or past the last ack.
            assert detail.active_version is not None and detail.active_version >= promoted[-1]
            assert versions[detail.active_version].state is State.ACTIVE
            assert sum(v.state is State.ACTIVE for v in versions.values()) == 1
            report = reg.verify()
            assert report.ok, report.problems
            assert report.blobs_checked == len({v.artifact.sha256 for v in versions.values()})
            # Every stored blob file is complete; leftovers of a killed write are only temp files.
            for sha in reg.blobs:
                assert reg.blobs.verify(sha) is None
