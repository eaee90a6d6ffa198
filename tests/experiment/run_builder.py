"""Build experiment run directories on disk for the report and verify tests: real files, written
with the real ``IterationRecord.to_dict`` and ``CellSpec.to_dict``, in the harness's layout."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capevo.baselines.base import Budget, CellSpec, EpisodeResult, IterationRecord

BUDGET = Budget(env_steps_per_iteration=1000, eval_episodes=10)


@dataclass(frozen=True)
class Raw:
    """What a test generated for one cell, kept apart from the records so expectations are
    computed from these lists, not through the code under test."""

    successes: list[list[bool]]  # per iteration, per episode
    rewards: list[list[float]]
    steps: list[list[int]]
    unsafe: list[list[int]]
    interventions: list[list[int]]
    train: list[int]
    delta_pi: list[float]


def gen_raw(seed: int, *, iterations: int, episodes: int, p_success: Sequence[float], reward_scale: float = 1.0,
            train: int = 1000, drift: float = 0.0, p_unsafe: float = 0.0, p_block: float = 0.0) -> Raw:  # fmt: skip
    rng = np.random.default_rng(seed)
    succ, rew, steps, unsafe, inter = [], [], [], [], []
    for i in range(iterations):
        s = (rng.random(episodes) < p_success[i]).tolist()
        succ.append([bool(x) for x in s])
        rew.append([float(round(x, 6)) for x in rng.normal(reward_scale * (1 + i), 0.5, episodes)])
        st = rng.integers(50, 100, episodes).tolist()
        steps.append([int(x) for x in st])
        unsafe.append([int(rng.integers(1, 4)) if rng.random() < p_unsafe else 0 for _ in range(episodes)])
        inter.append([int(rng.binomial(n, p_block)) for n in st])
    return Raw(
        successes=succ,
        rewards=rew,
        steps=steps,
        unsafe=unsafe,
        interventions=inter,
        train=[train] * iterations,
        delta_pi=[drift * i for i in range(iterations)],
    )


def records_of(raw: Raw, eval_seeds: Sequence[int]) -> list[IterationRecord]:
    out = []
    for i in range(len(raw.successes)):
        eps = tuple(
            EpisodeResult(
                seed=eval_seeds[j],
                success=raw.successes[i][j],
                reward=raw.rewards[i][j],
                steps=raw.steps[i][j],
                unsafe_steps=raw.unsafe[i][j],
                interventions=raw.interventions[i][j],
            )
            for j in range(len(raw.successes[i]))
        )
        out.append(
            IterationRecord(
                iteration=i,
                episodes=eps,
                env_steps_train=raw.train[i],
                env_steps_eval=sum(raw.steps[i]),
                delta_pi=raw.delta_pi[i],
                wall_s=1.5,
            )
        )
    return out


def write_cell(root: Path, *, task: str, method: str, seed: int, raw: Raw | None, knowledge: str = "random weights",
               status: str = "done", governance: bool = True, options: Mapping[str, Any] | None = None,
               iterations: int | None = None, budget: Budget = BUDGET) -> CellSpec:  # fmt: skip
    """Write one cell directory; ``status`` is done, failed, unfinished or no-cell-json."""
    if raw is not None and len(raw.successes[0]) != budget.eval_episodes:
        budget = Budget(env_steps_per_iteration=budget.env_steps_per_iteration, eval_episodes=len(raw.successes[0]))
    spec = CellSpec(
        task=task,
        method=method,
        seed=seed,
        iterations=iterations or (len(raw.successes) if raw else 2),
        budget=budget,
        governance=governance,
        options=dict(options or {}),
    )
    d = root / "cells" / (spec.key + ("-gov-off" if not governance else ""))
    d.mkdir(parents=True)
    if status != "no-cell-json":
        (d / "cell.json").write_text(json.dumps({"cell": spec.to_dict(), "knowledge": knowledge}))
    if raw is not None:
        lines = [json.dumps(r.to_dict(), sort_keys=True) + "\n" for r in records_of(raw, spec.eval_seeds())]
        (d / "metrics.jsonl").write_text("".join(lines))
    if status == "done":
        (d / "done.json").write_text(
            json.dumps({"wall_s": 12.5, "env_steps_train": 0, "env_steps_eval": 0, "attempts": 1})
        )
    elif status == "failed":
        (d / "failed.json").write_text(json.dumps({"error": "RuntimeError: boom", "traceback": "...", "attempts": 3}))
    return spec


def write_run_files(root: Path) -> None:
    (root / "experiment.json").write_text(
        json.dumps({"preset": "test", "name": "h2", "yaml": "preset: test\nseeds: [1, 2, 3]\n"})
    )
    (root / "provenance.json").write_text(
        json.dumps(
            {
                "commit": "abc123",
                "versions": {"capevo": "0.1", "numpy": "1.26"},
                "machine": {"cores": 2},
                "wall_s": 99.0,
                "command": "capevo experiment run x.yaml",
            }
        )
    )


OURS_SEEDS = (42, 7, 123)
AM_SEEDS = (42, 7)


def build_run(root: Path) -> tuple[Path, dict[str, Raw]]:
    """T6 ours-code × 3 seeds, am × 2 seeds, T1 s-ecm × 1, T3 ablation cells, explorer on/off on T1,
    and a failed, an unfinished and an unreadable cell."""
    root.mkdir()
    write_run_files(root)
    raws: dict[str, Raw] = {}
    for i, s in enumerate(OURS_SEEDS):
        raw = gen_raw(100 + i, iterations=3, episodes=10, p_success=(0.1, 0.5, 0.9), reward_scale=3.0)
        raws[f"T6-ours-code-s{s}"] = raw
        write_cell(root, task="T6", method="ours-code", seed=s, raw=raw, knowledge="hand-written skills")
    for i, s in enumerate(AM_SEEDS):
        raw = gen_raw(200 + i, iterations=3, episodes=10, p_success=(0.0, 0.2, 0.3), drift=0.6, p_unsafe=0.3)
        raws[f"T6-am-s{s}"] = raw
        write_cell(root, task="T6", method="am", seed=s, raw=raw)
    raw = gen_raw(300, iterations=3, episodes=10, p_success=(0.0, 0.0, 0.0), train=0)
    raws["T1-s-ecm-s42"] = raw
    write_cell(root, task="T1", method="s-ecm", seed=42, raw=raw, knowledge="v0 ECMs")
    raw = gen_raw(301, iterations=3, episodes=10, p_success=(0.0, 0.0, 0.1))
    raws["T3-ours-code-s42"] = raw
    write_cell(root, task="T3", method="ours-code", seed=42, raw=raw, options={"modality": "rl"})
    # over budget in its second iteration
    raw = gen_raw(302, iterations=2, episodes=10, p_success=(0.0, 0.1))
    raw.train[1] = BUDGET.env_steps_per_iteration + 1
    raws["T3-am-s42"] = raw
    write_cell(root, task="T3", method="am", seed=42, raw=raw)
    for on in (True, False):
        raw = gen_raw(400 + on, iterations=1, episodes=20, p_success=(0.0,), train=0, p_unsafe=0.0 if on else 0.6,
                      p_block=0.4 if on else 0.0)  # fmt: skip
        raws[f"T1-explorer-{'on' if on else 'off'}"] = raw
        write_cell(root, task="T1", method="explorer", seed=1, raw=raw, governance=on, knowledge="scripted")
    write_cell(root, task="T1", method="spirl", seed=42, raw=gen_raw(5, iterations=1, episodes=10, p_success=(1.0,)),
               status="failed", iterations=2)  # fmt: skip
    write_cell(root, task="T1", method="skimo", seed=42, raw=gen_raw(6, iterations=1, episodes=10, p_success=(1.0,)),
               status="unfinished", iterations=2)  # fmt: skip
    write_cell(root, task="T1", method="am-bc", seed=42, raw=None, status="no-cell-json")
    return root, raws
