"""What trace writing costs in the real episode loop, as a share of episode wall time.

Each task's v0 skills (the untuned code ECMs every evolution starts from) run through the real
episode loop (``TaskEnv``, ``LoadedCapabilitySet``, ``DecompositionPolicy``, an enforcing
paper-Φ governor) with three sinks, each seed once per sink, back to back, the order alternating
by seed, so a slow phase of a shared machine hits every sink alike:

- ``none``: no sink; the loop builds no trace record;
- ``noop``: a sink whose methods do nothing; the loop builds every record;
- ``writer``: a real :class:`~capevo.runtime.traces.TraceWriter` (default settings: lz4, 256 KiB
  chunks, 1 s flush interval, background flush thread), one file per task for the whole run, as
  the runtime worker keeps one writer per capability set.

Figures per task (medians over episodes):

- ``writer share``: the CPU time of the writer's ``write_*`` calls (the calling thread's CPU
  clock around each, less the same clock around the no-op sink's calls: the clock's own cost)
  plus the flush thread's CPU time, over the episode's CPU time (the loop's thread and the flush
  thread). CPU clocks, so time the OS gives other processes on a shared box does not count; the
  episodes are CPU-bound, so this is also their share of wall time on an idle box.
- ``traces share, paired``: (``writer`` - ``none``) episode wall time over ``none``'s, the same
  seed: everything traces cost the loop (records built, writes, flushes), and the machine's
  noise, which on a shared box is of the same order.

    .venv/bin/python benchmarks/bench_traces_loop.py [--tasks T1 T6] [--seeds 6]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import markdown_table, save_results, scratch_dir

from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy
from capevo.learner.skills import seed_registry
from capevo.records import CapabilitySet
from capevo.registry.local import LocalRegistry
from capevo.runtime.capabilities import LoadedCapabilitySet
from capevo.runtime.episode import make_governor, run_episode
from capevo.runtime.governance import Phi
from capevo.runtime.tasks import make_task
from capevo.runtime.traces import TraceMetadata, TraceWriter
from capevo.runtime.traces.sink import WRITE_METHODS

SINKS = ("none", "noop", "writer")


def clock_writes(sink: Any, spent: list[int]) -> None:
    """Shadow ``sink``'s ``write_*`` methods with ones that add their thread CPU ns to ``spent[0]``."""

    def clocked(inner: Callable[[Any], None]) -> Callable[[Any], None]:
        def timed(record: Any) -> None:
            t0 = time.thread_time_ns()
            try:
                inner(record)
            finally:
                spent[0] += time.thread_time_ns() - t0

        return timed

    for name in WRITE_METHODS:
        setattr(sink, name, clocked(getattr(sink, name)))


def flush_thread_ns(sink: Any) -> int:
    """CPU ns the writer's background flush thread has spent so far (0 for a sink without one)."""
    thread = getattr(sink, "_thread", None)
    if thread is None or thread.ident is None or not thread.is_alive():
        return 0
    return time.clock_gettime_ns(time.pthread_getcpuclockid(thread.ident))


class NoOpSink:
    """A trace sink that does nothing."""

    def write_plan_step(self, record: Any) -> None:
        pass

    write_invocation = write_intervention = write_env_step = write_unsafe_step = write_episode_summary = write_plan_step

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


