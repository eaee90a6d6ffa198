"""Runtime throughput: raw robosuite vs the capevo episode loop (governance and MCAP traces on).

Same task, same episodes: the episode loop runs T1 pick with the test suite's code ECMs
(reach, grasp, lift from a real LocalRegistry) under an enforcing governor with traces to a
real MCAP file; its executed actions are recorded and replayed, per seed, through

* ``robosuite``: ``env.robosuite_env.step(action)`` (after ``TaskEnv.reset(seed)``): the floor;
* ``task_env``: ``TaskEnv.step(action)`` (capevo's task wrapper: observation noise, dropped
  actions, task reward and success);
* ``loop``: ``run_episode`` itself (decisions, termination predicates over ``signals()``,
  ECM invocation, governance + unsafe check, trace records for every step and call).

Two measurements, each the median over rounds:

* **in-run** (the headline; immune to the box's drift): during the loop's own run, the time
  spent inside ``robosuite_env.step`` and inside ``TaskEnv.step``/``reset`` is clocked; the
  robosuite rate is steps / (robosuite step time + reset time), the TaskEnv rate steps /
  (TaskEnv step time + reset time), the loop rate steps / the loop's wall time.
* **replay**: the recorded actions replayed through ``robosuite_env.step`` and through
  ``TaskEnv.step`` in separate passes, interleaved round by round with the loop (a shared
  2-core box drifts between passes, so this one is noisier).

    .venv/bin/python benchmarks/bench_worker.py [--rounds 5] [--seeds 10] [--horizon 150]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
# Test support: the T1 code skills (tests/runtime) and the process helpers they use (tests/).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "runtime"))

from _common import markdown_table, save_results
from runtime_support import publish_pick

from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy
from capevo.registry.local import LocalRegistry
from capevo.runtime.capabilities import LoadedCapabilitySet
from capevo.runtime.episode import make_governor, run_episode
from capevo.runtime.governance import Phi
from capevo.runtime.tasks import make_task
from capevo.runtime.traces import MemoryTraceSink, TraceMetadata, TraceWriter

TARGET_OVERHEAD_PCT = 3.0


class _TimedSink:
    """Forwards to a TraceSink, clocking every write."""

    def __init__(self, inner: Any, clock: dict[str, float]) -> None:
        self.inner, self.clock = inner, clock

    def __getattr__(self, name: str) -> Any:
        fn = getattr(self.inner, name)
        if not name.startswith("write_"):
            return fn

        def timed(record: Any) -> None:
            t0 = time.perf_counter()
            fn(record)
            self.clock["trace writes"] += time.perf_counter() - t0

        return timed


class _TimedGovernor:
    def __init__(self, inner: Any, clock: dict[str, float]) -> None:
        self.inner, self.clock = inner, clock
        self.phi, self.enforce = inner.phi, inner.enforce

    def __call__(self, state: Any, action: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return self.inner(state, action)
        finally:
            self.clock["governance R(a, Φ)"] += time.perf_counter() - t0


class _TimedCaps:
    def __init__(self, inner: Any, clock: dict[str, float]) -> None:
        self.inner, self.clock = inner, clock

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def make_invoker(self, name: str, **kwargs: Any) -> Any:
        invoker = self.inner.make_invoker(name, **kwargs)
        step = invoker.step

        def timed(obs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return step(obs)
            finally:
                self.clock["ECM call (invoker)"] += time.perf_counter() - t0

        invoker.step = timed
        return invoker


def component_breakdown(
    env: Any, caps: Any, policy: Any, governor: Any, seeds: list[int], tmp: Path, phi: Any
) -> dict[str, dict[str, float]]:
    """One instrumented loop pass: wall time per part of a step."""
    clock = dict.fromkeys(
        [
            "TaskEnv.step (robosuite inside)",
            "TaskEnv.reset",
            "signals() for termination",
            "robot_state()",
            "ECM call (invoker)",
            "governance R(a, Φ)",
            "trace writes",
        ],
        0.0,
    )
    originals = {"step": env.step, "reset": env.reset, "signals": env.signals, "robot_state": env.robot_state}
    keys = {
        "step": "TaskEnv.step (robosuite inside)",
        "reset": "TaskEnv.reset",
        "signals": "signals() for termination",
        "robot_state": "robot_state()",
    }

    depth = [0]  # TaskEnv.step calls signals() itself (for the reward); count only the loop's calls

    def wrap(attr: str) -> Any:
        fn = originals[attr]

        def timed(*a: Any, **k: Any) -> Any:
            if depth[0]:
                return fn(*a, **k)
            depth[0] += attr == "step"
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                clock[keys[attr]] += time.perf_counter() - t0
                depth[0] -= attr == "step"

        return timed

    for attr in originals:
        setattr(env, attr, wrap(attr))
    metadata = TraceMetadata.collect(
        run_id="bench-breakdown",
        task=env.task_spec.name,
        capability_set=caps.capability_set,
        phi_hash=phi.hash,
        agent_identity_hash="bench",
        seeds=seeds,
    )
    steps = 0
    try:
        with TraceWriter(tmp / "breakdown.mcap", metadata) as writer:
            sink = _TimedSink(writer, clock)
            tcaps, tgov = _TimedCaps(caps, clock), _TimedGovernor(governor, clock)
            t0 = time.perf_counter()
            for i, seed in enumerate(seeds):
                steps += run_episode(env, tcaps, policy, tgov, sink, seed=seed, episode=i).steps
            total = time.perf_counter() - t0
    finally:
        for attr in originals:
            delattr(env, attr)
    out = {k: {"us_per_step": v / steps * 1e6, "share": v / total} for k, v in clock.items()}
    rest = total - sum(clock.values())
    out["rest of the loop (decisions, unsafe check, records)"] = {
        "us_per_step": rest / steps * 1e6,
        "share": rest / total,
    }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--horizon", type=int, default=150)
    parser.add_argument("--task", default="T1")
    args = parser.parse_args(argv)
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)

    tmp = Path(tempfile.mkdtemp(prefix="bench-worker-"))
    registry = LocalRegistry(tmp / "registry", actor="bench")
    publish_pick(registry)
    env = make_task(args.task, horizon=args.horizon)
    rs = env.robosuite_env
    env.reset(seed=0)
    shapes = {k: tuple(v.shape) for k, v in env.obs_dict.items()}
    caps = LoadedCapabilitySet(registry, args.task, observation_shapes=shapes)
    policy = DecompositionPolicy(identity=IdentityMemory.default())
    phi = Phi.default()
    governor = make_governor(env, phi)
    seeds = list(range(args.seeds))

    # One recording pass: the executed actions of each seed's episode.
    actions: dict[int, list[np.ndarray]] = {}
    for seed in seeds:
        sink = MemoryTraceSink()
        run_episode(env, caps, policy, governor, sink, seed=seed)
        actions[seed] = [np.asarray(s.action, dtype=np.float64) for s in sink.env_steps]
    total_steps = sum(len(a) for a in actions.values())

    def raw() -> float:
        t0 = time.perf_counter()
        for seed in seeds:
            env.reset(seed=seed)
            for a in actions[seed]:
                rs.step(a)
        return time.perf_counter() - t0

    def task_env() -> float:
        t0 = time.perf_counter()
        for seed in seeds:
            env.reset(seed=seed)
            for a in actions[seed]:
                env.step(a)
        return time.perf_counter() - t0

    clock = {"robosuite": 0.0, "task_env": 0.0, "reset": 0.0}
    rs_step, env_step, env_reset = rs.step, env.step, env.reset

    def timed(fn: Any, key: str) -> Any:
        def wrapper(*a: Any, **k: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                clock[key] += time.perf_counter() - t0

        return wrapper

    def loop(round_index: int) -> tuple[float, int, dict[str, float]]:
        metadata = TraceMetadata.collect(
            run_id=f"bench-{round_index}",
            task=env.task_spec.name,
            capability_set=caps.capability_set,
            phi_hash=phi.hash,
            agent_identity_hash="bench",
            seeds=seeds,
        )
        steps = 0
        for key in clock:
            clock[key] = 0.0
        # Instance attributes shadow the methods: TaskEnv calls self._env.step, the loop env.step.
        rs.step, env.step, env.reset = (
            timed(rs_step, "robosuite"),
            timed(env_step, "task_env"),
            timed(env_reset, "reset"),
        )
        try:
            with TraceWriter(tmp / f"loop-{round_index}.mcap", metadata) as sink:
                t0 = time.perf_counter()
                for i, seed in enumerate(seeds):
                    steps += run_episode(env, caps, policy, governor, sink, seed=seed, episode=i).steps
                elapsed = time.perf_counter() - t0
        finally:
            del rs.step, env.step, env.reset
        return elapsed, steps, dict(clock)

    rates: dict[str, list[float]] = {"robosuite": [], "task_env": [], "loop": []}
    in_run: dict[str, list[float]] = {"robosuite": [], "task_env": [], "loop": []}
    for r in range(args.rounds):
        rates["robosuite"].append(total_steps / raw())
        rates["task_env"].append(total_steps / task_env())
        elapsed, steps, spent = loop(r)
        if steps != total_steps:
            raise SystemExit(f"the loop ran {steps} steps, the recording {total_steps}: episodes are not reproducible")
        rates["loop"].append(steps / elapsed)
        in_run["loop"].append(steps / elapsed)
        in_run["robosuite"].append(steps / (spent["robosuite"] + spent["reset"]))
        in_run["task_env"].append(steps / (spent["task_env"] + spent["reset"]))
        print(
            f"round {r + 1}/{args.rounds}: in-run "
            + ", ".join(f"{k} {v[-1]:.1f}/s" for k, v in in_run.items())
            + "; replay "
            + ", ".join(f"{k} {v[-1]:.1f}/s" for k, v in rates.items() if k != "loop"),
            flush=True,
        )

    def table(rates: dict[str, list[float]]) -> tuple[dict[str, float], list[list[Any]], float, float]:
        med = {k: statistics.median(v) for k, v in rates.items()}
        vs_raw = (1.0 - med["loop"] / med["robosuite"]) * 100.0
        vs_task = (1.0 - med["loop"] / med["task_env"]) * 100.0
        rows: list[list[Any]] = [
            ["robosuite (env.step)", f"{med['robosuite']:.1f}", "-", "-"],
            ["TaskEnv.step", f"{med['task_env']:.1f}", f"{(1 - med['task_env'] / med['robosuite']) * 100:.2f}%", "-"],
            ["episode loop (gov + MCAP)", f"{med['loop']:.1f}", f"{vs_raw:.2f}%", f"{vs_task:.2f}%"],
        ]
        return med, rows, vs_raw, vs_task

    breakdown = component_breakdown(env, caps, policy, governor, seeds, tmp, phi)

    headers = ["mode", "steps/s", "slower than robosuite", "slower than TaskEnv"]
    med_in, rows_in, in_raw, in_task = table(in_run)
    med, rows, overhead_raw, overhead_task = table(rates)
    per_step_us = (1.0 / med_in["loop"] - 1.0 / med_in["task_env"]) * 1e6
    print()
    print(f"{args.task}, {args.seeds} seeds, {total_steps} steps per round, median of {args.rounds} rounds")
    print("\nin-run (clocked inside the loop's own run):")
    print(markdown_table(headers, rows_in))
    print("\nreplay (separate passes):")
    print(markdown_table(headers, rows))
    print(
        f"\nloop cost per step over TaskEnv.step (in-run): {per_step_us:.0f} µs; target: at most {TARGET_OVERHEAD_PCT}%"
    )
    print("\nwhere a loop step's time goes (one instrumented pass):")
    print(
        markdown_table(
            ["part", "µs per env step", "share of the loop's wall time"],
            [[k, f"{v['us_per_step']:.1f}", f"{v['share'] * 100:.2f}%"] for k, v in breakdown.items()],
        )
    )
    path = save_results(
        "bench_worker",
        {
            "task": args.task,
            "seeds": args.seeds,
            "horizon": args.horizon,
            "rounds": args.rounds,
            "steps_per_round": total_steps,
            "in_run_steps_per_s": {k: {"median": med_in[k], "all": v} for k, v in in_run.items()},
            "in_run_overhead_vs_robosuite_pct": in_raw,
            "in_run_overhead_vs_task_env_pct": in_task,
            "replay_steps_per_s": {k: {"median": med[k], "all": v} for k, v in rates.items()},
            "replay_overhead_vs_robosuite_pct": overhead_raw,
            "replay_overhead_vs_task_env_pct": overhead_task,
            "loop_cost_per_step_us": per_step_us,
            "breakdown": breakdown,
            "target_overhead_pct": TARGET_OVERHEAD_PCT,
        },
    )
    print(f"results: {path}")
    caps.close()
    env.close()
    registry.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
