"""Trace cost per env step where it is paid: inside the real episode loop, between robosuite steps.

``bench_traces.py`` times the writer in tight loops (warm caches) and after a synthetic cache
sweep. This runs a task's v0 skills (the untuned code ECMs every evolution starts from)
through the real episode loop (``TaskEnv``, ``LoadedCapabilitySet``, ``DecompositionPolicy``,
an enforcing paper-Φ governor, perturbations on) with a real ``TraceWriter`` on every
channel, and clocks every ``write_*`` call with the calling thread's CPU clock. Each seed runs
once per batch size, back to back, the order alternating by seed, so a slow phase of a shared
machine hits both alike. ``% of env step`` divides by the CPU time of the same episodes'
``TaskEnv.step`` calls. The writer's background flush thread is not in the figures; in a busy
loop it finds nothing to do (every write checks the flush interval itself).

    .venv/bin/python benchmarks/bench_traces_loop.py [--task T1] [--seeds 6] [--batches 1 64]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results

from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy
from capevo.learner.skills import seed_registry
from capevo.registry.local import LocalRegistry
from capevo.registry.records import CapabilitySet
from capevo.runtime.capabilities import LoadedCapabilitySet
from capevo.runtime.episode import make_governor, run_episode
from capevo.runtime.governance import Phi
from capevo.runtime.tasks import make_task
from capevo.runtime.traces import RUNTIME_BATCH, TraceMetadata, TraceWriter

TARGET_US = 20.0
WRITES = ("write_plan_step", "write_invocation", "write_intervention", "write_env_step", "write_episode_summary")


def clock_writes(writer: TraceWriter, spent: list[int]) -> None:
    """Shadow the writer's ``write_*`` methods with ones that add their thread CPU ns to ``spent[0]``."""
    for name in WRITES:
        inner: Callable[[Any], None] = getattr(writer, name)

        def timed(record: Any, inner: Callable[[Any], None] = inner) -> None:
            t0 = time.thread_time_ns()
            try:
                inner(record)
            finally:
                spent[0] += time.thread_time_ns() - t0

        setattr(writer, name, timed)


def measure(task: str, seeds: int, batches: list[int]) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="bench-traces-loop-"))
    registry = LocalRegistry(tmp / "registry", actor="bench")
    env = make_task(task)
    caps = None
    per_batch: dict[int, dict[str, list[float]]] = {b: {"us_per_step": [], "pct": []} for b in batches}
    totals = {b: {"steps": 0, "bytes": 0, "write_ns": 0, "step_ns": 0} for b in batches}
    try:
        seed_registry(registry, task)
        env.reset(seed=0)
        caps = LoadedCapabilitySet(
            registry, task, observation_shapes={k: tuple(v.shape) for k, v in env.obs_dict.items()}
        )
        policy = DecompositionPolicy(identity=IdentityMemory.default())
        governor = make_governor(env, Phi.default())
        step_ns = [0]
        step = env.step

        def timed_step(action: Any) -> Any:
            t0 = time.thread_time_ns()
            try:
                return step(action)
            finally:
                step_ns[0] += time.thread_time_ns() - t0

        env.step = timed_step  # type: ignore[method-assign]
        metadata = TraceMetadata.collect(
            run_id="bench-traces-loop",
            task=task,
            capability_set=CapabilitySet(revision=1, active={"reach": 1}),
            phi_hash=governor.phi.hash,
            agent_identity_hash="0" * 64,
            seeds=tuple(range(seeds)),
        )
        for i in range(seeds):
            order = batches if i % 2 == 0 else batches[::-1]
            for batch in order:
                path = tmp / f"b{batch}-s{i}.mcap"
                spent = [0]
                step_ns[0] = 0
                with TraceWriter(path, metadata, batch=batch) as writer:
                    clock_writes(writer, spent)
                    outcome = run_episode(env, caps, policy, governor, writer, seed=1000 + i, episode=i)
                n = outcome.steps
                per_batch[batch]["us_per_step"].append(spent[0] / n / 1000)
                per_batch[batch]["pct"].append(100 * spent[0] / step_ns[0])
                t = totals[batch]
                t["steps"] += n
                t["bytes"] += path.stat().st_size
                t["write_ns"] += spent[0]
                t["step_ns"] += step_ns[0]
        del env.step
    finally:
        if caps is not None:
            caps.close()
        env.close()
        registry.close()
    rows = {}
    for batch in batches:
        t = totals[batch]
        us = per_batch[batch]["us_per_step"]
        rows[batch] = {
            "batch": batch,
            "episodes": seeds,
            "steps": t["steps"],
            "us_per_step_median": statistics.median(us),
            "us_per_step_per_episode": [round(x, 1) for x in us],
            "us_per_step_all": t["write_ns"] / t["steps"] / 1000,
            "env_step_cpu_ms": t["step_ns"] / t["steps"] / 1e6,
            "pct_of_env_step": 100 * t["write_ns"] / t["step_ns"],
            "bytes_per_step": t["bytes"] / t["steps"],
        }
    return {"task": task, "rows": [rows[b] for b in batches]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="T1")
    parser.add_argument("--seeds", type=int, default=6, help="episodes per batch size")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, RUNTIME_BATCH])
    args = parser.parse_args(argv)
    logging.getLogger("robosuite").setLevel(logging.ERROR)
    result = measure(args.task, args.seeds, args.batches)
    table = markdown_table(
        [
            "batch",
            "episodes",
            "steps",
            "CPU µs/step (median)",
            "per episode",
            "% of env step",
            "bytes/step",
        ],
        [
            [
                r["batch"],
                r["episodes"],
                r["steps"],
                f"{r['us_per_step_median']:.1f}",
                ", ".join(f"{x:.0f}" for x in r["us_per_step_per_episode"]),
                f"{r['pct_of_env_step']:.2f} %",
                f"{r['bytes_per_step']:.0f}",
            ]
            for r in result["rows"]
        ],
    )
    print(f"{args.task}, target <= {TARGET_US:.0f} µs and < 1 % of an env step")
    print(table)
    save_results("bench_traces_loop", {"args": vars(args), "machine": machine(), **result})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
