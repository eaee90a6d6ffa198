"""recover() and the lenient scanner on truncated and corrupted files (scan/recover invariants)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from _trace_helpers import make_env_step, make_metadata, one_of_each, write_trace
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from capevo.errors import Conflict, Corrupt, ErrorCode, Invalid, NotFound
from capevo.runtime.traces import EnvStep, TraceReader, TraceWriter, default_output, recover
from capevo.runtime.traces.recover import RECOVERY_METADATA
from capevo.runtime.traces.scan import McapScan

N_STEPS = 60


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished trace with many small chunks."""
    path = tmp_path_factory.mktemp("src") / "run.mcap"
    return write_trace(path, [make_env_step(0, i, obs_dim=8) for i in range(N_STEPS)], chunk_size=1024)


def steps_of(path: Path) -> list[int]:
    return [s.step for s in TraceReader(path).records() if isinstance(s, EnvStep)]


def messages_per_chunk(path: Path) -> list[int]:
    with path.open("rb") as f:
        return [
            sum(isinstance(r, Message) for r in breakup_chunk(rec))
            for rec in StreamReader(f, emit_chunks=True).records
            if isinstance(rec, Chunk)
        ]


def test_recover_of_a_finished_file_copies_everything(finished: Path, tmp_path: Path) -> None:
    # Recover invariants 1, 2 and 4.
    out = tmp_path / "copy.mcap"
    report = recover(finished, out)
    assert report.complete and report.reason == "complete"
    assert report.messages == N_STEPS and report.messages_by_topic == {"/env/step": N_STEPS}
    assert report.dropped_messages == 0 and report.metadata_records == 2
    assert list(TraceReader(out).records()) == list(TraceReader(finished).records())
    assert TraceReader(out).metadata() == make_metadata()
    with out.open("rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert json.loads(meta[RECOVERY_METADATA]["source_complete"]) is True
    assert meta[RECOVERY_METADATA]["messages"] == str(N_STEPS)


def test_message_times_and_sequences_are_preserved(finished: Path, tmp_path: Path) -> None:
    out = recover(finished, tmp_path / "copy.mcap").output

    def stamps(p: str | Path) -> list[tuple[int, int, int, bytes]]:
        with Path(p).open("rb") as f:
            return [
                (m.log_time, m.publish_time, m.sequence, m.data)
                for _, _, m in make_reader(f).iter_messages(log_time_order=False)
            ]

    assert stamps(out) == stamps(finished)


def test_truncation_anywhere_recovers_a_prefix(finished: Path, tmp_path: Path) -> None:
    # Scan invariants 1-3 at many cut points: never raises, always a growing prefix.
    data = finished.read_bytes()
    cuts = sorted({*range(8, len(data), max(1, len(data) // 150)), len(data) - 1, len(data) - 9})
    previous = -1
    for cut in cuts:
        src = tmp_path / "cut.mcap"
        src.write_bytes(data[:cut])
        out = tmp_path / "out.mcap"
        report = recover(src, out, overwrite=True)
        assert not report.complete
        steps = steps_of(out)
        assert steps == list(range(len(steps))), cut
        assert len(steps) >= previous
        previous = len(steps)
        assert report.good_bytes <= cut
    assert previous == N_STEPS  # cutting only the summary loses no message


def test_truncated_mid_chunk_keeps_earlier_chunks_whole(finished: Path, tmp_path: Path) -> None:
    per_chunk = messages_per_chunk(finished)
    assert len(per_chunk) >= 4
    with finished.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    third = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[2]
    src = tmp_path / "cut.mcap"
    src.write_bytes(finished.read_bytes()[: third.chunk_start_offset + third.chunk_length // 2])
    report = recover(src, tmp_path / "out.mcap")
    assert report.messages == per_chunk[0] + per_chunk[1]
    assert f"truncated chunk record at offset {third.chunk_start_offset}" in report.reason
    assert report.good_bytes == third.chunk_start_offset


def test_corrupt_chunk_stops_the_salvage_there(finished: Path, tmp_path: Path) -> None:
    # Scan invariant 2: a chunk failing its CRC or decompression yields nothing.
    per_chunk = messages_per_chunk(finished)
    with finished.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    second = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[1]
    data = bytearray(finished.read_bytes())
    data[second.chunk_start_offset + second.chunk_length - 5] ^= 0xFF  # inside the compressed bytes
    src = tmp_path / "flipped.mcap"
    src.write_bytes(bytes(data))
    report = recover(src, tmp_path / "out.mcap")
    assert report.messages == per_chunk[0]
    assert f"corrupt chunk record at offset {second.chunk_start_offset}" in report.reason
    with pytest.raises(Corrupt) as exc:  # strict reading names the damage and the fix
        list(TraceReader(src).records())
    assert exc.value.code is ErrorCode.CORRUPT
    assert "damaged or unfinished" in exc.value.message and "capevo trace recover" in exc.value.message


def test_zero_filled_tail_is_not_a_record(tmp_path: Path) -> None:
    # A file system may leave zeros after a crash: opcode 0 ends the scan.
    path = tmp_path / "run.mcap"
    w = TraceWriter(path, make_metadata(), background_flush=False)
    w.write_env_step(make_env_step())
    w.flush()
    with path.open("ab") as f:
        f.write(bytes(4096))
    scan = McapScan(path)
    assert sum(isinstance(r, Message) for r in scan) == 1
    assert scan.result is not None and "invalid opcode 0" in scan.result.reason
    w.close()


def test_huge_length_field_does_not_allocate(tmp_path: Path) -> None:
    # Scan invariant 1: a length beyond the file ends the scan without reading it.
    path = write_trace(tmp_path / "run.mcap", [])
    data = bytearray(path.read_bytes())
    data[9:17] = (2**62).to_bytes(8, "little")  # the header record's length field
    path.write_bytes(bytes(data))
    scan = McapScan(path)
    assert list(scan) == []
    assert scan.result is not None and "truncated header record at offset 8" in scan.result.reason


def test_recover_unfinished_file_of_a_live_writer(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    records = one_of_each()
    with TraceWriter(path, make_metadata(), background_flush=False) as w:
        for r in records[:-1]:  # everything but the episode summary (which flushes)
            if isinstance(r, EnvStep):
                w.write_env_step(r)
        w.flush()
        report = recover(path, tmp_path / "out.mcap")
    assert not report.complete and report.reason == "file ends without a footer"
    assert report.messages == 1


def test_recover_errors(finished: Path, tmp_path: Path) -> None:
    # Recover invariant 3 and scan invariant 4.
    with pytest.raises(Invalid) as exc:
        recover(finished, finished)
    assert exc.value.code is ErrorCode.INVALID and "must differ from the source" in exc.value.message
    out = tmp_path / "exists.mcap"
    out.write_bytes(b"keep me")
    with pytest.raises(Conflict) as exc:
        recover(finished, out)
    assert exc.value.code is ErrorCode.CONFLICT and "already exists" in exc.value.message
    assert out.read_bytes() == b"keep me"
    with pytest.raises(NotFound) as exc:
        recover(tmp_path / "missing.mcap", tmp_path / "o.mcap")
    assert exc.value.code is ErrorCode.NOT_FOUND and "trace file not found" in exc.value.message
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(Invalid) as exc:
        recover(tmp_path / "empty.mcap", tmp_path / "o.mcap")
    assert "not an MCAP file (an empty file)" in exc.value.message
    with pytest.raises(Invalid) as exc:
        recover(tmp_path, tmp_path / "o.mcap")
    assert "is a directory" in exc.value.message
    assert not (tmp_path / "o.mcap").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []


def test_recover_does_not_touch_the_source(finished: Path, tmp_path: Path) -> None:
    before = finished.read_bytes()
    mtime = os.stat(finished).st_mtime_ns
    recover(finished, tmp_path / "x.mcap")
    assert finished.read_bytes() == before and os.stat(finished).st_mtime_ns == mtime


def test_default_output_name() -> None:
    assert default_output("/runs/r1/trace.mcap") == Path("/runs/r1/trace.recovered.mcap")
