"""Runtime throughput: raw robosuite vs the capevo episode loop (governance and MCAP traces on).

Same task, same episodes, interleaved. A recording pass runs T1 pick with the test suite's
code ECMs (reach, grasp, lift from a real LocalRegistry) under an enforcing governor and keeps
each seed's executed actions. The governor's envelope is ``--phi``: ``task`` (the default, the
runtime's default too) is ``Phi.for_task(task_spec(task))``, which reads proximity pairs, so
``robot_state()`` senses them every step (``make_governor`` sets ``env.sense_proximity``);
``paper`` is ``Phi.default()``, which reads none. Then, every round, for every seed, three runs go back to back
(their order rotating from round to round, so drift on a shared box hits all of them alike):

* robosuite: ``robosuite_env.reset()``, then the recorded actions through
  ``robosuite_env.step(a)``, on the robosuite environment capevo builds (PickPlace,
  BASIC/OSC_POSE Panda controller, horizon, headless, every observable on). Between the timed
  reset and the timed steps an untimed ``TaskEnv.reset(seed)`` puts the episode's scene in
  place, so the steps replay the very episode the worker ran. Even steps run robosuite as
  shipped (``robosuite_stock``: the floor); odd steps run it the way capevo's TaskEnv does,
  without the work of robosuite's step that capevo never reads (``robosuite_lean``; see
  ``capevo.runtime.tasks.lean_stepping``: per-substep observable sampling, each robot's action
  size recomputed every substep, and robosuite's reward for a task that has its own, as T1).
  Each is extrapolated to the whole episode from its own steps;
* ``task_env``: ``TaskEnv.reset(seed)`` and ``TaskEnv.step(a)`` (capevo's task wrapper:
  exact observations, observation noise, dropped actions, task reward, signals, success);
* ``worker``: ``run_episode`` itself (decisions, termination predicates, ECM invocation,
  proximity sensing, governance R(a, Φ), the independent safety monitor, MCAP trace records on
  all five channels through a real ``TraceWriter``, opened before and closed after the round).

Every run is clocked in wall time (``perf_counter``) and in CPU time of the whole process
(``process_time``: the trace writer's flush thread counts). Overheads are reported per round
and per episode pair, as median and interquartile range. Inside the task_env and worker runs
robosuite's own reset and step calls are clocked too ("in-run"): the variant against the
robosuite work it contains, sampled in the same episodes, immune to drift between runs. A
worker episode that runs a different number of steps than recorded stops the benchmark.

A last, separately instrumented pass splits a worker step into parts (µs per step):
``robot_state()`` (with, as a row of its own, the proximity sensing inside it), governance,
the safety monitor's ``judge``, and the rest.

    .venv/bin/python benchmarks/bench_worker.py [--rounds 12] [--seeds 8] [--horizon 150] [--phi task|paper]
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
# Test support: the T1 code skills (tests/runtime) and the process helpers they use (tests/).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "runtime"))

from _common import markdown_table, percentile, save_results, scratch_dir
from runtime_support import publish_pick

import capevo
from capevo.agent.identity import IdentityMemory
from capevo.agent.policy import DecompositionPolicy
from capevo.registry.local import LocalRegistry
from capevo.runtime.capabilities import LoadedCapabilitySet
from capevo.runtime.episode import make_governor, run_episode
from capevo.runtime.governance import Phi
from capevo.runtime.governance.proximity import ProximitySensor
from capevo.runtime.safety_monitor import SafetyMonitor
from capevo.runtime.tasks import lean_stepping, make_task, task_spec
from capevo.runtime.traces import MemoryTraceSink, TraceMetadata, TraceWriter

TARGET_OVERHEAD_PCT = 3.0
CLOCKS = ("wall", "cpu")
SENSING = "  of which proximity sensing (ProximitySensor.sense)"
"""A part inside ``robot_state()``: reported, and not added again to the sum of the parts."""


def _now() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


class _Timed:
    """Wraps callables so each call's wall time adds to ``clock[key]``, its CPU time (this
    thread's) to ``cpu[key]``. Nested timed calls count in both parts."""

    def __init__(self, clock: dict[str, float], cpu: dict[str, float]) -> None:
        self.clock, self.cpu = clock, cpu

    def wrap(self, fn: Callable[..., Any], key: str) -> Callable[..., Any]:
        clock, cpu = self.clock, self.cpu
        clock.setdefault(key, 0.0)
        cpu.setdefault(key, 0.0)

        def timed(*a: Any, **k: Any) -> Any:
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                cpu[key] += time.thread_time() - c0
                clock[key] += time.perf_counter() - t0

        return timed


