"""TraceWriter, TraceReader and MemoryTraceSink on real MCAP files."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jsonschema
import pytest
from _trace_helpers import count_messages, make_env_step, make_metadata, one_of_each, write_records, write_trace
from mcap.reader import make_reader

from capevo.errors import Conflict, Corrupt, ErrorCode, Invalid
from capevo.runtime.traces import (
    EnvStep,
    MemoryTraceSink,
    PlanStep,
    TraceReader,
    TraceSink,
    TraceWriter,
    topics,
)
from capevo.runtime.traces.records import MESSAGE_ENCODING, SCHEMA_ENCODING
from capevo.runtime.traces.scan import McapScan, has_footer


def test_round_trip_of_every_record_type(tmp_path: Path) -> None:
    records = one_of_each(0) + one_of_each(1)
    path = write_trace(tmp_path / "run.mcap", records)
    reader = TraceReader(path)
    assert list(reader.records()) == records  # reader invariant 1: order and types
    assert list(reader.plan_steps()) == [r for r in records if isinstance(r, PlanStep)]
    assert list(reader.env_steps()) == [r for r in records if isinstance(r, EnvStep)]
    assert [r.TOPIC for r in reader.records(["/plan", "/episode/summary"])] == ["/plan", "/episode/summary"] * 2
    assert reader.metadata() == make_metadata()
    assert reader.topic_counts() == {
        "/plan": 2,
        "/ecm/invocation": 4,
        "/governance/intervention": 4,
        "/env/step": 2,
        "/safety/unsafe": 2,
        "/episode/summary": 2,
    }
    assert reader.scan_result is not None and reader.scan_result.complete


def test_file_is_standard_mcap_with_jsonschema_channels(tmp_path: Path) -> None:
    # What Foxglove needs: a finished file, jsonschema schemas, json messages that validate.
    path = write_trace(tmp_path / "run.mcap", one_of_each(), compression="zstd")
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(one_of_each())
        assert sorted(c.topic for c in summary.channels.values()) == sorted(topics())
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert schema.encoding == SCHEMA_ENCODING == "jsonschema"
            assert channel.message_encoding == MESSAGE_ENCODING == "json"
            jsonschema.Draft202012Validator.check_schema(json.loads(schema.data))
        n = 0
        for schema, _channel, message in reader.iter_messages(log_time_order=False):
            assert schema is not None
            jsonschema.validate(json.loads(message.data), json.loads(schema.data))
            assert message.log_time == message.publish_time > 0
            n += 1
        assert n == len(one_of_each())
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["capevo.run"]["run_id"] == "run-1"
    assert meta["capevo.run"]["phi_hash"] == "f" * 64
    assert meta["capevo.packages"]["mcap"]


def test_sequence_numbers_count_per_channel(tmp_path: Path) -> None:
    # Writer invariant 4.
    path = write_trace(tmp_path / "run.mcap", one_of_each(0) + one_of_each(1))
    seqs: dict[str, list[int]] = {}
    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            seqs.setdefault(channel.topic, []).append(message.sequence)
    assert seqs["/plan"] == [0, 1]
    assert seqs["/ecm/invocation"] == [0, 1, 2, 3]


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_compressions_and_small_chunks(tmp_path: Path, compression: str) -> None:
    steps = [make_env_step(0, i) for i in range(200)]
    path = write_trace(tmp_path / "run.mcap", steps, compression=compression, chunk_size=4096)
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 10  # chunk_size bounds the chunks
    assert {c.compression for c in summary.chunk_indexes} == {"" if compression == "none" else compression}
    assert list(TraceReader(path).env_steps()) == steps


def test_header_and_metadata_are_on_disk_at_once_and_channels_with_the_first_chunk(tmp_path: Path) -> None:
    # Writer invariant 1.
    from mcap.records import Channel, Header, Schema

    path = tmp_path / "run.mcap"
    w = TraceWriter(path, make_metadata(), background_flush=False)
    try:
        reader = TraceReader(path, allow_incomplete=True)
        assert reader.metadata() == make_metadata()
        assert not reader.complete
        assert isinstance(next(iter(McapScan(path))), Header)
        w.write_env_step(make_env_step())
        w.flush()
        records = list(McapScan(path))
        assert sorted(r.topic for r in records if isinstance(r, Channel)) == sorted(topics())
        assert all(r.encoding == "jsonschema" for r in records if isinstance(r, Schema))
    finally:
        w.close()


def test_flush_puts_every_record_in_the_file(tmp_path: Path) -> None:
    # Writer invariant 2 (explicit flush point), checked by reading the open file.
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), flush_interval_s=3600, background_flush=False) as w:
        for i in range(25):
            w.write_env_step(make_env_step(0, i))
        assert count_messages(path) == 0  # still in the open chunk
        w.flush()
        assert count_messages(path) == 25
        w.write_env_step(make_env_step(0, 25))
        assert count_messages(path) == 25
        assert w.messages_written == 26


def test_write_path_flushes_after_the_interval(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), flush_interval_s=0.05, background_flush=False) as w:
        w.write_env_step(make_env_step(0, 0))
        time.sleep(0.1)
        w.write_env_step(make_env_step(0, 1))  # this write sees the interval has passed
        assert count_messages(path) == 2


def test_background_thread_flushes_an_idle_writer(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), flush_interval_s=0.05) as w:
        for i in range(3):
            w.write_env_step(make_env_step(0, i))
        deadline = time.monotonic() + 10
        while count_messages(path) < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert count_messages(path) == 3
        assert w.flushes >= 1


def test_episode_summary_is_flushed_immediately(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), flush_interval_s=3600, background_flush=False) as w:
        write_records(w, one_of_each())
        assert count_messages(path) == len(one_of_each())


def test_close_is_idempotent_and_final(tmp_path: Path) -> None:
    # Writer invariant 3.
    path = tmp_path / "run.mcap"
    w = TraceWriter(path, make_metadata())
    w.write_env_step(make_env_step())
    w.close()
    w.close()
    assert w.closed and has_footer(path)
    assert w._thread is not None and not w._thread.is_alive()
    with pytest.raises(Conflict) as exc:
        w.write_env_step(make_env_step())
    assert exc.value.code is ErrorCode.CONFLICT
    assert "is closed" in exc.value.message
    with pytest.raises(Conflict):
        w.flush()


def test_exception_in_block_still_finishes_the_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with pytest.raises(RuntimeError), TraceWriter(path, make_metadata()) as w:
        w.write_env_step(make_env_step())
        raise RuntimeError("episode blew up")
    assert has_footer(path)
    assert len(list(TraceReader(path).env_steps())) == 1


def test_existing_file_is_not_overwritten(tmp_path: Path) -> None:
    # Writer invariant 5.
    path = write_trace(tmp_path / "run.mcap", [make_env_step()])
    with pytest.raises(Conflict) as exc:
        TraceWriter(path, make_metadata())
    assert exc.value.code is ErrorCode.CONFLICT
    assert "already exists" in exc.value.message
    assert len(list(TraceReader(path).env_steps())) == 1
    with TraceWriter(path, make_metadata(), overwrite=True) as w:
        w.write_plan_step(PlanStep(episode=0, step=0, ecm="a", version=1))
    assert TraceReader(path).topic_counts()["/env/step"] == 0


def test_parent_directories_are_created(tmp_path: Path) -> None:
    path = write_trace(tmp_path / "runs" / "r1" / "trace.mcap", [make_env_step()])
    assert has_footer(path)


def test_wrong_record_type_is_invalid(tmp_path: Path) -> None:
    with TraceWriter(tmp_path / "run.mcap", make_metadata()) as w:
        with pytest.raises(Invalid) as exc:
            w.write_env_step(PlanStep(episode=0, step=0, ecm="a", version=1))  # type: ignore[arg-type]
        assert exc.value.code is ErrorCode.INVALID
        assert exc.value.message == "write_env_step takes a EnvStep, got PlanStep"
        with pytest.raises(Invalid):
            w.write_plan_step(make_env_step())  # type: ignore[arg-type]
        assert w.messages_written == 0


@pytest.mark.parametrize(
    ("kw", "text"),
    [
        ({"chunk_size": 0}, "chunk_size must be a positive integer"),
        ({"chunk_size": 1.5}, "chunk_size must be a positive integer"),
        ({"flush_interval_s": 0}, "flush_interval_s must be a positive number"),
        ({"compression": "brotli"}, "unknown trace compression 'brotli'; valid: lz4, zstd, none"),
    ],
)
def test_bad_writer_config_is_invalid(tmp_path: Path, kw: dict[str, object], text: str) -> None:
    with pytest.raises(Invalid) as exc:
        TraceWriter(tmp_path / "run.mcap", make_metadata(), **kw)  # type: ignore[arg-type]
    assert exc.value.code is ErrorCode.INVALID
    assert text in exc.value.message
    assert not (tmp_path / "run.mcap").exists()


def test_reader_refuses_an_unfinished_file_by_default(tmp_path: Path) -> None:
    # Reader invariant 2.
    path = tmp_path / "run.mcap"
    w = TraceWriter(path, make_metadata(), background_flush=False)
    try:
        w.write_env_step(make_env_step())
        w.flush()
        with pytest.raises(Corrupt) as exc:
            TraceReader(path)
        assert exc.value.code is ErrorCode.CORRUPT
        assert "unfinished" in exc.value.message and "capevo trace recover" in exc.value.message
        lenient = TraceReader(path, allow_incomplete=True)
        assert len(list(lenient.env_steps())) == 1
        assert lenient.scan_result is not None and not lenient.scan_result.complete
        assert lenient.scan_result.reason == "file ends without a footer"
    finally:
        w.close()


def test_reader_skips_foreign_channels(tmp_path: Path) -> None:
    # Reader invariant 3: a channel another tool added is ignored.
    from mcap.writer import Writer

    path = tmp_path / "mixed.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        for name, data in make_metadata().to_mcap().items():
            w.add_metadata(name, data)
        sid = w.register_schema("capevo.PlanStep", "jsonschema", json.dumps(PlanStep.SCHEMA).encode())
        plan = w.register_channel("/plan", "json", sid)
        other = w.register_channel("/camera", "json", 0)
        w.add_message(other, 1, b'{"pixels": 1}', 1)
        w.add_message(plan, 2, b'{"episode":0,"step":0,"ecm":"a","version":1,"reason":""}', 2)
        w.finish()
    assert list(TraceReader(path).records()) == [PlanStep(episode=0, step=0, ecm="a", version=1)]


def test_reader_errors(tmp_path: Path) -> None:
    with pytest.raises(Invalid) as exc:
        list(TraceReader(write_trace(tmp_path / "r.mcap", [])).records(["/nope"]))
    assert "unknown trace topic" in exc.value.message
    (tmp_path / "text.mcap").write_text("hello, I am not an MCAP file")
    with pytest.raises(Invalid) as exc:
        TraceReader(tmp_path / "text.mcap")
    assert exc.value.code is ErrorCode.INVALID
    assert "not an MCAP file (bad magic bytes)" in exc.value.message


def test_empty_trace_is_valid(tmp_path: Path) -> None:
    path = write_trace(tmp_path / "empty.mcap", [])
    reader = TraceReader(path)
    assert list(reader.records()) == []
    assert reader.metadata().run_id == "run-1"
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.channels) == len(topics())


# -- MemoryTraceSink ------------------------------------------------------------------------


def test_both_sinks_satisfy_the_protocol(tmp_path: Path) -> None:
    with TraceWriter(tmp_path / "run.mcap", make_metadata()) as w:
        assert isinstance(w, TraceSink)
    assert isinstance(MemoryTraceSink(), TraceSink)


def test_memory_sink_keeps_records_in_order() -> None:
    # Sink invariant 2.
    records = one_of_each(0) + one_of_each(1)
    sink = MemoryTraceSink(make_metadata())
    with sink:
        write_records(sink, records)  # type: ignore[arg-type]
    assert sink.records == records
    assert sink.by_topic("/plan") == sink.plan_steps == [r for r in records if isinstance(r, PlanStep)]
    assert len(sink.invocations) == 4 and len(sink.interventions) == 4
    assert len(sink.env_steps) == 2 and len(sink.episode_summaries) == 2
    assert sink.closed


def test_memory_sink_rejects_what_the_writer_rejects(tmp_path: Path) -> None:
    # Sink invariant 1: same errors as the real writer.
    import dataclasses

    # The writer refuses a record that does not encode when it encodes it (at the latest, the
    # next flush); the sink at once.
    bad = dataclasses.replace(make_env_step(), obs=("x",))  # type: ignore[arg-type]
    sink = MemoryTraceSink()
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata()) as w:
        for target in (sink, w):
            with pytest.raises(Invalid) as exc:
                target.write_env_step(bad)
                target.flush()
            assert "EnvStep does not encode as JSON" in exc.value.message
            with pytest.raises(Invalid) as exc:
                target.write_episode_summary(make_env_step())  # type: ignore[arg-type]
            assert exc.value.message == "write_episode_summary takes a EpisodeSummary, got EnvStep"
    assert sink.records == [] and list(TraceReader(path).records()) == []
    sink.close()
    with pytest.raises(Conflict) as exc:
        sink.write_plan_step(PlanStep(episode=0, step=0, ecm="a", version=1))
    assert exc.value.code is ErrorCode.CONFLICT


# -- writer invariant 4 ----------------------------------------------------------------------


def test_records_keep_order_write_times_and_sequences(tmp_path: Path) -> None:
    records = one_of_each(0) + one_of_each(1)
    windows: list[tuple[int, int]] = []
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), background_flush=False, flush_interval_s=3600) as w:
        for r in records:
            before = time.time_ns()
            write_records(w, [r])
            windows.append((before, time.time_ns()))
            time.sleep(0.002)
        assert w.messages_written == len(records)
    assert list(TraceReader(path).records()) == records
    with path.open("rb") as f:
        messages = [
            (m.log_time, m.channel_id, m.sequence) for _, _, m in make_reader(f).iter_messages(log_time_order=False)
        ]
    for (log_time, _, _), (before, after) in zip(messages, windows, strict=True):
        assert before <= log_time <= after  # stamped by the write call
    by_channel: dict[int, list[int]] = {}
    for _, channel, sequence in messages:
        by_channel.setdefault(channel, []).append(sequence)
    assert all(seqs == list(range(len(seqs))) for seqs in by_channel.values())


def test_a_record_that_does_not_encode_is_left_out_by_the_call_that_encodes_it(tmp_path: Path) -> None:
    bad = dataclasses.replace(make_env_step(0, 1), obs=("x",))  # type: ignore[arg-type]
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), background_flush=False, flush_interval_s=3600) as w:
        w.write_env_step(make_env_step(0, 0))
        w.write_env_step(bad)  # kept, not yet encoded
        w.write_env_step(make_env_step(0, 2))
        assert w.messages_written == 3
        with pytest.raises(Invalid, match="EnvStep does not encode as JSON"):
            w.flush()
        assert w.messages_written == 2 and count_messages(path) == 2  # the others are in the file
        w.flush()  # raised once
    assert [s.step for s in TraceReader(path).env_steps()] == [0, 2]
    with path.open("rb") as f:
        sequences = [m.sequence for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert sequences == [0, 1]  # the refused record took no sequence number


def test_a_full_batch_of_kept_records_is_encoded_by_the_write_that_fills_it(tmp_path: Path) -> None:
    from capevo.runtime.traces.writer import KEPT_RECORDS

    bad = dataclasses.replace(make_env_step(0, 0), obs=("x",))  # type: ignore[arg-type]
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), background_flush=False, flush_interval_s=3600) as w:
        w.write_env_step(bad)
        for i in range(1, KEPT_RECORDS - 1):
            w.write_env_step(make_env_step(0, i, obs_dim=2))
        with pytest.raises(Invalid, match="EnvStep does not encode as JSON"):
            w.write_env_step(make_env_step(0, KEPT_RECORDS - 1, obs_dim=2))
        assert w.messages_written == KEPT_RECORDS - 1
    assert [s.step for s in TraceReader(path).env_steps()] == list(range(1, KEPT_RECORDS))


def test_close_finishes_the_file_before_raising_for_a_kept_bad_record(tmp_path: Path) -> None:
    bad = dataclasses.replace(make_env_step(0, 1), next_obs=(None,))  # type: ignore[arg-type]
    path = tmp_path / "run.mcap"
    w = TraceWriter(path, make_metadata(), background_flush=False)
    w.write_env_step(make_env_step(0, 0))
    w.write_env_step(bad)
    with pytest.raises(Invalid, match="EnvStep does not encode as JSON"):
        w.close()
    assert w.closed and has_footer(path)
    assert [s.step for s in TraceReader(path).env_steps()] == [0]
    w.close()  # still idempotent


def test_the_background_thread_encodes_an_idle_writers_records(tmp_path: Path) -> None:
    # An idle writer's kept records reach the file by the timer; a bad one among them is
    # reported by the owner's next call.
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), flush_interval_s=0.1) as w:
        for i in range(5):
            w.write_env_step(make_env_step(0, i))
        w.write_env_step(dataclasses.replace(make_env_step(0, 5), action=("x",)))  # type: ignore[arg-type]
        deadline = time.monotonic() + 20
        while count_messages(path) < 5 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert count_messages(path) == 5
        with pytest.raises(Invalid, match="EnvStep does not encode as JSON"):
            w.write_env_step(make_env_step(0, 6))
        w.write_env_step(make_env_step(0, 7))
    assert [s.step for s in TraceReader(path).env_steps()] == [0, 1, 2, 3, 4, 6, 7]


def test_a_write_the_os_refuses_ends_the_writer_with_unavailable(tmp_path: Path) -> None:
    # The OS refusing a write (here: the file descriptor closed under the writer) surfaces as
    # Unavailable from the call that flushed, and every later write raises the same error.
    import os

    from capevo.errors import Unavailable

    w = TraceWriter(tmp_path / "run.mcap", make_metadata(), flush_interval_s=3600, background_flush=False)
    w.write_env_step(make_env_step(0, 0))
    os.close(w._file.fileno())
    with pytest.raises(Unavailable, match="failed") as first:
        w.flush()
    with pytest.raises(Unavailable) as later:
        w.write_env_step(make_env_step(0, 1))
    assert later.value is first.value
    with pytest.raises(Unavailable):
        w.close()
    assert w.closed
