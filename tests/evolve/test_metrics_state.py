"""Config presets, durable metrics files, the run manifest and the journal.

Invariants: config 1-4, metrics 1-4, state 1-3.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from capevo.errors import Corrupt, ErrorCode, IdentityViolation, Invalid
from capevo.evolve.config import EvolveConfig, config_names, make_config
from capevo.evolve.metrics import (
    CSV_COLUMNS,
    GateSummary,
    IterationMetrics,
    MetricsLog,
    outcome_stats,
    read_metrics,
)
from capevo.evolve.state import Journal, RunManifest, load_manifest, save_manifest
from capevo.runtime.evaluation import EpisodeOutcome

# --- config ------------------------------------------------------------------------------


def test_presets_are_valid_and_round_trip() -> None:
    assert config_names() == ("tiny", "cpu-small", "paper")
    for name in config_names():
        cfg = make_config(name)
        assert cfg.preset == name
        assert EvolveConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
        assert cfg.gate_episodes >= cfg.gate.min_n
    tiny = make_config("tiny")
    assert (tiny.iterations, tiny.live_episodes, tiny.horizon) == (2, 3, 40) and 3 <= tiny.gate_episodes <= 4
    assert make_config("cpu-small", iterations=5).iterations == 5


def test_unknown_preset_lists_the_valid_ones() -> None:
    with pytest.raises(Invalid) as info:
        make_config("huge")
    assert info.value.code is ErrorCode.INVALID
    assert info.value.message == "unknown preset 'huge'; valid: tiny, cpu-small, paper"


def test_a_gate_that_could_never_promote_is_refused() -> None:
    with pytest.raises(Invalid) as info:
        make_config("cpu-small", gate_episodes=3)
    assert "below the gate's min_n (8)" in info.value.message


def test_the_gate_extension_option_reaches_the_gate_and_a_resume_notices_it() -> None:
    from capevo.evolve.run import EvolveOptions

    base = EvolveOptions(task="T1", preset="cpu-small").resolved_config()
    extended = EvolveOptions(task="T1", preset="cpu-small", gate_extension=20, iterations=12).resolved_config()
    assert base.gate.extend_n == 0 and extended.gate.extend_n == 20 and extended.iterations == 12
    assert extended.gate_seeds_max == 30 and extended.gate == dataclasses.replace(base.gate, extend_n=20)
    assert base.resume_mismatches(extended) == ["gate"]
    assert type(extended).from_dict(extended.to_dict()) == extended


def test_tie_siblings_reaches_the_cem_settings_a_resume_notices_it_and_must_be_a_bool() -> None:
    from capevo.evolve.config import CemSettings
    from capevo.evolve.run import EvolveOptions

    base = EvolveOptions(task="T5", preset="cpu-small").resolved_config()
    tied = EvolveOptions(task="T5", preset="cpu-small", tie_siblings=True).resolved_config()
    assert not base.cem.tie_siblings and tied.cem == dataclasses.replace(base.cem, tie_siblings=True)
    assert base.resume_mismatches(tied) == ["cem"]
    assert EvolveConfig.from_dict(json.loads(json.dumps(tied.to_dict()))) == tied
    # a manifest written before the setting existed reads back untied
    old = base.to_dict()
    del old["cem"]["tie_siblings"]
    assert EvolveConfig.from_dict(old) == base
    with pytest.raises(Invalid) as info:
        CemSettings(tie_siblings="yes")  # type: ignore[arg-type]
    assert info.value.details["field"] == "cem.tie_siblings"


def test_resume_mismatches_ignore_iterations_only() -> None:
    a = make_config("tiny")
    assert a.resume_mismatches(a.replace(iterations=9)) == []
    assert a.resume_mismatches(a.replace(live_episodes=5, horizon=50)) == ["horizon", "live_episodes"]


# --- metrics -----------------------------------------------------------------------------


def _outcome(seed: int, success: bool, reward: float) -> EpisodeOutcome:
    return EpisodeOutcome(
        seed=seed,
        success=success,
        reward=reward,
        steps=10,
        duration_s=0.1,
        interventions=1,
        unsafe_steps=0,
        ecm_failures=0,
        capability_set={"pick.reach": 0},
    )


def test_outcome_stats() -> None:
    empty = outcome_stats([])
    assert (empty.episodes, empty.success_low, empty.reward_low) == (0, None, None)
    s = outcome_stats([_outcome(1, True, 2.0), _outcome(2, False, 4.0), _outcome(3, False, 6.0)])
    assert (s.episodes, s.successes, s.interventions) == (3, 1, 3)
    assert s.success_rate == pytest.approx(1 / 3) and s.reward_mean == pytest.approx(4.0)
    assert s.reward_var == pytest.approx(4.0)  # sample variance of 2, 4, 6
    assert s.success_low is not None and s.success_high is not None
    assert 0 < s.success_low < 1 / 3 < s.success_high < 1
    # 95% t interval: mean ± t(0.975, 2) * sd / sqrt(3)
    assert s.reward_high - s.reward_mean == pytest.approx(4.302652729749464 * 2 / 3**0.5)


def _row(i: int) -> IterationMetrics:
    outcomes = [_outcome(100 + i, i % 2 == 0, float(i))]
    return IterationMetrics(
        iteration=i,
        started_at=1000.0 + i,
        live=outcome_stats(outcomes),
        live_seeds=(100 + i,),
        episodes=tuple(o.to_dict() for o in outcomes),
        delta_pi=0.0,
        identity_hash="ab" * 32,
        active_versions={"pick.reach": 0},
        active_after={"pick.reach": i},
        gate=GateSummary(
            ecm="pick.reach",
            candidate_version=i,
            active_version=0,
            decision="reject",
            mode="paired",
            n=4,
            candidate_successes=0,
            candidate_rate=0.0,
            candidate_low=0.0,
            candidate_high=0.4,
            p_success=1.0,
        ),
        wall_s=1.5,
    )


def test_metrics_log_appends_and_reads_back(tmp_path: Path) -> None:
    log = MetricsLog(tmp_path)
    for i in range(3):
        log.append(_row(i))
    assert read_metrics(tmp_path) == [_row(i) for i in range(3)]
    lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert lines[0].split(",") == list(CSV_COLUMNS) and len(lines) == 4
    assert MetricsLog(tmp_path).completed == 3
    with pytest.raises(Invalid) as info:
        log.append(_row(5))
    assert info.value.message == "metrics row for iteration 5, expected 3"


def test_a_torn_row_is_dropped_and_the_csv_rebuilt(tmp_path: Path) -> None:
    log = MetricsLog(tmp_path)
    log.append(_row(0))
    with open(tmp_path / "metrics.jsonl", "ab") as f:
        f.write(b'{"iteration": 1, "torn')  # a write that never completed
    (tmp_path / "metrics.csv").write_text("garbage\n")
    again = MetricsLog(tmp_path)
    assert again.completed == 1
    assert (tmp_path / "metrics.jsonl").read_bytes().endswith(b"\n")
    assert len((tmp_path / "metrics.csv").read_text().splitlines()) == 2  # header + row 0
    again.append(_row(1))
    assert [r.iteration for r in read_metrics(tmp_path)] == [0, 1]


def test_rows_out_of_order_are_corrupt(tmp_path: Path) -> None:
    (tmp_path / "metrics.jsonl").write_text(json.dumps(_row(1).to_dict()) + "\n")
    with pytest.raises(Corrupt) as info:
        MetricsLog(tmp_path)
    assert info.value.code is ErrorCode.CORRUPT and "is iteration 1, expected 0" in info.value.message


_CHILD = """
import sys, time
sys.path.insert(0, sys.argv[2])
from test_metrics_state import _row
from capevo.evolve.metrics import MetricsLog
log = MetricsLog(sys.argv[1])
i = log.completed
while True:
    log.append(_row(i))
    print(i, flush=True)
    i += 1