class _TimedSink:
    """A TraceSink that forwards to ``inner``, clocking every write."""

    def __init__(self, inner: Any, timed: _Timed) -> None:
        for name in ("write_plan_step", "write_invocation", "write_intervention", "write_env_step"):
            setattr(self, name, timed.wrap(getattr(inner, name), "trace writes"))
        self.write_episode_summary = timed.wrap(inner.write_episode_summary, "trace: episode summary + flush")
        self.flush, self.close = inner.flush, inner.close


class _TimedGovernor:
    """The governor, its calls clocked; every other attribute is the governor's own."""

    def __init__(self, inner: Any, timed: _Timed) -> None:
        self.inner = inner
        self._call = timed.wrap(inner, "governance R(a, Φ)")

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def __call__(self, state: Any, action: Any) -> Any:
        return self._call(state, action)


class _TimedCaps:
    def __init__(self, inner: Any, timed: _Timed) -> None:
        self.inner, self.timed = inner, timed

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def make_invoker(self, name: str, **kwargs: Any) -> Any:
        invoker = self.inner.make_invoker(name, **kwargs)
        invoker.step = self.timed.wrap(invoker.step, "ECM call (invoker)")
        return invoker


def component_breakdown(
    env: Any, caps: Any, policy: Any, governor: Any, seeds: list[int], tmp: Path, metadata: TraceMetadata
) -> dict[str, dict[str, float]]:
    """One instrumented worker pass: wall time per part of a step (the timers add a little)."""
    clock: dict[str, float] = {}
    cpu: dict[str, float] = {}
    timed = _Timed(clock, cpu)
    rs = env.robosuite_env
    # Instance attributes shadow the methods; TaskEnv calls self._env.step, the loop env.step.
    rs.step = timed.wrap(rs.step, "robosuite env.step")
    env.reset = timed.wrap(env.reset, "TaskEnv.reset")
    env.robot_state = timed.wrap(env.robot_state, "robot_state() incl. sensing")
    # The sensor is the env's own and the loop builds its monitor itself: clock both classes'
    # methods for this pass (class attributes, restored below).
    sense, judge = ProximitySensor.sense, SafetyMonitor.judge
    ProximitySensor.sense = timed.wrap(sense, SENSING)  # type: ignore[method-assign]
    env.step = timed.wrap(env.step, "TaskEnv.step (robosuite step inside)")
    SafetyMonitor.judge = timed.wrap(judge, "safety monitor judge()")  # type: ignore[method-assign]
    steps = 0
    try:
        with TraceWriter(tmp / "breakdown.mcap", metadata) as writer:
            sink = _TimedSink(writer, timed)
            tcaps, tgov = _TimedCaps(caps, timed), _TimedGovernor(governor, timed)
            t0, c0 = time.perf_counter(), time.thread_time()
            for i, seed in enumerate(seeds):
                steps += run_episode(env, tcaps, policy, tgov, sink, seed=seed, episode=i).steps
            total, total_cpu = time.perf_counter() - t0, time.thread_time() - c0
    finally:
        del rs.step, env.reset, env.robot_state, env.step
        ProximitySensor.sense, SafetyMonitor.judge = sense, judge  # type: ignore[method-assign]
    out: dict[str, dict[str, float]] = {}
    for k in clock:
        wall, spent = clock[k], cpu[k]
        if k.startswith("TaskEnv.step"):
            k = "TaskEnv.step beyond robosuite"
            wall, spent = wall - clock["robosuite env.step"], spent - cpu["robosuite env.step"]
        out[k] = {"us_per_step": wall / steps * 1e6, "cpu_us_per_step": spent / steps * 1e6}
    parts = [v for k, v in out.items() if k != SENSING]
    out["rest of the loop (decisions, predicates, records)"] = {
        "us_per_step": total / steps * 1e6 - sum(v["us_per_step"] for v in parts),
        "cpu_us_per_step": total_cpu / steps * 1e6 - sum(v["cpu_us_per_step"] for v in parts),
    }
    for v in out.values():
        v["share"] = v["us_per_step"] / (total / steps * 1e6)
    return out


