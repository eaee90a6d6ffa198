"""Rows (capevo.runtime.traces.rows) and their batch encoding: the same messages as records."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _trace_helpers import f32, make_metadata, one_of_each, write_records
from hypothesis import given
from hypothesis import strategies as st
from mcap.reader import make_reader

from capevo.errors import Conflict, Invalid
from capevo.runtime.state import ArmState
from capevo.runtime.traces import EcmInvocation, EnvStep, MemoryTraceSink, Outcome, TraceReader, TraceWriter, codec
from capevo.runtime.traces import rows as rows_module
from capevo.runtime.traces.rows import env_step_of, invocation_of, key_state_of

any_floats = st.floats(allow_nan=True, allow_infinity=True)
# The record path prints a payload with "null" in a name or an error through its template
# (other bytes, the same record); names here leave that to test_null_in_a_name_decodes_alike.
names = st.text(max_size=12).filter(lambda s: "null" not in s)
ints = st.integers(min_value=0, max_value=2**53)
# Mostly what the loop passes, sometimes what only a careless caller would (orjson, and so the
# record path, refuses integers beyond 64 bits).
odd_ints = ints | st.sampled_from([True, 2.5, "3", None, -1, 2**63, 2**64, 2**70])
odd_names = names | st.sampled_from([7, None])


def float32_array(values: list[float]) -> np.ndarray:
    with np.errstate(over="ignore"):  # beyond float32's range: inf, as the env would hold
        return np.asarray(values, dtype=np.float32)


def vectors(size: int = 40) -> st.SearchStrategy[Any]:
    floats = st.lists(any_floats, max_size=size)
    return st.one_of(
        floats.map(tuple),
        floats.map(float32_array),  # the loop's observations
        floats.map(lambda v: float32_array(v).tobytes()),  # packed input (input_state_of)
        st.just(b"\x00" * 6),  # not whole float32 values
        floats.map(lambda v: np.asarray(v, dtype=np.float64)),
        # float32 arrays the C splicer must not print as they are (it reads numpy's array head)
        floats.map(lambda v: float32_array(v + v)[::2]),  # strided
        floats.map(lambda v: float32_array(v).astype(">f4")),  # byte-swapped
        floats.map(lambda v: float32_array([0.5, *v])[1:]),  # offset into its buffer
        st.lists(st.integers(-5, 5) | any_floats, max_size=8).map(tuple),  # not all floats
        st.just(("x", 1.0)),  # does not encode
    )


arms = st.builds(lambda p, f: ArmState(eef_pos=p, eef_force=f), vectors(3), vectors(3))
# Mostly positions in a vector of up to 40 values (the loop's selections from its observation),
# sometimes past its end, negative or not a tuple of ints: the record path decides those.
input_indexes = (
    st.none()
    | st.lists(st.integers(0, 40), max_size=8).map(tuple)
    | st.sampled_from([(-1,), (0, 2**70), [0, 1], (True,), (1.5,), "0"])
)
arm_lists = st.lists(arms, max_size=2).map(tuple) | st.just((object(),))


@st.composite
def batches(draw: st.DrawFn) -> list[tuple[bool, tuple[Any, ...]]]:
    """A batch of env step and invocation rows whose vectors repeat the way the loop's do."""
    pool = draw(st.lists(vectors(), min_size=1, max_size=4))
    shared = st.sampled_from(pool) | vectors()
    rows: list[tuple[bool, tuple[Any, ...]]] = []
    for _ in range(draw(st.integers(1, 6))):
        head = (draw(odd_ints), draw(odd_ints), draw(odd_names), draw(odd_ints))
        action = draw(shared)
        if draw(st.booleans()):
            reward = draw(any_floats | st.integers(-3, 3))
            flags = (draw(st.booleans()), draw(st.booleans()), draw(st.booleans()))
            rows.append((True, (*head, draw(shared), action, reward, draw(shared), *flags, draw(arm_lists))))
        else:
            outcome = draw(st.sampled_from(Outcome) | st.sampled_from(["ok", "bogus"]))
            error = draw(st.none() | names)
            output = draw(st.none() | st.just(action))
            selects = draw(input_indexes)
            rows.append((False, (*head, draw(shared), selects, output, draw(any_floats), outcome, error)))
    return rows


def through_record(is_step: bool, row: tuple[Any, ...]) -> bytes | type[Invalid]:
    encoder = codec.RecordEncoder()
    try:
        return encoder.env_step(env_step_of(row)) if is_step else encoder.invocation(invocation_of(row))  # type: ignore[arg-type]
    except Invalid:
        return Invalid