"""


def test_acknowledged_rows_survive_sigkill(tmp_path: Path) -> None:
    here = str(Path(__file__).parent)
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(tmp_path), here], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    acked = -1
    deadline = time.monotonic() + 60
    while acked < 5 and time.monotonic() < deadline:
        acked = int(proc.stdout.readline())
    proc.kill()
    proc.wait()
    proc.stdout.close()
    rows = MetricsLog(tmp_path).rows
    assert len(rows) >= acked + 1
    assert list(rows[: acked + 1]) == [_row(i) for i in range(acked + 1)]
    csv_rows = (tmp_path / "metrics.csv").read_text().splitlines()[1:]
    assert len(csv_rows) == len(rows)


# --- manifest and journal -----------------------------------------------------------------


def _manifest(**changes: object) -> RunManifest:
    base = {
        "task": "pick",
        "modality": "code",
        "seed": 0,
        "perturbations": True,
        "config": make_config("tiny"),
        "identity_hash": "aa" * 32,
        "mode": "embedded",
        "registry": "/r",
        "learner": "local",
        "created_at": 1.0,
    }
    base.update(changes)
    return RunManifest(**base)  # type: ignore[arg-type]


def test_manifest_round_trip_and_resume_checks(tmp_path: Path) -> None:
    m = _manifest()
    save_manifest(tmp_path, m)
    assert load_manifest(tmp_path) == m
    m.check_resume(_manifest(created_at=5.0, config=make_config("tiny", iterations=7)))
    with pytest.raises(IdentityViolation) as info:
        m.check_resume(_manifest(identity_hash="bb" * 32))
    assert info.value.code is ErrorCode.IDENTITY_VIOLATION
    assert info.value.message.startswith("the agent's identity changed since this run started")
    with pytest.raises(Invalid) as info2:
        m.check_resume(_manifest(modality="rl", config=make_config("tiny", live_episodes=5)))
    assert info2.value.details["differ"] == ["modality", "config.live_episodes"]
    assert "'code' -> 'rl'" in info2.value.message


def test_journal_attempts_and_torn_tail(tmp_path: Path) -> None:
    j = Journal(tmp_path)
    j.write("start", 0, capability_set={"a": 0})
    j.write("candidate", 0, ecm="a", version=1)
    j.write("decided", 0, ecm="a", version=1)
    j.write("start", 1, capability_set={"a": 1})
    with open(tmp_path / "journal.jsonl", "ab") as f:
        f.write(b'{"event": "candid')
    j2 = Journal(tmp_path)
    assert [e["event"] for e in j2.attempt(0)] == ["start", "candidate", "decided"]
    assert [e["event"] for e in j2.attempt(1)] == ["start"]
    assert j2.last(1, "candidate") is None and j2.last(0, "candidate")["version"] == 1  # type: ignore[index]
    j2.write("candidate", 1, ecm="a", version=2)
    assert Journal(tmp_path).last(1, "candidate")["version"] == 2  # type: ignore[index]