def measure(task: str, seeds: int) -> dict[str, Any]:
    """Run ``seeds`` episodes of ``task`` per sink, alternating; the figures of the module docstring."""
    tmp = scratch_dir("bench-traces-loop-")
    registry = LocalRegistry(tmp / "registry", actor="bench")
    env = make_task(task)
    caps = None
    runs: dict[str, list[dict[str, int]]] = {name: [] for name in SINKS}
    try:
        seed_registry(registry, task)
        env.reset(seed=0)
        caps = LoadedCapabilitySet(
            registry, task, observation_shapes={k: tuple(v.shape) for k, v in env.obs_dict.items()}
        )
        policy = DecompositionPolicy(identity=IdentityMemory.default())
        governor = make_governor(env, Phi.default())
        metadata = TraceMetadata.collect(
            run_id=f"bench-traces-loop-{task}",
            task=task,
            capability_set=CapabilitySet(revision=1, active={"reach": 1}),
            phi_hash=governor.phi.hash,
            agent_identity_hash="0" * 64,
            seeds=tuple(range(seeds)),
        )
        path = tmp / f"{task}.mcap"
        sinks: dict[str, Any] = {"none": None, "noop": NoOpSink(), "writer": TraceWriter(path, metadata)}
        spent = {name: [0] for name in SINKS}
        for name in ("noop", "writer"):
            clock_writes(sinks[name], spent[name])
        try:
            for i in range(seeds):
                for name in SINKS if i % 2 == 0 else SINKS[::-1]:
                    sink = sinks[name]
                    spent[name][0] = 0
                    background = flush_thread_ns(sink)
                    t0, c0 = time.perf_counter_ns(), time.thread_time_ns()
                    outcome = run_episode(env, caps, policy, governor, sink, seed=1000 + i, episode=i)
                    cpu, wall = time.thread_time_ns() - c0, time.perf_counter_ns() - t0
                    runs[name].append(
                        {
                            "steps": outcome.steps,
                            "wall_ns": wall,
                            "cpu_ns": cpu,
                            "write_ns": spent[name][0],
                            "background_ns": flush_thread_ns(sink) - background,
                        }
                    )
        finally:
            sinks["writer"].close()
        file_bytes = path.stat().st_size
    finally:
        if caps is not None:
            caps.close()
        env.close()
        registry.close()

    none, noop, writer = runs["none"], runs["noop"], runs["writer"]
    steps = sum(r["steps"] for r in writer)
    writer_share = [
        (w["write_ns"] - n["write_ns"] + w["background_ns"]) / (w["cpu_ns"] + w["background_ns"])
        for w, n in zip(writer, noop, strict=True)
    ]
    paired = [(w["wall_ns"] - b["wall_ns"]) / b["wall_ns"] for w, b in zip(writer, none, strict=True)]
    return {
        "task": task,
        "episodes": seeds,
        "steps": steps,
        "wall_ms_per_step": {
            name: statistics.median(r["wall_ns"] / r["steps"] / 1e6 for r in rs) for name, rs in runs.items()
        },
        "cpu_ms_per_step": {
            name: statistics.median(r["cpu_ns"] / r["steps"] / 1e6 for r in rs) for name, rs in runs.items()
        },
        "writer_us_per_step": statistics.median(
            (w["write_ns"] - n["write_ns"] + w["background_ns"]) / w["steps"] / 1000
            for w, n in zip(writer, noop, strict=True)
        ),
        "writer_pct_of_episode": 100 * statistics.median(writer_share),
        "writer_pct_of_episode_per_episode": [round(100 * x, 3) for x in writer_share],
        "traces_pct_paired": 100 * statistics.median(paired),
        "traces_pct_paired_per_episode": [round(100 * x, 2) for x in paired],
        "bytes_per_step": file_bytes / steps,
        "runs": runs,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["T1", "T6"])
    parser.add_argument("--seeds", type=int, default=6, help="episodes per sink")
    args = parser.parse_args(argv)
    logging.getLogger("robosuite").setLevel(logging.ERROR)
    results = [measure(task, args.seeds) for task in args.tasks]
    table = markdown_table(
        [
            "task",
            "episodes",
            "steps",
            "ms/step none",
            "ms/step noop",
            "ms/step writer",
            "writer µs/step",
            "writer % of episode",
            "traces %, paired",
            "bytes/step",
        ],
        [
            [
                r["task"],
                r["episodes"],
                r["steps"],
                f"{r['wall_ms_per_step']['none']:.2f}",
                f"{r['wall_ms_per_step']['noop']:.2f}",
                f"{r['wall_ms_per_step']['writer']:.2f}",
                f"{r['writer_us_per_step']:.1f}",
                f"{r['writer_pct_of_episode']:.2f} %",
                f"{r['traces_pct_paired']:+.1f} %",
                f"{r['bytes_per_step']:.0f}",
            ]
            for r in results
        ],
    )
    print(table)
    command = f".venv/bin/python benchmarks/bench_traces_loop.py --tasks {' '.join(args.tasks)} --seeds {args.seeds}"
    save_results("bench_traces_loop", {"command": command, "args": vars(args), "tasks": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
