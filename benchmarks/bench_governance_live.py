"""Governance cost per action over the actions real episodes produce: R(a, Φ) p50/p99, six tasks.

``bench_governance.py`` times chosen cases (allow, each modify path, reject); this times the
mix a run actually has. For each task, its built-in v0 skills (the manual, untuned code ECMs
every evolution starts from) run ``--episodes`` seeded episodes through the real episode
loop (``TaskEnv``, ``LoadedCapabilitySet``, ``DecompositionPolicy``, an enforcing governor,
perturbations on), once under the paper's Φ and once under the per-task Φ
(``Phi.for_task``). The governor is wrapped so that every call's ``(state, action)`` is kept
and the call is clocked where it runs (*in loop*: between robosuite steps, which evict the
caches). Then every kept pair is governed again ``--repeats`` times by a fresh governor of
the same Φ, layout and action frames, in a shuffled order, each call timed alone with
``perf_counter_ns`` (*in process*: the timer's own cost, ``timer_ns``, is included).
``% of env step`` is the in-process p50 over the p50 of the same episodes' ``TaskEnv.step``.

``sense`` is ``TaskEnv.robot_state()`` per step: the state governance reads, which under the
per-task Φ includes the proximity pairs MuJoCo measures (not part of R(a, Φ), but paid per step).

    .venv/bin/python benchmarks/bench_governance_live.py [--episodes 2] [--repeats 20] [--tasks T1 T6]
"""

from __future__ import annotations

import argparse
import logging
import random
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import markdown_table, percentile, save_results, scratch_dir

from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy
from capevo.learner.skills import seed_registry
from capevo.registry.local import LocalRegistry
from capevo.runtime.capabilities import LoadedCapabilitySet
from capevo.runtime.episode import make_governor, run_episode
from capevo.runtime.governance import Governor, Phi
from capevo.runtime.tasks import make_task

TARGET_P50_MS = 0.005
TASKS = ("T1", "T2", "T3", "T4", "T5", "T6")
ENVELOPES: dict[str, Callable[[Any], Phi]] = {"paper": lambda env: Phi.default(), "per-task": Phi.for_task}


class RecordingGovernor:
    """A governor that keeps every call's inputs, its in-loop duration and what R answered."""

    def __init__(self, inner: Governor) -> None:
        self.inner, self.phi, self.enforce = inner, inner.phi, inner.enforce
        self.calls: list[tuple[Any, Any]] = []
        self.loop_ns: list[int] = []
        self.outcomes: list[str] = []

    def new_episode(self) -> None:
        self.inner.new_episode()

    def __call__(self, state: Any, action: Any) -> Any:
        t0 = time.perf_counter_ns()
        governed, ivs = self.inner(state, action)
        self.loop_ns.append(time.perf_counter_ns() - t0)
        self.calls.append((state, action))
        self.outcomes.append("allow" if not ivs else "reject" if governed is None else "modify")
        return governed, ivs


