"""Trace cost per env step where it is paid: inside the real episode loop, between robosuite steps.

``bench_traces.py`` times the writer in tight loops (warm caches) and after a synthetic cache
sweep. This runs a task's v0 skills (the untuned code ECMs every evolution starts from)
through the real episode loop (``TaskEnv``, ``LoadedCapabilitySet``, ``DecompositionPolicy``,
an enforcing paper-Φ governor, perturbations on) and measures three things per env step, each
seed once per variant, back to back, the order alternating by seed, so a slow phase of a shared
machine hits every variant alike:

- **write calls**: every ``write_*`` call of a real ``TraceWriter`` clocked with the calling
  thread's CPU clock (the env step and invocation rows' calls are the writer's C queue, whose
  full batches and due flushes encode, frame, compress and write inside the call). That clock
  is a system call here (about 0.7 µs on the reference VM), so each seed also runs through a
  sink whose methods do nothing, behind the same clock: its figure is the harness's own floor,
  and ``net`` subtracts it.
- **building**: what the loop does only for traces, outside the write calls: the records it
  still builds (interventions, and invocations of ECMs that cannot run) and, where an ECM's
  inputs are not all in the flat observation, its packed input vector (one C call,
  :func:`capevo.runtime.traces.rows.input_state_of`; a TaskEnv's ECMs name theirs by position in
  the observation instead, ``input_index``, which costs the loop nothing). The benchmark shadows
  those names in :mod:`capevo.runtime.episode` with clocked wrappers (the wrapper's argument
  repacking is counted, so this errs high), floor subtracted per call. The row tuples
  themselves are built inline in the loop and are not clocked (1–3 µs each, cold, by a
  one-off: see BENCHMARKS.md).
- **flush thread**: the CPU time of the writer's background flush thread over the episode
  (its wake-ups included, which wait in C without the GIL); in a busy loop the write calls find
  the flush due first.

Each variant keeps one sink for the whole run, as the runtime worker keeps one writer per
capability set: the flush thread's start and the file's summary are paid once per file, not
in the figures.

``whole`` is the three together. ``% of env step`` divides by the CPU time of the same
episodes' ``TaskEnv.step`` calls.

``--compressions lz4 none`` runs each batch size once per chunk compression (the worker's
``--trace-compression``), alternating with the rest, so the two are compared on the same episodes.

    .venv/bin/python benchmarks/bench_traces_loop.py [--task T1] [--seeds 8] [--batches 1 64]
        [--compressions lz4 none]
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, save_results

import capevo.runtime.episode as episode_loop
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
from capevo.runtime.traces.sink import WRITE_METHODS
from capevo.runtime.traces.writer import COMPRESSIONS

TARGET_US = 20.0
WRITES = WRITE_METHODS


BUILDERS = ("EnvStep", "EcmInvocation", "TraceIntervention", "_key_state", "_input_state")
"""The names the episode loop calls only to build trace records (see the module docstring); those
it does not have (the loop hands rows, not records, since the rows change) are skipped, so the
script also measures the code from before it (``PYTHONPATH`` at an older checkout)."""


def clocked(inner: Callable[..., Any], spent: list[int]) -> Callable[..., Any]:
    """``inner`` with its thread CPU ns added to ``spent[0]`` and its calls counted in ``spent[1]``."""

    def timed(*args: Any, **kwargs: Any) -> Any:
        t0 = time.thread_time_ns()
        try:
            return inner(*args, **kwargs)
        finally:
            spent[0] += time.thread_time_ns() - t0
            spent[1] += 1

    return timed


def clock_writes(writer: Any, spent: list[int]) -> None:
    """Shadow the writer's ``write_*`` methods with clocked ones (see :func:`clocked`)."""
    for name in WRITES:
        if hasattr(writer, name):
            setattr(writer, name, clocked(getattr(writer, name), spent))


@contextlib.contextmanager
def clock_building(spent: list[int]) -> Iterator[None]:
    """Shadow the loop's record builders with clocked ones for the duration of the block."""
    originals = {name: getattr(episode_loop, name) for name in BUILDERS if hasattr(episode_loop, name)}
    try:
        for name, inner in originals.items():
            setattr(episode_loop, name, clocked(inner, spent))
        yield
    finally:
        for name, inner in originals.items():
            setattr(episode_loop, name, inner)


def flush_thread_ns(sink: Any) -> int:
    """CPU ns the writer's background flush thread has spent so far (0 for a sink without one)."""
    thread = getattr(sink, "_thread", None)
    if thread is None or thread.ident is None:
        return 0
    return time.clock_gettime_ns(time.pthread_getcpuclockid(thread.ident))


class NoOpSink:
    """A trace sink that does nothing: the clock floor of :func:`clock_writes`."""

    def __init__(self, path: Path, metadata: TraceMetadata, *, batch: int) -> None:
        del path, metadata, batch

    def write_plan_step(self, record: Any) -> None:
        pass

    write_invocation = write_intervention = write_env_step = write_episode_summary = write_plan_step
    write_env_step_row = write_invocation_row = write_plan_step

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> NoOpSink:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


NOOP = (0, "")
"""The (batch, compression) variant that stands for :class:`NoOpSink` in a run."""