def test_the_c_splicer_is_built() -> None:
    # scripts/test builds it; without it the tests below would compare Python with itself.
    assert codec.rows_kernel_available()


@pytest.mark.parametrize("kernel", [True, False], ids=["c", "python"])
@given(batch=batches())
def test_a_row_encodes_to_its_records_message(kernel: bool, batch: list[tuple[bool, tuple[Any, ...]]]) -> None:
    payloads = codec.RecordEncoder(kernel=kernel).rows(batch)
    assert len(payloads) == len(batch)
    for (is_step, row), payload in zip(batch, payloads, strict=True):
        want = through_record(is_step, row)
        if want is Invalid:
            assert isinstance(payload, Invalid)
        else:
            assert payload == want


@pytest.mark.parametrize("kernel", [True, False], ids=["c", "python"])
@given(batch=batches())
def test_a_batch_encodes_each_row_as_alone(kernel: bool, batch: list[tuple[bool, tuple[Any, ...]]]) -> None:
    # Sharing vector texts across rows never hands one row another's values.
    together = codec.RecordEncoder(kernel=kernel).rows(batch)
    alone = [codec.RecordEncoder(kernel=kernel).rows([item])[0] for item in batch]
    for a, b in zip(together, alone, strict=True):
        assert (a == b) if isinstance(b, bytes) else isinstance(a, Invalid)


def test_the_c_splicer_refuses_what_is_not_a_batch() -> None:
    with pytest.raises(TypeError, match="list of"):
        codec.RecordEncoder().rows([(True,)])  # type: ignore[list-item]
    assert codec.RecordEncoder().rows([]) == codec.RecordEncoder(kernel=False).rows([]) == []


def test_null_in_a_name_or_error_decodes_alike() -> None:
    obs = np.asarray([0.5, -1.25], dtype=np.float32)
    arm = ArmState(eef_pos=(0.125, 0.25, 0.375), eef_force=(0.0, 0.0, 1.5))  # float32 values
    step = (0, 1, "nullify", 2, obs, (0.25, 0.5), 1.0, obs, False, False, True, (arm,))
    call = (0, 1, "nullify", 2, obs, None, (0.25,), 0.001, Outcome.EXCEPTION, "null pointer")
    step_payload, call_payload = codec.RecordEncoder().rows([(True, step), (False, call)])
    assert isinstance(step_payload, bytes) and isinstance(call_payload, bytes)
    assert codec.decode(EnvStep.TOPIC, step_payload) == env_step_of(step)  # type: ignore[arg-type]
    assert codec.decode(EcmInvocation.TOPIC, call_payload) == invocation_of(call)  # type: ignore[arg-type]


def test_key_state_names_each_arm_in_order() -> None:
    a = ArmState(eef_pos=(1.0, 2.0, 3.0), eef_force=(0.0, 0.0, 0.0))
    b = ArmState(eef_pos=(4.0, 5.0, 6.0), eef_force=(1.0, 1.0, 1.0))
    assert list(key_state_of((a, b)).items()) == [
        ("arm0_eef_pos", a.eef_pos),
        ("arm0_eef_force", a.eef_force),
        ("arm1_eef_pos", b.eef_pos),
        ("arm1_eef_force", b.eef_force),
    ]
    assert key_state_of(()) == {}


def loop_like_rows(steps: int, arms: int = 1) -> list[tuple[bool, tuple[Any, ...]]]:
    """Rows as the episode loop makes them: each step's obs is the last step's next_obs, which
    is also the ECM's input."""
    rng = np.random.default_rng(5)
    obs = rng.standard_normal(45).astype(np.float32)
    rows: list[tuple[bool, tuple[Any, ...]]] = []
    for i in range(steps):
        nxt = rng.standard_normal(45).astype(np.float32)
        action = f32(rng.uniform(-1, 1, 7))  # float32 values, so the records read back exactly
        state = tuple(
            ArmState(eef_pos=f32(rng.standard_normal(3)), eef_force=(0.0, 0.0, float(i)))  # type: ignore[arg-type]
            for _ in range(arms)
        )
        selects = (3, 4, 5, 40, 41) if i % 2 else None  # the ECM's inputs in the observation, or all of it
        rows.append((False, (0, i, "reach", 1, obs, selects, action, 0.002, Outcome.OK, None)))
        rows.append((True, (0, i, "reach", 1, obs, action, -0.5 * i, nxt, False, i == steps - 1, False, state)))
        obs = nxt
    return rows


