"""McapFileWriter against the mcap package's readers (capevo.runtime.traces.mcapfile invariants 1-3)."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.records import Chunk, MessageIndex
from mcap.stream_reader import StreamReader

from capevo.errors import Invalid
from capevo.runtime.traces.mcapfile import McapFileWriter

messages = st.lists(
    st.tuples(st.integers(1, 3), st.integers(0, 2**63 - 1), st.integers(0, 2**32 - 1), st.binary(max_size=300)),
    max_size=80,
)


def build(msgs: list[tuple[int, int, int, bytes]], *, chunk_size: int, compression: str, flush_every: int = 0) -> bytes:
    buf = io.BytesIO()
    w = McapFileWriter(buf, chunk_size=chunk_size, compression=compression)
    w.start(profile="p", library="test")
    w.add_metadata("m", {"k": "v"})
    sid = w.register_schema(name="s", encoding="jsonschema", data=b'{"type":"object"}')
    for topic in ("/a", "/b", "/c"):
        w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
    for i, (channel, t, seq, data) in enumerate(msgs):
        w.add_message(channel, t, t // 2, seq, data)
        if flush_every and i % flush_every == 0:
            w.flush()
    w.finish()
    assert w.position == len(buf.getvalue())  # invariant 3
    assert w.messages == len(msgs)
    return buf.getvalue()


@settings(max_examples=60, deadline=None)
@given(messages, st.sampled_from(["lz4", "zstd", ""]), st.sampled_from([64, 1024, 1 << 20]), st.integers(0, 7))
def test_mcap_readers_see_every_message(
    msgs: list[tuple[int, int, int, bytes]], compression: str, chunk_size: int, flush_every: int
) -> None:
    # Invariant 1, with out-of-order times, several channels, tiny and huge chunks.
    data = build(msgs, chunk_size=chunk_size, compression=compression, flush_every=flush_every)
    reader = make_reader(io.BytesIO(data), validate_crcs=True)
    summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None
    stats = summary.statistics
    assert stats.message_count == len(msgs) and stats.chunk_count == len(summary.chunk_indexes)
    assert stats.channel_count == 3 and stats.schema_count == 1 and stats.metadata_count == 1
    for cid in (1, 2, 3):
        assert stats.channel_message_counts.get(cid, 0) == sum(1 for m in msgs if m[0] == cid)
    if msgs:
        assert stats.message_start_time == min(m[1] for m in msgs)
        assert stats.message_end_time == max(m[1] for m in msgs)
    got = [
        (m.channel_id, m.log_time, m.sequence, m.data, m.publish_time, ch.topic)
        for _, ch, m in reader.iter_messages(log_time_order=False)
    ]
    assert sorted(got) == sorted((c, t, s, d, t // 2, f"/{'abc'[c - 1]}") for c, t, s, d in msgs)
    assert [m.name for m in reader.iter_metadata()] == ["m"]
    # The whole stream, CRCs included, parses with the reference stream reader too.
    records = list(StreamReader(io.BytesIO(data), validate_crcs=True, emit_chunks=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert all(c.compression == compression for c in chunks)
    # Invariant 2: no empty chunk, and each chunk's message indexes cover its messages.
    assert sum(len(r.records) for r in records if isinstance(r, MessageIndex)) == len(msgs)
    assert all(c.uncompressed_size > 0 for c in chunks)


def test_chunk_size_bounds_chunks_and_empty_flush_writes_nothing() -> None:
    buf = io.BytesIO()
    w = McapFileWriter(buf, chunk_size=500, compression="lz4")
    w.start(profile="", library="")
    cid = w.register_channel(topic="/a", message_encoding="json", schema_id=0)
    before = w.position
    w.flush()
    assert w.position == before  # invariant 2: no empty chunk
    for i in range(50):
        w.add_message(cid, i, i, i, b"x" * 100)
    w.finish()
    summary = make_reader(io.BytesIO(buf.getvalue())).get_summary()
    assert summary is not None
    # A message record is 9 + 22 + 100 = 131 bytes: 4 of them reach 500, so 12 full chunks + 1.
    assert len(summary.chunk_indexes) == 13
    assert all(c.uncompressed_size < 500 + 131 for c in summary.chunk_indexes)


def test_unknown_compression_is_invalid(tmp_path: Path) -> None:
    with pytest.raises(Invalid) as exc:
        McapFileWriter(io.BytesIO(), chunk_size=10, compression="brotli")
    assert "unknown MCAP chunk compression 'brotli'" in exc.value.message


def build_batched(msgs: list[tuple[int, int, int, bytes]], *, chunk_size: int, batch: int, batched: bool) -> bytes:
    """The file ``msgs`` make (publish time = log time), added ``batch`` at a time with
    add_messages, or one by one with add_message, with a flush after each batch."""
    buf = io.BytesIO()
    w = McapFileWriter(buf, chunk_size=chunk_size, compression="lz4")
    w.start(profile="p", library="test")
    sid = w.register_schema(name="s", encoding="jsonschema", data=b'{"type":"object"}')
    for topic in ("/a", "/b", "/c"):
        w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
    for i in range(0, len(msgs), batch):
        if batched:
            w.add_messages(msgs[i : i + batch])
        else:
            for channel, t, seq, data in msgs[i : i + batch]:
                w.add_message(channel, t, t, seq, data)
        w.flush()
    w.finish()
    assert w.messages == len(msgs)
    return buf.getvalue()


@settings(max_examples=80, deadline=None)
@given(messages, st.integers(1, 40))
def test_add_messages_writes_the_bytes_add_message_writes_within_a_chunk(
    msgs: list[tuple[int, int, int, bytes]], batch: int
) -> None:
    # Same records, indexes and summary while no batch fills a chunk.
    want = build_batched(msgs, chunk_size=1 << 20, batch=batch, batched=False)
    assert build_batched(msgs, chunk_size=1 << 20, batch=batch, batched=True) == want


@settings(max_examples=80, deadline=None)
@given(messages, st.sampled_from([64, 1024]), st.integers(1, 40))
def test_add_messages_finishes_a_full_chunk_after_the_batch_never_inside_it(
    msgs: list[tuple[int, int, int, bytes]], chunk_size: int, batch: int
) -> None:
    data = build_batched(msgs, chunk_size=chunk_size, batch=batch, batched=True)
    reader = make_reader(io.BytesIO(data))
    got = [(c.id, m.log_time, m.sequence, m.data) for _, c, m in reader.iter_messages(log_time_order=False)]
    assert got == [(c, t, s, d) for c, t, s, d in msgs]
    summary = reader.get_summary()
    assert summary is not None
    # Invariant 2: each batch is flushed, so every chunk holds exactly one batch.
    assert [c.message_end_time for c in summary.chunk_indexes] == [
        max(t for _, t, _, _ in msgs[i : i + batch]) for i in range(0, len(msgs), batch)
    ]