def timer_overhead_ns(n: int = 20_000) -> float:
    clock = time.perf_counter_ns
    xs = []
    for _ in range(n):
        t0 = clock()
        xs.append(clock() - t0)
    xs.sort()
    return float(xs[len(xs) // 2])


def time_each(governor: Governor, calls: Sequence[tuple[Any, Any]], repeats: int, seed: int) -> list[list[int]]:
    """Per call index, ``repeats`` durations in ns, the calls interleaved in shuffled rounds."""
    clock = time.perf_counter_ns
    out: list[list[int]] = [[] for _ in calls]
    order = list(range(len(calls)))
    rng = random.Random(seed)
    for state, action in calls[:200]:  # warm-up
        governor(state, action)
    for _ in range(repeats):
        rng.shuffle(order)
        for i in order:
            state, action = calls[i]
            t0 = clock()
            governor(state, action)
            out[i].append(clock() - t0)
    return out


def ms(xs: Sequence[float], q: float) -> float:
    return percentile(xs, q) / 1e6 if xs else float("nan")


def measure(task: str, envelope: str, episodes: int, repeats: int, horizon: int | None) -> dict[str, Any]:
    tmp = scratch_dir("bench-gov-live-")
    registry = LocalRegistry(tmp / "registry", actor="bench")
    env = make_task(task, horizon=horizon)
    caps = None
    try:
        seed_registry(registry, task)
        env.reset(seed=0)
        caps = LoadedCapabilitySet(
            registry, task, observation_shapes={k: tuple(v.shape) for k, v in env.obs_dict.items()}
        )
        policy = DecompositionPolicy(identity=IdentityMemory.default())
        phi = ENVELOPES[envelope](env)
        inner = make_governor(env, phi)
        recorder = RecordingGovernor(inner)
        step_ns: list[int] = []
        sense_ns: list[int] = []
        step, sense = env.step, env.robot_state

        def timed_step(action: Any) -> Any:
            t0 = time.perf_counter_ns()
            try:
                return step(action)
            finally:
                step_ns.append(time.perf_counter_ns() - t0)

        def timed_sense() -> Any:
            t0 = time.perf_counter_ns()
            try:
                return sense()
            finally:
                sense_ns.append(time.perf_counter_ns() - t0)

        env.step = timed_step  # type: ignore[method-assign]
        env.robot_state = timed_sense  # type: ignore[method-assign]
        successes = unsafe = 0
        try:
            for seed in range(episodes):
                outcome = run_episode(env, caps, policy, recorder, None, seed=1000 + seed, episode=seed)
                successes += outcome.success
                unsafe += outcome.unsafe_steps > 0
        finally:
            del env.step
            del env.robot_state
        fresh = Governor(phi, env.task_spec.action_layout, frames=inner.frames)
        per_call = time_each(fresh, recorder.calls, repeats, seed=len(recorder.calls))
    finally:
        if caps is not None:
            caps.close()
        env.close()
        registry.close()
    n = len(recorder.calls)
    step_p50 = percentile(step_ns, 50) / 1e6
    every = [t for ts in per_call for t in ts]
    by_outcome: dict[str, list[int]] = {"allow": [], "modify": [], "reject": []}
    for outcome, ts in zip(recorder.outcomes, per_call, strict=True):
        by_outcome[outcome].extend(ts)
    return {
        "task": task,
        "envelope": envelope,
        "phi_hash": phi.hash,
        "episodes": episodes,
        "successes": successes,
        "unsafe_episodes": unsafe,
        "actions": n,
        "share": {k: sum(1 for o in recorder.outcomes if o == k) / n for k in ("allow", "modify", "reject")},
        "in_process": {"p50_ms": ms(every, 50), "p99_ms": ms(every, 99), "samples": len(every)},
        "in_process_by_outcome_p50_ms": {k: ms(v, 50) for k, v in by_outcome.items() if v},
        "pct_of_env_step": 100.0 * ms(every, 50) / step_p50,
        "in_loop": {"p50_ms": ms(recorder.loop_ns, 50), "p99_ms": ms(recorder.loop_ns, 99)},
        "sense_p50_ms": percentile(sense_ns, 50) / 1e6,
        "env_step_p50_ms": step_p50,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS))
    parser.add_argument("--envelopes", nargs="+", default=list(ENVELOPES), choices=list(ENVELOPES))
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per recorded action")
    parser.add_argument("--horizon", type=int, default=None, help="default: each task's own")
    parser.add_argument("--out", default="governance_live")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.repeats < 1:
        parser.error("--episodes and --repeats must be at least 1")
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    timer = timer_overhead_ns()
    rows: list[dict[str, Any]] = []
    for task in args.tasks:
        for envelope in args.envelopes:
            row = measure(task, envelope, args.episodes, args.repeats, args.horizon)
            rows.append(row)
            print(f"{task} {envelope}: {row['actions']} actions, p50 {row['in_process']['p50_ms']:.4f} ms", flush=True)
    table = []
    for r in rows:
        by = r["in_process_by_outcome_p50_ms"]
        table.append(
            [
                r["task"],
                r["envelope"],
                r["actions"],
                " / ".join(f"{100 * r['share'][k]:.0f}" for k in ("allow", "modify", "reject")),
                f"{r['in_process']['p50_ms']:.4f}",
                f"{r['in_process']['p99_ms']:.4f}",
                " / ".join(f"{by[k]:.4f}" if k in by else "—" for k in ("allow", "modify")),
                f"{r['pct_of_env_step']:.3f} %",
                f"{r['in_loop']['p50_ms']:.4f} / {r['in_loop']['p99_ms']:.4f}",
                f"{r['sense_p50_ms']:.3f}",
                f"{r['successes']}/{r['episodes']}",
            ]
        )
    print()
    print(f"timer overhead {timer:.0f} ns per call (included); target p50 <= {TARGET_P50_MS} ms")
    print(
        markdown_table(
            [
                "task",
                "Φ",
                "actions",
                "allow / modify / reject %",
                "p50 ms",
                "p99 ms",
                "p50 allow / modify ms",
                "p50 % of env step",
                "in loop p50 / p99 ms",
                "sense p50 ms",
                "v0 success",
            ],
            table,
        )
    )
    path = save_results(args.out, {"timer_ns": timer, "target_p50_ms": TARGET_P50_MS, "rows": rows})
    print(f"results: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