@pytest.mark.parametrize("batch", [1, 5, 64])
@pytest.mark.usefixtures("writer_parts")  # the C parts and their Python versions (conftest.py)
def test_writer_files_rows_as_their_records_in_write_order(tmp_path: Path, batch: int) -> None:
    rows = loop_like_rows(12, arms=2)
    records = one_of_each(0)  # its one env step comes after the rows
    expected = []
    path = tmp_path / "run.mcap"
    with TraceWriter(path, make_metadata(), batch=batch) as w:
        write_records(w, records[:3])
        expected += records[:3]
        for is_step, row in rows:
            (w.write_env_step_row if is_step else w.write_invocation_row)(row)  # type: ignore[arg-type]
            expected.append(env_step_of(row) if is_step else invocation_of(row))  # type: ignore[arg-type]
        write_records(w, records[3:])
        expected += records[3:]
    assert list(TraceReader(path).records()) == expected
    with path.open("rb") as f:
        sequences: dict[str, list[int]] = {}
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            sequences.setdefault(channel.topic, []).append(message.sequence)
    assert all(seq == list(range(len(seq))) for seq in sequences.values())
    # The bytes on the wire are the records' own.
    with path.open("rb") as f:
        steps = [m.data for _, _c, m in make_reader(f).iter_messages(topics=["/env/step"], log_time_order=False)]
    assert steps[:-1] == [codec.RecordEncoder().env_step(env_step_of(r)) for s, r in rows if s]  # type: ignore[arg-type]


@pytest.mark.usefixtures("writer_parts")  # the C parts and their Python versions (conftest.py)
def test_a_row_that_does_not_encode_is_dropped_with_invalid(tmp_path: Path) -> None:
    rows = loop_like_rows(3)
    bad = (0, 9, "reach", 1, ("x",), (0.0,), 0.0, (0.0,), False, False, False, ())
    path = tmp_path / "run.mcap"
    w = TraceWriter(path, make_metadata(), batch=10)
    w.write_invocation_row(rows[0][1])  # type: ignore[arg-type]
    w.write_env_step_row(bad)  # type: ignore[arg-type]
    w.write_env_step_row(rows[1][1])  # type: ignore[arg-type]
    with pytest.raises(Invalid) as exc:
        w.flush()
    assert "EnvStep does not encode as JSON" in exc.value.message
    w.close()
    assert list(TraceReader(path).records()) == [invocation_of(rows[0][1]), env_step_of(rows[1][1])]  # type: ignore[arg-type]


@pytest.mark.usefixtures("writer_parts")  # the C parts and their Python versions (conftest.py)
def test_sinks_reject_a_row_of_the_wrong_shape_at_once(tmp_path: Path) -> None:
    with TraceWriter(tmp_path / "run.mcap", make_metadata(), batch=64) as w:
        for target in (MemoryTraceSink(), w):
            with pytest.raises(Invalid) as exc:
                target.write_env_step_row((0, 1, "reach"))  # type: ignore[arg-type]
            assert exc.value.message == "write_env_step_row takes a tuple of 12 fields, got a tuple of 3"
            with pytest.raises(Invalid) as exc:
                target.write_invocation_row([0] * 10)  # type: ignore[arg-type]
            assert exc.value.message == "write_invocation_row takes a tuple of 10 fields, got a list"
    assert w.messages_written == 0


@pytest.mark.usefixtures("writer_parts")  # the C parts and their Python versions (conftest.py)
def test_memory_sink_keeps_rows_as_records_and_rejects_what_the_writer_rejects() -> None:
    rows = loop_like_rows(4)
    sink = MemoryTraceSink()
    for is_step, row in rows:
        (sink.write_env_step_row if is_step else sink.write_invocation_row)(row)  # type: ignore[arg-type]
    assert sink.records == [env_step_of(r) if s else invocation_of(r) for s, r in rows]  # type: ignore[arg-type]
    assert json.loads(codec.encode(sink.env_steps[0]))["key_state"]["arm0_eef_force"] == [0.0, 0.0, 0.0]
    with pytest.raises(Invalid) as exc:
        sink.write_env_step_row((0, 1, "reach", 1, (), (), 0.0, (), False, False, False, (object(),)))
    assert "arms need eef_pos and eef_force" in exc.value.message
    sink.close()
    with pytest.raises(Conflict):
        sink.write_env_step_row(rows[1][1])  # type: ignore[arg-type]
    assert len(sink.records) == len(rows)


