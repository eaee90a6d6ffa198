"""export_transitions, Transitions files, episode selection and summarize (export/summary invariants)."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from _trace_helpers import make_env_step, make_metadata, one_of_each, same_floats, write_records, write_trace
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from capevo.errors import Corrupt, ErrorCode, Invalid
from capevo.runtime.traces import (
    EnvStep,
    EpisodeSummary,
    Intervention,
    TraceWriter,
    Transitions,
    export_transitions,
    parse_episodes,
    summarize,
)
from capevo.runtime.traces.export import format_vector


def episode(ep: int, n: int, *, ecm: str = "reach", obs_dim: int = 5) -> list[EnvStep]:
    steps = [make_env_step(ep, i, obs_dim=obs_dim, ecm=ecm) for i in range(n)]
    steps[-1] = make_env_step(ep, n - 1, obs_dim=obs_dim, ecm=ecm, truncated=True, is_success=ep % 2 == 0)
    return steps


def test_arrays_shapes_and_dtypes(tmp_path: Path) -> None:
    # Export invariants 1 and 2.
    steps = episode(0, 4) + episode(1, 3, ecm="grasp")
    t = export_transitions(write_trace(tmp_path / "run.mcap", steps))
    assert len(t) == 7
    assert t.obs.shape == t.next_obs.shape == (7, 5) and t.action.shape == (7, 7)
    assert t.obs.dtype == t.action.dtype == t.next_obs.dtype == t.reward.dtype == np.float32
    assert t.done.dtype == t.terminated.dtype == t.truncated.dtype == t.is_success.dtype == np.bool_
    assert t.version.dtype == t.episode.dtype == t.step.dtype == np.int64
    assert t.ecm.dtype.kind == t.run_id.dtype.kind == "U"
    for i, s in enumerate(steps):
        assert t.obs[i].tolist() == list(s.obs) and t.next_obs[i].tolist() == list(s.next_obs)
        assert t.action[i].tolist() == list(s.action)
        assert t.reward[i] == np.float32(s.reward)
        assert t.done[i] == s.done and t.ecm[i] == s.ecm
        assert (t.episode[i], t.step[i], t.version[i]) == (s.episode, s.step, s.version)
    assert t.run_id.tolist() == ["run-1"] * 7
    assert t.done.tolist() == [False, False, False, True, False, False, True]
    with pytest.raises(ValueError):
        t.obs[0, 0] = 1.0  # read-only


def test_filters_and_several_files(tmp_path: Path) -> None:
    a = write_trace(tmp_path / "a.mcap", episode(0, 2) + episode(1, 2, ecm="grasp") + episode(2, 2))
    with TraceWriter(tmp_path / "b.mcap", make_metadata("run-2")) as w:
        write_records(w, episode(0, 3))
    t = export_transitions([a, tmp_path / "b.mcap"], episodes=parse_episodes("0,2"))
    assert list(zip(t.run_id.tolist(), t.episode.tolist(), strict=True)) == [
        ("run-1", 0),
        ("run-1", 0),
        ("run-1", 2),
        ("run-1", 2),
        ("run-2", 0),
        ("run-2", 0),
        ("run-2", 0),
    ]
    assert export_transitions(a, ecms={"grasp"}).episode.tolist() == [1, 1]
    empty = export_transitions(a, episodes={99})
    assert len(empty) == 0 and empty.obs.shape == (0, 0)


def test_mixed_dimensions_are_invalid(tmp_path: Path) -> None:
    # Export invariant 4.
    path = write_trace(tmp_path / "run.mcap", episode(0, 2, obs_dim=5) + episode(1, 2, obs_dim=6))
    with pytest.raises(Invalid) as exc:
        export_transitions(path)
    assert exc.value.code is ErrorCode.INVALID
    assert exc.value.message.startswith("obs of run run-1 episode 1 step 0 has 6 values, earlier steps have 5")
    assert len(export_transitions(path, episodes={1})) == 2


def test_npz_and_jsonl_files(tmp_path: Path) -> None:
    # Export invariant 3; jsonl is strict JSON with the same keys.
    t = export_transitions(write_trace(tmp_path / "run.mcap", episode(0, 3)))
    npz = t.save_npz(tmp_path / "out" / "t.npz")
    assert Transitions.load_npz(npz).equals(t)
    with np.load(npz, allow_pickle=False) as data:
        assert sorted(data.files) == sorted(Transitions.ARRAYS)
    lines = t.save_jsonl(tmp_path / "t.jsonl").read_text().splitlines()
    assert len(lines) == 3
    rows = [json.loads(line, parse_constant=lambda c: pytest.fail(c)) for line in lines]
    assert set(rows[0]) == set(Transitions.ARRAYS)
    assert rows[2]["done"] is True and rows[0]["obs"] == pytest.approx(t.obs[0].tolist())
    assert np.asarray(rows[1]["action"], dtype=np.float32).tolist() == t.action[1].tolist()


def test_load_npz_errors(tmp_path: Path) -> None:
    np.savez(tmp_path / "other.npz", obs=np.zeros((1, 1)))
    with pytest.raises(Corrupt) as exc:
        Transitions.load_npz(tmp_path / "other.npz")
    assert exc.value.code is ErrorCode.CORRUPT and "missing arrays" in exc.value.message
    with pytest.raises(Invalid):
        Transitions.load_npz(tmp_path / "nope.npz")


def test_transitions_validate_lengths() -> None:
    t = Transitions.from_steps([])
    arrays = t.arrays()
    arrays["reward"] = np.zeros(3, dtype=np.float32)
    with pytest.raises(Invalid) as exc:
        Transitions(**arrays)
    assert "must be a rank-2 array with 3 rows" in exc.value.message


def test_unfinished_file_needs_allow_incomplete(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    w = TraceWriter(path, make_metadata(), background_flush=False)
    try:
        write_records(w, episode(0, 2))
        w.flush()
        with pytest.raises(Corrupt) as exc:
            export_transitions(path)
        assert "unfinished" in exc.value.message
        assert len(export_transitions(path, allow_incomplete=True)) == 2
    finally:
        w.close()


f32s = st.floats(width=32, allow_nan=False, allow_infinity=False)


ECM_NAME_CHARS = st.characters(exclude_categories=("Cs",), exclude_characters="\x00")


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    dims=st.tuples(st.integers(0, 12), st.integers(0, 8)),
    data=st.data(),
)
def test_export_of_arbitrary_steps_round_trips(dims: tuple[int, int], data: st.DataObject) -> None:
    obs_dim, act_dim = dims
    vec = lambda n: st.lists(f32s, min_size=n, max_size=n).map(tuple)  # noqa: E731
    steps = [
        EnvStep(
            episode=data.draw(st.integers(0, 3)),
            step=i,
            # numpy <U strips NUL; a lone surrogate is not UTF-8.
            ecm=data.draw(st.text(ECM_NAME_CHARS, max_size=10)),
            version=data.draw(st.integers(0, 2**40)),
            obs=data.draw(vec(obs_dim)),
            action=data.draw(vec(act_dim)),
            reward=data.draw(st.floats(allow_nan=False, allow_infinity=False, width=32)),
            next_obs=data.draw(vec(obs_dim)),
            terminated=data.draw(st.booleans()),
            truncated=data.draw(st.booleans()),
        )
        for i in range(data.draw(st.integers(0, 6)))
    ]
    with tempfile.TemporaryDirectory() as tmp:
        path = write_trace(Path(tmp) / "run.mcap", steps)
        t = export_transitions(path)
        assert len(t) == len(steps)
        for i, s in enumerate(steps):
            assert t.obs[i].tolist() == list(s.obs) and t.action[i].tolist() == list(s.action)
            assert t.next_obs[i].tolist() == list(s.next_obs)
            assert t.reward[i] == np.float32(s.reward)
            assert t.ecm[i] == s.ecm and t.version[i] == s.version and t.done[i] == s.done
        t.save_npz(Path(tmp) / "t.npz")
        assert Transitions.load_npz(Path(tmp) / "t.npz").equals(t)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 50)), min_size=1, max_size=6))
def test_episode_selection_parses_what_it_prints(ranges: list[tuple[int, int]]) -> None:
    # Export invariant 5.
    spec = ",".join(f"{lo}-{lo + w}" if w else str(lo) for lo, w in ranges)
    sel = parse_episodes(spec)
    assert parse_episodes(str(sel)) == sel
    for lo, w in ranges:
        assert lo in sel and lo + w in sel
    members = {e for lo, w in ranges for e in range(lo, lo + w + 1)}
    for probe in (0, 1, 7, 999_999, 10**6 + 60):
        assert (probe in sel) == (probe in members)


@pytest.mark.parametrize("spec", ["all", "", " ALL ", "*"])
def test_episode_selection_all(spec: str) -> None:
    sel = parse_episodes(spec)
    assert sel.ranges is None and 0 in sel and 10**9 in sel and str(sel) == "all"


@pytest.mark.parametrize("spec", ["x", "1,,2", "3-1", "-1", "1-", "1.5", "²", "9" * 30])
def test_episode_selection_errors(spec: str) -> None:
    with pytest.raises(Invalid) as exc:
        parse_episodes(spec)
    assert exc.value.code is ErrorCode.INVALID
    assert exc.value.message.startswith(f"bad episode selection {spec!r}")


# -- summarize ------------------------------------------------------------------------------


def test_summary_of_finished_and_unfinished_episodes(tmp_path: Path) -> None:
    # Summary invariants 1-3: ep 0 has a summary record; ep 1 died mid-episode.
    path = tmp_path / "run.mcap"
    w = TraceWriter(path, make_metadata(), background_flush=False)
    try:
        write_records(w, one_of_each(0))
        ep1 = [make_env_step(1, i, reward=0.5) for i in range(4)]
        write_records(w, ep1)
        write_records(w, [Intervention(episode=1, step=2, constraint="c", original_action=(1.0,), result_action=None)])
        w.flush()
        s = summarize(path)
    finally:
        w.close()
    assert not s.complete
    assert [e.episode for e in s.episodes] == [0, 1]
    done, running = s.episodes
    summary = next(r for r in one_of_each(0) if isinstance(r, EpisodeSummary))
    assert done.finished and done.success is True and done.total_reward == summary.total_reward
    assert (done.steps, done.interventions, done.seed) == (summary.steps, summary.interventions, summary.seed)
    assert not running.finished and running.success is None
    assert running.total_reward == 2.0 and running.steps == 4 and running.interventions == 1
    assert s.success_rate == 1.0
    d = s.to_dict()
    assert d["run_id"] == "run-1" and d["complete"] is False and d["topic_counts"]["/env/step"] == 5
    assert summarize(path).complete is True  # closed now


def test_strict_summary_refuses_an_unfinished_file(tmp_path: Path) -> None:
    path = tmp_path / "open.mcap"
    w = TraceWriter(path, make_metadata(), background_flush=False)
    try:
        with pytest.raises(Corrupt) as exc:
            summarize(path, allow_incomplete=False)
        assert exc.value.code is ErrorCode.CORRUPT and "unfinished" in exc.value.message
    finally:
        w.close()


def test_summary_json_has_no_nan(tmp_path: Path) -> None:
    bad = EpisodeSummary(
        episode=0,
        seed=None,
        success=False,
        total_reward=math.nan,
        steps=0,
        interventions=0,
        unsafe_steps=0,
        capability_set={},
        duration_s=math.inf,
    )
    path = write_trace(tmp_path / "run.mcap", [bad])
    text = json.dumps(summarize(path).to_dict(), allow_nan=False)
    assert '"total_reward": null' in text


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(width=32), max_size=40))
def test_format_vector_names_each_float32_uniquely(values: list[float]) -> None:
    parsed = json.loads(f"[{format_vector(values)}]", parse_constant=lambda c: pytest.fail(c))
    expected = [v if math.isfinite(v) else float("nan") for v in values]
    got = [float("nan") if v is None else float(np.float32(v)) for v in parsed]
    assert same_floats(got, expected)