def _spread(xs: list[float]) -> dict[str, float]:
    return {
        "median": statistics.median(xs),
        "p25": percentile(xs, 25),
        "p75": percentile(xs, 75),
        "min": min(xs),
        "max": max(xs),
        "n": len(xs),
    }


class _Clock:
    """Wall and process-CPU seconds spent inside wrapped calls."""

    def __init__(self) -> None:
        self.wall = 0.0
        self.cpu = 0.0

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*a: Any, **k: Any) -> Any:
            w0, c0 = _now()
            try:
                return fn(*a, **k)
            finally:
                w1, c1 = _now()
                self.wall += w1 - w0
                self.cpu += c1 - c0

        return timed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=12)
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=150)
    parser.add_argument("--task", default="T1")
    parser.add_argument(
        "--phi",
        choices=("paper", "task"),
        default="task",
        help="the governing envelope: Phi.for_task (the runtime default; proximity sensing on) or the paper's",
    )
    parser.add_argument("--label", default="", help="free text stored with the results (e.g. the code state)")
    parser.add_argument("--out", default="bench_worker", help="results file name under benchmarks/results/")
    args = parser.parse_args(argv)
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)

    tmp = scratch_dir("bench-worker-")
    registry = LocalRegistry(tmp / "registry", actor="bench")
    publish_pick(registry)
    env = make_task(args.task, horizon=args.horizon)
    rs = env.robosuite_env
    env.reset(seed=0)
    shapes = {k: tuple(v.shape) for k, v in env.obs_dict.items()}
    caps = LoadedCapabilitySet(registry, args.task, observation_shapes=shapes)
    policy = DecompositionPolicy(identity=IdentityMemory.default())
    phi = Phi.default() if args.phi == "paper" else Phi.for_task(task_spec(args.task))
    governor = make_governor(env, phi)
    seeds = list(range(args.seeds))

    def metadata(run_id: str) -> TraceMetadata:
        return TraceMetadata.collect(
            run_id=run_id,
            task=env.task_spec.name,
            capability_set=caps.capability_set,
            phi_hash=phi.hash,
            agent_identity_hash="bench",
            seeds=seeds,
        )

    # One recording pass: the executed actions of each seed's episode.
    actions: dict[int, list[np.ndarray]] = {}
    for seed in seeds:
        sink = MemoryTraceSink()
        run_episode(env, caps, policy, governor, sink, seed=seed)
        actions[seed] = [np.asarray(s.action, dtype=np.float64) for s in sink.env_steps]
    steps_per_round = sum(len(a) for a in actions.values())

    # TaskEnv switches off work of robosuite's step that it never reads (instance attributes,
    # capevo.runtime.tasks.lean_stepping); the replay switches them off and on step by step.
    overrides = env.robosuite_overrides

    def use_lean(lean: bool) -> None:
        (lean_stepping.install if lean else lean_stepping.remove)(rs, overrides)

    Times = dict[str, tuple[float, float]]  # variant -> (wall, cpu) seconds of one episode

    def run_robosuite(seed: int, _episode: int, _writer: Any) -> Times:
        """robosuite reset + the recorded steps, odd steps lean, even steps stock."""
        acts = actions[seed]
        use_lean(False)
        try:
            w0, c0 = _now()
            rs.reset()
            w1, c1 = _now()
            env.reset(seed=seed)  # untimed: the recorded episode's scene (jitter included)
            spent = {"stock": [0.0, 0.0, 0], "lean": [0.0, 0.0, 0]}
            for i, a in enumerate(acts):
                mode = "lean" if i % 2 else "stock"
                use_lean(bool(i % 2))
                s0, p0 = _now()
                rs.step(a)
                s1, p1 = _now()
                acc = spent[mode]
                acc[0] += s1 - s0
                acc[1] += p1 - p0
                acc[2] += 1
        finally:
            use_lean(True)
        n = len(acts)
        out: Times = {}
        for mode, (wall, cpu, k) in spent.items():
            # the whole episode at this mode's per-step cost (both modes see the same states)
            out[f"robosuite_{mode}"] = ((w1 - w0) + wall / k * n, (c1 - c0) + cpu / k * n)
        return out

    def in_run(variant: str, call: Callable[[], int], seed: int) -> Times:
        """Run ``call`` with robosuite's reset and step clocked: the variant's total and the
        robosuite time inside it."""
        clock = _Clock()
        rs.step, rs.reset = clock.wrap(rs.step), clock.wrap(rs.reset)
        try:
            w0, c0 = _now()
            steps = call()
            w1, c1 = _now()
        finally:
            del rs.step, rs.reset
        if steps != len(actions[seed]):
            raise SystemExit(
                f"seed {seed}: {variant} ran {steps} steps, the recording {len(actions[seed])}: "
                "episodes are not reproducible"
            )
        return {variant: (w1 - w0, c1 - c0), f"{variant}_robosuite_inside": (clock.wall, clock.cpu)}

    def run_task_env(seed: int, _episode: int, _writer: Any) -> Times:
        def call() -> int:
            env.reset(seed=seed)
            for a in actions[seed]:
                env.step(a)
            return len(actions[seed])

        return in_run("task_env", call, seed)

    def run_worker(seed: int, episode: int, writer: Any) -> Times:
        def call() -> int:
            return run_episode(env, caps, policy, governor, writer, seed=seed, episode=episode).steps

        return in_run("worker", call, seed)

    runners = [run_robosuite, run_task_env, run_worker]
    names = ("robosuite_stock", "robosuite_lean", "task_env", "worker")
    inside = ("task_env_robosuite_inside", "worker_robosuite_inside")
    # per quantity, per clock: per-round totals and per-episode times
    totals: dict[str, dict[str, list[float]]] = {v: {c: [] for c in CLOCKS} for v in names + inside}
    episodes: dict[str, dict[str, list[float]]] = {v: {c: [] for c in CLOCKS} for v in names + inside}
    loads: list[float] = []
    for r in range(args.rounds):
        round_total = {v: [0.0, 0.0] for v in names + inside}
        with TraceWriter(tmp / f"worker-{r}.mcap", metadata(f"bench-{r}")) as writer:
            for i, seed in enumerate(seeds):
                k = (r + i) % len(runners)
                for runner in runners[k:] + runners[:k]:
                    for v, (wall, cpu) in runner(seed, i, writer).items():
                        round_total[v][0] += wall
                        round_total[v][1] += cpu
                        episodes[v]["wall"].append(wall)
                        episodes[v]["cpu"].append(cpu)
        for v in names + inside:
            totals[v]["wall"].append(round_total[v][0])
            totals[v]["cpu"].append(round_total[v][1])
        loads.append(os.getloadavg()[0])
        print(
            f"round {r + 1}/{args.rounds} (load {loads[-1]:.1f}), steps/s wall|cpu: "
            + ", ".join(
                f"{v} {steps_per_round / round_total[v][0]:.1f}|{steps_per_round / round_total[v][1]:.1f}"
                for v in names
            ),
            flush=True,
        )

    breakdown = component_breakdown(env, caps, policy, governor, seeds, tmp, metadata("bench-breakdown"))

    def pct(a: list[float], b: list[float]) -> list[float]:
        return [(x / y - 1.0) * 100.0 for x, y in zip(a, b, strict=True)]

    def us(a: list[float], b: list[float]) -> list[float]:
        return [(x - y) / steps_per_round * 1e6 for x, y in zip(a, b, strict=True)]

    results: dict[str, Any] = {
        "task": args.task,
        "phi": args.phi,
        "phi_hash": phi.hash,
        "label": args.label,
        "seeds": args.seeds,
        "horizon": args.horizon,
        "rounds": args.rounds,
        "steps_per_round": steps_per_round,
        "loadavg_1m_per_round": loads,
        "capevo": str(Path(capevo.__file__).resolve().parent),
        "target_overhead_pct": TARGET_OVERHEAD_PCT,
    }
    rows: list[list[Any]] = []
    inrun_rows: list[list[Any]] = []
    for clock in CLOCKS:
        tot, ep = {v: totals[v][clock] for v in totals}, {v: episodes[v][clock] for v in episodes}
        comparisons = {
            "robosuite_lean_vs_stock": ("robosuite_lean", "robosuite_stock"),
            "task_env_vs_robosuite_stock": ("task_env", "robosuite_stock"),
            "worker_vs_robosuite_stock": ("worker", "robosuite_stock"),
            "worker_vs_robosuite_lean": ("worker", "robosuite_lean"),
        }
        res: dict[str, Any] = {
            "steps_per_s": {v: _spread([steps_per_round / t for t in tot[v]]) for v in names},
            "slower_pct_per_round": {k: _spread(pct(tot[a], tot[b])) for k, (a, b) in comparisons.items()},
            "slower_pct_per_episode_pair": {k: _spread(pct(ep[a], ep[b])) for k, (a, b) in comparisons.items()},
            "extra_us_per_step_per_round": {k: _spread(us(tot[a], tot[b])) for k, (a, b) in comparisons.items()},
            # In-run: each variant against the robosuite calls made inside it (lean robosuite,
            # as TaskEnv runs it), clocked in the same episodes: no drift between the two.
            "in_run_slower_pct_per_round": {
                v: _spread(pct(tot[v], tot[f"{v}_robosuite_inside"])) for v in ("task_env", "worker")
            },
            "in_run_extra_us_per_step_per_round": {
                v: _spread(us(tot[v], tot[f"{v}_robosuite_inside"])) for v in ("task_env", "worker")
            },
        }
        results[clock] = res
        for v in names:
            rate = res["steps_per_s"][v]
            key = {"robosuite_lean": "robosuite_lean_vs_stock"}.get(v, f"{v}_vs_robosuite_stock")
            if v == "robosuite_stock":
                cells = ["—", "—"]
            else:
                o, e = res["slower_pct_per_round"][key], res["slower_pct_per_episode_pair"][key]
                cells = [
                    f"{o['median']:+.2f} % [{o['p25']:+.2f}, {o['p75']:+.2f}]",
                    f"{e['median']:+.2f} % [{e['p25']:+.2f}, {e['p75']:+.2f}]",
                ]
            rows.append([clock, v, f"{rate['median']:.1f} [{rate['min']:.1f}–{rate['max']:.1f}]", *cells])
        for v in ("task_env", "worker"):
            o, x = res["in_run_slower_pct_per_round"][v], res["in_run_extra_us_per_step_per_round"][v]
            inrun_rows.append(
                [
                    clock,
                    v,
                    f"{o['median']:+.2f} % [{o['p25']:+.2f}, {o['p75']:+.2f}]",
                    f"{x['median']:.0f} [{x['p25']:.0f}, {x['p75']:.0f}]",
                ]
            )
    results["breakdown"] = breakdown

    print()
    print(
        f"{args.task}, Φ {args.phi}, {args.seeds} seeds, {steps_per_round} steps per variant per round, "
        f"{args.rounds} rounds, load {min(loads):.1f}–{max(loads):.1f}"
    )
    print("\ninterleaved episodes (robosuite_stock / robosuite_lean: alternate steps of the same replays):")
    print(
        markdown_table(
            [
                "clock",
                "variant",
                "steps/s median [min–max]",
                "slower than robosuite_stock, per round: median [IQR]",
                "per episode pair: median [IQR]",
            ],
            rows,
        )
    )
    print("\nin-run (against the robosuite reset/step calls inside the same episodes):")
    print(markdown_table(["clock", "variant", "slower, per round: median [IQR]", "µs per step [IQR]"], inrun_rows))
    print("\nwhere a worker step's time goes (one instrumented pass; wall and CPU of the main thread):")
    print(
        markdown_table(
            ["part", "µs per env step (wall)", "µs per env step (CPU)", "share of the worker's step (wall)"],
            [
                [k, f"{v['us_per_step']:.1f}", f"{v['cpu_us_per_step']:.1f}", f"{v['share'] * 100:.2f}%"]
                for k, v in breakdown.items()
            ],
        )
    )
    path = save_results(args.out, results)
    print(f"results: {path}")
    caps.close()
    env.close()
    registry.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