@pytest.mark.parametrize("packed", [True, False], ids=["c", "python"])
def test_input_state_of_is_the_concatenation_of_the_keys_the_observation_has(packed: bool) -> None:
    pack = rows_module.input_state_of if packed else rows_module.concatenated_input
    rng = np.random.default_rng(3)
    obs = {
        "a": rng.standard_normal(3).astype(np.float32),
        "b": rng.standard_normal((2, 2)).astype(np.float32),
        "c": rng.standard_normal(1).astype(np.float32),
    }
    got = pack(obs, ("b", "missing", "a"))
    assert (type(got) is bytes) == packed
    want = np.concatenate([obs["b"], obs["a"]], axis=None)
    call = invocation_of((0, 0, "reach", 1, got, None, None, 0.0, Outcome.OK, None))
    assert isinstance(call.input_state, np.ndarray) and not call.input_state.flags.writeable
    assert call.input_state.tolist() == want.tolist()
    # The same values, selected from the flat observation by their positions in it.
    flat = np.concatenate([obs["c"], obs["b"], obs["a"]], axis=None)
    index = rows_module.observation_index(obs, ("c", "b", "a"), ("b", "missing", "a"))
    assert index == (1, 2, 3, 4, 5, 6, 7)
    selected = invocation_of((0, 0, "reach", 1, flat, index, None, 0.0, Outcome.OK, None)).input_state
    assert selected.tolist() == want.tolist() and not selected.flags.writeable  # type: ignore[union-attr]
    assert rows_module.observation_index(obs, ("c", "a"), ("b",)) is None  # b is not in the flat observation
    assert pack(obs, ("missing",)) in ((), b"")
    # What is not a float32 array (or not a dict) takes numpy, whatever the build.
    mixed = {"a": np.arange(3, dtype=np.float64), "b": obs["b"]}
    assert pack(mixed, ("a", "b")).tolist() == np.concatenate([mixed["a"], obs["b"]], axis=None).tolist()
    strided = {"t": obs["b"][:, 0]}  # not C-contiguous
    assert pack(strided, ("t",)).tolist() == obs["b"][:, 0].tolist()
    from types import MappingProxyType

    assert pack(MappingProxyType(obs), ("a",)).tolist() == obs["a"].tolist()
    assert pack(obs, ["a"]).tolist() == obs["a"].tolist()  # type: ignore[arg-type]
    assert rows_module.input_state_of is not rows_module.concatenated_input  # the C part is built


@pytest.mark.parametrize("kernel", [True, False], ids=["c", "python"])
def test_packed_input_bytes_encode_as_their_array(kernel: bool) -> None:
    values = np.asarray([0.5, -1.25, 3.0], dtype=np.float32)
    as_bytes = (0, 2, "grasp", 3, values.tobytes(), None, (0.25,), 0.001, Outcome.OK, None)
    as_array = (0, 2, "grasp", 3, values, None, (0.25,), 0.001, Outcome.OK, None)
    encoder = codec.RecordEncoder(kernel=kernel)
    assert encoder.rows([(False, as_bytes)]) == encoder.rows([(False, as_array)])
    (bad,) = encoder.rows([(False, (0, 2, "grasp", 3, b"\x00" * 5, None, None, 0.0, Outcome.OK, None))])
    assert isinstance(bad, Invalid) and "not whole float32 values" in bad.message


@pytest.mark.parametrize("kernel", [True, False], ids=["c", "python"])
def test_an_input_index_encodes_the_values_it_selects(kernel: bool) -> None:
    obs = np.asarray([0.5, -1.25, 3.0, 1e-7, float("nan")], dtype=np.float32)
    obs.flags.writeable = False
    encoder = codec.RecordEncoder(kernel=kernel)

    def call(index: object, inputs: np.ndarray = obs) -> tuple[object, ...]:
        return (0, 2, "grasp", 3, inputs, index, (0.25,), 0.001, Outcome.OK, None)

    selected = encoder.rows([(False, call((2, 0, 3, 0)))])[0]
    assert selected == encoder.rows([(False, call(None, obs[[2, 0, 3, 0]]))])[0]
    assert json.loads(selected)["input_state"] == [3.0, 0.5, 1e-07, 0.5]
    assert json.loads(encoder.rows([(False, call(()))])[0])["input_state"] == []
    # A selected NaN is null, as in the record (the record path prints it); the NaN it skips is not read.
    assert json.loads(encoder.rows([(False, call((4, 1)))])[0])["input_state"] == [None, -1.25]
    for bad in ((5,), (-1,), (0, True), [0], (0.0,)):
        (payload,) = encoder.rows([(False, call(bad))])
        assert isinstance(payload, Invalid) and payload.details["field"] == "input_index"