def measure(task: str, seeds: int, batches: list[int], compressions: list[str]) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="bench-traces-loop-"))
    registry = LocalRegistry(tmp / "registry", actor="bench")
    env = make_task(task)
    caps = None
    variants = [*((b, c) for b in batches for c in compressions), NOOP]
    runs: dict[tuple[int, str], list[dict[str, int]]] = {v: [] for v in variants}
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
        # One sink per variant for the whole run, as a worker keeps one writer per capability set
        # (its flush thread started once, its file finished once, outside the figures).
        sinks: dict[tuple[int, str], Any] = {}
        spent: dict[tuple[int, str], list[int]] = {}
        paths = {(batch, compression): tmp / f"b{batch}-{compression}.mcap" for batch, compression in variants}
        for variant in variants:
            batch, compression = variant
            if variant == NOOP:
                sinks[variant] = NoOpSink(paths[variant], metadata, batch=batch)
            else:
                sinks[variant] = TraceWriter(paths[variant], metadata, batch=batch, compression=compression)
            spent[variant] = [0, 0]
            clock_writes(sinks[variant], spent[variant])
        try:
            for i in range(seeds):
                for variant in variants if i % 2 == 0 else variants[::-1]:
                    sink, writes, building = sinks[variant], spent[variant], [0, 0]
                    writes[:] = [0, 0]
                    step_ns[0] = 0
                    background_before = flush_thread_ns(sink)
                    with clock_building(building):
                        outcome = run_episode(env, caps, policy, governor, sink, seed=1000 + i, episode=i)
                    runs[variant].append(
                        {
                            "steps": outcome.steps,
                            "write_ns": writes[0],
                            "write_calls": writes[1],
                            "build_ns": building[0],
                            "build_calls": building[1],
                            "background_ns": flush_thread_ns(sink) - background_before,
                            "step_ns": step_ns[0],
                        }
                    )
        finally:
            for sink in sinks.values():
                sink.close()
        file_bytes = {v: paths[v].stat().st_size if v != NOOP else 0 for v in variants}
        del env.step
    finally:
        if caps is not None:
            caps.close()
        env.close()
        registry.close()

    # The clock's own cost per call: a no-op write is a call and the clock, nothing else.
    noop = runs[NOOP]
    floor_ns = statistics.median(r["write_ns"] / r["write_calls"] for r in noop)

    def net(r: dict[str, int], kind: str) -> float:
        return (r[f"{kind}_ns"] - floor_ns * r[f"{kind}_calls"]) / r["steps"] / 1000

    rows = []
    for variant in variants[:-1]:
        batch, compression = variant
        rs = runs[variant]
        steps = sum(r["steps"] for r in rs)
        step_us = sum(r["step_ns"] for r in rs) / steps / 1000
        writes = [net(r, "write") for r in rs]
        building = [net(r, "build") for r in rs]
        background = [r["background_ns"] / r["steps"] / 1000 for r in rs]
        whole = [w + b + t for w, b, t in zip(writes, building, background, strict=True)]
        rows.append(
            {
                "batch": batch,
                "compression": compression,
                "episodes": seeds,
                "steps": steps,
                "gross_write_us_per_step_median": statistics.median(r["write_ns"] / r["steps"] / 1000 for r in rs),
                "write_us_per_step_median": statistics.median(writes),
                "build_us_per_step_median": statistics.median(building),
                "background_us_per_step_median": statistics.median(background),
                "whole_us_per_step_median": statistics.median(whole),
                "whole_us_per_step_per_episode": [round(x, 1) for x in whole],
                "env_step_cpu_ms": step_us / 1000,
                "whole_pct_of_env_step": 100 * statistics.median(whole) / step_us,
                "bytes_per_step": file_bytes[variant] / steps,
            }
        )
    return {"task": task, "clock_floor_us_per_call": floor_ns / 1000, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="T1")
    parser.add_argument("--seeds", type=int, default=8, help="episodes per variant")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, RUNTIME_BATCH])
    parser.add_argument("--compressions", nargs="+", default=["lz4"], choices=sorted(COMPRESSIONS))
    args = parser.parse_args(argv)
    logging.getLogger("robosuite").setLevel(logging.ERROR)
    result = measure(args.task, args.seeds, args.batches, args.compressions)
    table = markdown_table(
        [
            "batch",
            "compression",
            "episodes",
            "steps",
            "write calls, gross",
            "write calls, net",
            "building, net",
            "flush thread",
            "whole (µs/step)",
            "whole, per episode",
            "% of env step",
            "bytes/step",
        ],
        [
            [
                r["batch"],
                r["compression"],
                r["episodes"],
                r["steps"],
                f"{r['gross_write_us_per_step_median']:.1f}",
                f"{r['write_us_per_step_median']:.1f}",
                f"{r['build_us_per_step_median']:.1f}",
                f"{r['background_us_per_step_median']:.1f}",
                f"{r['whole_us_per_step_median']:.1f}",
                ", ".join(f"{x:.0f}" for x in r["whole_us_per_step_per_episode"]),
                f"{r['whole_pct_of_env_step']:.2f} %",
                f"{r['bytes_per_step']:.0f}",
            ]
            for r in result["rows"]
        ],
    )
    print(f"{args.task}, target <= {TARGET_US:.0f} µs and < 1 % of an env step (medians over episodes)")
    print(f"clock floor {result['clock_floor_us_per_call']:.2f} µs per clocked call")
    print(table)
    save_results("bench_traces_loop", {"args": vars(args), "machine": machine(), **result})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
