"""The trace, worker, governance (live and rates) and resolve benchmarks still run against the code (tiny budgets).

No timing is judged.

A benchmark drives the runtime through its public seams (sinks, writers, the episode loop); when
one of those changes, the script is the first thing to break, and nobody runs it until a figure
is wanted. These runs only check that each completes and reports what it measured.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import _common  # noqa: E402
import bench_governance_live  # noqa: E402
import bench_governance_rates  # noqa: E402
import bench_resolve_clients  # noqa: E402
import bench_sac_throughput  # noqa: E402
import bench_traces_loop  # noqa: E402
import bench_worker  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(autouse=True)
def results_in(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)
    logging.getLogger("robosuite").setLevel(logging.ERROR)
    return tmp_path


def test_trace_loop_benchmark_measures_the_writer_in_a_real_episode(results_in: Path) -> None:
    result = bench_traces_loop.measure("T1", 2)
    runs = result["runs"]
    assert set(runs) == {"none", "noop", "writer"}
    # the same seeds, so the same episodes under every sink
    assert (
        [r["steps"] for r in runs["none"]] == [r["steps"] for r in runs["noop"]] == [r["steps"] for r in runs["writer"]]
    )
    assert result["steps"] > 0 and result["bytes_per_step"] > 100  # a file with every step in it
    assert all(r["write_ns"] > 0 for r in runs["writer"]) and all(r["write_ns"] == 0 for r in runs["none"])
    assert result["writer_pct_of_episode"] > 0 and all(ms > 0 for ms in result["wall_ms_per_step"].values())


def test_worker_benchmark_runs_its_variants_and_breakdown(results_in: Path) -> None:
    assert bench_worker.main(["--rounds", "1", "--seeds", "1", "--horizon", "12", "--out", "smoke"]) == 0
    saved = json.loads((results_in / "smoke.json").read_text())
    assert saved["benchmark"] == "smoke"
    text = json.dumps(saved, ensure_ascii=False)
    assert "trace writes" in text and "governance R(a, Φ)" in text


def test_governance_live_benchmark_times_every_action_of_a_real_episode(results_in: Path) -> None:
    row = bench_governance_live.measure("T6", "per-task", 1, 2, 12)
    assert row["actions"] == 12 and row["in_process"]["samples"] == 24  # each action timed twice
    assert row["in_process"]["p50_ms"] > 0 and row["env_step_p50_ms"] > 0 and row["pct_of_env_step"] > 0
    assert sum(row["share"].values()) == pytest.approx(1.0)


def test_governance_rates_benchmark_runs_adversaries_off_and_on_and_resumes(
    results_in: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["--tasks", "T6", "--episodes", "5", "--horizon", "4", "--jobs", "1", "--phi", "task"]
    argv += ["--adversaries", "arm_grab", "oscillate", "--out", "smoke"]
    assert bench_governance_rates.main(argv) == 0
    saved = json.loads((results_in / "smoke.json").read_text())
    assert {(j["adversary"], j["governance"]) for j in saved["results"]} == {
        (a, m) for a in ("arm_grab", "oscillate") for m in ("off", "on")
    }
    assert [e["seed"] for j in saved["results"] if j["adversary"] == "arm_grab" for e in j["episodes"]] == [3, 3]
    rows = {(r["adversary"], r["phi"]): r for r in saved["summary"]}
    assert rows[("all", "task")]["on"]["episodes"] == 2 and rows[("oscillate", "task")]["on"]["steps"] == 4
    assert rows[("oscillate", "task")]["off"]["unsafe_steps_by_axis"]["cap"] > 0
    assert "cap" not in rows[("oscillate", "task")]["on"]["unsafe_steps_by_axis"]
    assert len(list((results_in / "smoke.jobs").iterdir())) == 4
    capsys.readouterr()
    assert bench_governance_rates.main(argv) == 0  # every job's file is there: nothing reruns
    assert capsys.readouterr().err.count("(cached)") == 4


@pytest.mark.zenoh
def test_resolve_clients_benchmark_runs_raw_and_capevo_over_real_zenoh(results_in: Path) -> None:
    argv = ["--clients", "2", "--seconds", "0.3", "--warmup", "5", "--rounds", "1", "--publish-seconds", "0.3"]
    assert bench_resolve_clients.main([*argv, "--out", "smoke"]) == 0
    saved = json.loads((results_in / "smoke.json").read_text())
    (row,) = saved["by_clients"]
    assert row["clients"] == 2 and set(row["rounds"]) == {"raw", "capevo"}
    assert all(row[kind]["throughput_per_s"] > 0 and row[kind]["p50_ms"] > 0 for kind in ("raw", "capevo"))
    assert saved["server_exit_code"] == 0 and saved["reply_bytes"] > 100
    # reads alone and during 64 MiB sends (at least one each: raw to the sink, capevo publishes in parts)
    for during in saved["during_64mib_sends"].values():
        assert during["sends"] >= 1 and len(during["send_s"]) == during["sends"]
        assert during["quiet"]["n"] > 0 and during["during_64mib_sends"]["n"] > 0


def test_sac_throughput_benchmark_measures_each_part_and_estimates_the_paper_budget(results_in: Path) -> None:
    result = bench_sac_throughput.main(["--steps", "20"])
    assert set(result["rates_per_s"]) == {"sim", "grad", "sac_1env", "sac_2env"}
    assert all(r > 0 for r in result["rates_per_s"].values())
    assert all(h > 0 for h in result["estimates_hours"].values())  # no timing is judged, only that it ran
    assert json.loads((results_in / "sac_throughput.json").read_text())["steps"] == 20


def test_dagger_diagnosis_composes_clones_and_records_the_learners_env_steps(results_in: Path) -> None:
    import diag_bc_dagger

    assert diag_bc_dagger.main(["--preset", "tiny", "--rounds", "1", "--episodes", "1", "--eval-episodes", "2"]) == 0
    (row,) = json.loads((results_in / "bc_dagger.json").read_text())
    assert list(row["ecms"]) == ["pick.reach", "pick.grasp", "pick.lift"]
    assert all(len(e["dagger"]["rounds"]) == 1 for e in row["ecms"].values())
    spent = sum(e["demos"]["new_samples"] + e["dagger"]["env_steps"] for e in row["ecms"].values())
    assert row["learner_env_steps"] == spent > 0
    assert row["seeds"] == "600000-600001" and len(row["success"]) == len(row["unsafe"]) == 2


def test_sac_warm_start_diagnosis_clones_then_trains_and_records_each_stage(results_in: Path) -> None:
    import diag_sac_warm_start

    args = ["--name", "smoke", "--preset", "tiny", "--steps", "120", "--eval-episodes", "1"]
    remedies = ["--potential", "--bc-weight", "1", "--explore-std", "0.2", "--critic-warmup", "40"]
    assert diag_sac_warm_start.main([*args, *remedies]) == 0
    (row,) = json.loads((results_in / "sac_warm_start.json").read_text())
    assert row["name"] == "smoke" and row["demo_steps"] > 0
    assert row["bc_loss"][1] < row["bc_loss"][0]  # cloning fitted the demonstrations
    for stage in ("after_bc", "after_critic_warmup", "after_sac"):
        assert row[stage]["episodes"] == 1 and 0 <= row[stage]["successes"] <= 1
    assert row["settings"]["critic_warmup"] == 40


def test_sac_warm_start_diagnosis_trains_a_residual_over_the_clone(results_in: Path) -> None:
    import diag_sac_warm_start

    args = ["--name", "residual", "--preset", "tiny", "--steps", "120", "--eval-episodes", "1", "--residual"]
    assert diag_sac_warm_start.main([*args, "--potential", "--critic-warmup", "40"]) == 0
    (row,) = json.loads((results_in / "sac_warm_start.json").read_text())
    for stage in ("after_bc", "residual_start", "after_critic_warmup", "after_sac"):
        assert row[stage]["episodes"] == 1
    assert row["head_norm"]["clone"] > 0 and row["head_norm"]["residual"] > 0  # SAC moved the residual


def test_sac_warm_start_diagnosis_runs_awac_s_actor_update(results_in: Path) -> None:
    import diag_sac_warm_start

    args = ["--name", "awac", "--preset", "tiny", "--steps", "120", "--eval-episodes", "1", "--awac", "1.0"]
    assert diag_sac_warm_start.main([*args, "--explore-std", "0.05", "--learning-starts", "0"]) == 0
    (row,) = json.loads((results_in / "sac_warm_start.json").read_text())
    assert row["settings"]["awac"] == 1.0 and row["after_sac"]["episodes"] == 1
    assert row["actor_change"] > 0  # AWAC's own step moved the actor (SAC's is switched off)
    with pytest.raises(SystemExit):
        diag_sac_warm_start.main([*args, "--bc-weight", "1"])  # two actor updates at once


def test_the_residual_actor_starts_as_the_clone_and_trains_only_its_residual() -> None:
    import dataclasses

    import diag_sac_warm_start
    import numpy as np
    import torch
    from gymnasium import spaces

    from capevo.learner.neural_seed import SpacesEnv, new_sac
    from capevo.learner.presets import make_preset

    env = SpacesEnv(spaces.Box(-np.inf, np.inf, (9,), np.float32), spaces.Box(-1.0, 1.0, (4,), np.float32))
    sac = dataclasses.replace(make_preset("tiny").sac, net_arch=(16, 16))
    clone = new_sac(env, net_arch=sac.net_arch, seed=3, **sac.sac_kwargs())
    wide = diag_sac_warm_start.residual_over(clone, env, sac, 0.2)
    obs = torch.as_tensor(np.random.default_rng(0).normal(size=(64, 9)), dtype=torch.float32)
    with torch.no_grad():
        assert torch.allclose(wide.actor(obs, deterministic=True), clone.actor(obs, deterministic=True), atol=1e-6)
    before = {k: v.clone() for k, v in wide.actor.state_dict().items()}
    for _ in range(5):  # any loss: only the residual's entries may move
        wide.actor.optimizer.zero_grad()
        (wide.actor(obs, deterministic=True) - 0.5).pow(2).mean().backward()
        wide.actor.optimizer.step()
    after = wide.actor.state_dict()
    first, second = "latent_pi.0.weight", "latent_pi.2.weight"
    assert torch.equal(after[first][:16], before[first][:16]) and not torch.equal(after[first][16:], before[first][16:])
    assert torch.equal(after[second][:16], before[second][:16])  # the clone's block and a cross block
    assert torch.equal(after[second][16:, :16], torch.zeros(16, 16))  # the other cross block stays 0
    assert torch.equal(after["mu.weight"][:, :16], before["mu.weight"][:, :16])
    assert torch.equal(after["mu.bias"], before["mu.bias"])
    assert not torch.equal(after["mu.weight"][:, 16:], before["mu.weight"][:, 16:])


def test_a_benchmark_scratch_dir_is_gone_when_its_process_exits(tmp_path: Path) -> None:
    import subprocess

    code = f"import sys; sys.path.insert(0, {str(BENCHMARKS)!r}); import _common; p = _common.scratch_dir('b-'); "
    code += "(p / 'f').write_text('x'); print(p)"
    out = subprocess.run(
        [sys.executable, "-c", code], env={"TMPDIR": str(tmp_path)}, capture_output=True, text=True, check=True
    )
    made = Path(out.stdout.strip())
    assert made.parent == tmp_path and made.name.startswith("b-")
    assert not made.exists() and list(tmp_path.iterdir()) == []


def test_the_constant_adversaries_benchmark_counts_every_push_under_both_envelopes(results_in: Path) -> None:
    import bench_constant_adversaries

    assert bench_constant_adversaries.main(["--seeds", "1", "--steps", "3", "--without", "stopping_distance"]) == 0
    rows = json.loads((results_in / "constant_adversaries.json").read_text())["rows"]
    assert set(rows) == set(bench_constant_adversaries.PUSHES)
    for per in rows.values():
        assert set(per) == {"without stopping_distance", "default Φ"} and all(len(c) == 1 for c in per.values())


def test_the_closing_speeds_benchmark_times_both_sides_and_the_rule(results_in: Path) -> None:
    import bench_closing_speeds

    assert bench_closing_speeds.main(["--steps", "2", "--reps", "2"]) == 0
    out = json.loads((results_in / "closing_speeds.json").read_text())
    assert out["near_us_p50_with_closing"] > 0 and out["near_us_p50_without_closing"] > 0
    assert out["stopping_distance_check_us_p50"] > 0 and out["pairs_per_step"] >= 0