@pytest.mark.skipif(not codec.rows_kernel_available(), reason="C splicer not built")
@given(
    values=st.lists(
        st.floats(width=32, allow_nan=False, allow_infinity=False) | st.sampled_from([-0.0, -1e-7, -123456.0]),
        max_size=600,
    ),
    picks=st.lists(st.integers(0, 10**6), max_size=40),
)
def test_a_selection_from_a_vector_of_any_length_is_cut_as_in_python(values: list[float], picks: list[int]) -> None:
    # Vectors past the C splicer's 255-element stack buffer and every alignment of their commas
    # (it scans eight bytes at a time); '-' after a comma is where a borrowing zero-byte test errs.
    obs = np.asarray(values, dtype=np.float32)
    obs.flags.writeable = False
    index = tuple(p % len(values) for p in picks) if values else ()
    row = (0, 2, "grasp", 3, obs, index, (0.25,), 0.001, Outcome.OK, None)
    spliced = codec.RecordEncoder(kernel=True).rows([(False, row)])[0]
    assert spliced == codec.RecordEncoder(kernel=False).rows([(False, row)])[0]
    # the shortest text that names each float32 (read back as float32)
    assert np.array_equal(np.asarray(json.loads(spliced)["input_state"], dtype=np.float32), obs[list(index)])


@pytest.mark.skipif(not codec.rows_kernel_available(), reason="C splicer not built")
def test_the_c_splicer_splices_the_rows_the_episode_loop_hands_it() -> None:
    # The record path prints the same bytes, so only this tells a row the splicer gave up on
    # (at tens of µs of Python, cold, per row) from one it spliced.
    from capevo.runtime.traces import _native

    obs = np.arange(46, dtype=np.float32) / 7
    obs.flags.writeable = False
    packed = np.asarray(obs[:5]).tobytes()
    arm = ArmState(eef_pos=(0.1, 0.2, 0.9), eef_force=(0.0, -1.5, 3.25))
    rows = [
        (True, (0, 1, "pick.reach", 0, obs, (0.5, -1.0), 0.1, obs, False, False, False, (arm,))),
        (False, (0, 1, "pick.reach", 0, obs, tuple(range(21, 30)), (0.5, -1.0), 0.001, Outcome.OK, None)),
        (False, (0, 1, "pick.reach", 0, packed, None, None, 0.001, Outcome.TIMEOUT, "too slow")),
        (False, (0, 1, "pick.reach", 0, obs, None, (0.5,), 0.001, Outcome.OK, None)),
    ]
    encoder = codec.RecordEncoder(kernel=True)
    spliced = _native.encode_rows(rows, encoder.name_json)
    assert all(type(payload) is bytes for payload in spliced)
    assert spliced == codec.RecordEncoder(kernel=False).rows(rows)


@pytest.mark.skipif(not codec.rows_kernel_available(), reason="C splicer not built")
def test_the_c_splicer_reads_numpys_array_head_here() -> None:
    # Its probes agreed with the buffer protocol at import; each layout above then splices as the
    # Python path prints it (the batch property tests).
    assert codec.ARRAY_HEAD_READ


class FreshVectorsArm:
    """An arm whose vectors are properties making a new tuple per read, of ints (so the codec
    converts each): what a batch keys by identity is freed at once unless the batch holds it."""

    def __init__(self, i: int) -> None:
        self.i = i

    @property
    def eef_pos(self) -> tuple[int, ...]:
        return (self.i, self.i + 1, self.i + 2)

    @property
    def eef_force(self) -> tuple[int, ...]:
        return (-self.i, 0, 1)


@pytest.mark.parametrize("kernel", [True, False], ids=["c", "python"])
def test_vectors_made_per_read_never_lend_their_text_to_others(kernel: bool) -> None:
    obs = np.asarray([0.5, 1.5], dtype=np.float32)
    batch = [
        (True, (0, i, "reach", 1, obs, (0.25,), 0.0, obs, False, False, False, (FreshVectorsArm(i),)))
        for i in range(50)
    ]
    payloads = codec.RecordEncoder(kernel=kernel).rows(batch)  # type: ignore[arg-type]
    for (_, row), payload in zip(batch, payloads, strict=True):
        assert payload == through_record(True, row)
        i = row[1]
        assert json.loads(payload)["key_state"] == {"arm0_eef_pos": [i, i + 1, i + 2], "arm0_eef_force": [-i, 0, 1]}
