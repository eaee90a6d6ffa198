"""Governance overhead per action: p50/p99 for allow and modify paths, 7-dim and 12-dim, vs one env step.

Run::

    .venv/bin/python benchmarks/bench_governance.py                 # writes benchmarks/results/governance.json
    .venv/bin/python benchmarks/bench_governance.py --n 200000 --out /tmp/gov.json --env-steps 300

Cases named ``task_phi_*`` time ``Phi.for_task(task)`` (: the paper's
envelope plus the speed-and-separation rules) on orientation-carrying states; the targets apply
to the paper's Φ. Cases named ``task_phi_*/live_*`` govern states read from a real task
environment (``TaskEnv.robot_state()``, with the proximity pairs ``contact_approach`` reads),
with the hand near the bin floor and the can (T1), over the cubes (T3), or the two hands close
(T6). ``--env-steps`` also times ``TaskEnv.robot_state()`` itself and the proximity sensor's share
of it in those states (``proximity``): the task's cost of producing the state.

Each call is timed on its own with ``time.perf_counter_ns`` (the timer's own cost, reported
as ``timer_ns``, is included, so figures are slightly pessimistic). The garbage collector
stays on. The env step is a robosuite step with the BASIC (OSC_POSE) controller, headless;
``pct_of_env_step`` is governance p50 / env-step p50. Reading the state from robosuite
(:func:`capevo.runtime.governance.robosuite_state.robot_state`) is timed separately: it
is the task's cost of producing the state, not governance's.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
import timeit
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from capevo.runtime.governance import TWO_ARM_NO_GRIPPER, ArmPose, Phi
from capevo.runtime.state import SINGLE_PANDA, ArmState, RobotState

TARGET_P50_MS = 0.005
TARGET_PCT_OF_STEP = 0.1


def _arm(pos: tuple[float, float, float], force: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> ArmState:
    return ArmState(eef_pos=pos, eef_force=force)


def _percentiles(samples_ns: list[int]) -> dict[str, float]:
    xs = sorted(samples_ns)
    n = len(xs)

    def q(p: float) -> float:
        return xs[min(n - 1, math.ceil(p * n) - 1)] / 1e6

    return {"p50_ms": q(0.50), "p99_ms": q(0.99), "mean_ms": statistics.fmean(xs) / 1e6, "n": n}


def _time_calls(fn: Callable[[], Any], n: int, warmup: int, batches: int = 0) -> dict[str, float]:
    for _ in range(warmup):
        fn()
    clock = time.perf_counter_ns
    samples = [0] * n
    for i in range(n):
        t0 = clock()
        fn()
        samples[i] = clock() - t0
    out = _percentiles(samples)
    if batches:
        # The fastest of many 1000-call batches: the cost when no other process competes for the core.
        best = min(timeit.repeat(fn, number=1000, repeat=batches)) / 1000
        out["best_batch_mean_ms"] = best * 1e3
    return out


def _timer_overhead_ns(n: int) -> float:
    clock = time.perf_counter_ns
    xs = []
    for _ in range(n):
        t0 = clock()
        xs.append(clock() - t0)
    return statistics.median(xs)


def _numpy_reference(phi: Phi) -> Callable[[Any, np.ndarray], np.ndarray]:
    """A straightforward numpy box-and-cap check on one arm, for comparison only."""
    box = phi.constraints[0]
    lo = np.array(box.low) + box.margin
    hi = np.array(box.high) - box.margin

    def govern(state: RobotState, action: np.ndarray) -> np.ndarray:
        a = np.array(action, dtype=np.float64)
        p = np.array(state.arms[0].eef_pos)
        a[:3] = np.where((p >= hi) & (a[:3] > 0) | (p <= lo) & (a[:3] < 0), 0.0, a[:3])
        n = np.linalg.norm(a[:6])
        if n > 1.5:
            a[:6] *= 1.5 / n
        return a

    return govern


def governance_cases(phi: Phi) -> dict[str, tuple[Callable[..., Any], Any, Any]]:
    inside = RobotState(arms=(_arm((0.0, 0.0, 1.0)),))
    near_face = RobotState(arms=(_arm((0.55, 0.0, 1.0), (0.0, 0.0, 35.0)),))
    calm = np.array([0.2, -0.1, 0.3, 0.05, 0.0, -0.05, 1.0])
    out_fast = np.array([1.0, 0.4, -1.0, 1.0, 1.0, 0.5, 1.0])  # box + force + cap all act
    inside2 = RobotState(arms=(_arm((0.0, -0.2, 1.0)), _arm((0.0, 0.2, 1.0))))
    near2 = RobotState(arms=(_arm((0.55, -0.2, 1.0), (0.0, 0.0, 35.0)), _arm((0.0, 0.56, 1.25))))
    calm2 = np.concatenate([calm[:6], calm[:6]])
    out2 = np.concatenate([out_fast[:6], [0.0, 1.0, 1.0, 1.2, 1.2, 0.0]])
    g7 = phi.governor(SINGLE_PANDA)
    g12 = phi.governor(TWO_ARM_NO_GRIPPER)
    g7_off = phi.governor(SINGLE_PANDA, enforce=False)
    calm_t = tuple(calm.tolist())
    inside_margin = RobotState(arms=(_arm((0.55, 0.0, 1.0)),))
    outward = np.array([0.5, 0.2, 0.1, 0.0, 0.0, 0.1, 1.0])
    assert len(g7(inside_margin, outward)[1]) == 1
    nan7 = calm.copy()
    nan7[1] = np.nan
    assert g7(inside, calm)[1] == () and g12(inside2, calm2)[1] == ()
    assert len(g7(near_face, out_fast)[1]) == 3 and len(g12(near2, out2)[1]) == 3
    # The per-task Φ (paper's envelope + speed-and-separation rules), on states with orientation,
    # as TaskEnv.robot_state() produces them. "high": the hand at carrying height (inside the
    # guard's braking band and the bins' range, so several checks take their slow path);
    # "work": over the bins at grasp height.
    down = (-0.012, 0.989, 0.148, 1.0, 0.01, 0.012, 0.011, 0.148, -0.989)
    t1 = Phi.for_task("pick")  # T1
    gt = t1.governor(SINGLE_PANDA)
    high = RobotState(arms=(ArmPose(eef_pos=(-0.15, -0.1, 1.15), eef_force=(0.0, 0.0, 0.0), eef_rot=down),))
    work = RobotState(arms=(ArmPose(eef_pos=(0.1, -0.25, 0.9), eef_force=(0.0, 0.0, 0.0), eef_rot=down),))
    assert gt(high, calm)[1] == ()
    t6 = Phi.for_task("peg_in_hole")  # T6
    g6 = t6.governor(TWO_ARM_NO_GRIPPER)
    apart = RobotState(
        arms=(
            ArmPose(eef_pos=(0.0, -0.3, 1.1), eef_force=(0.0, 0.0, 0.0), eef_rot=down),
            ArmPose(eef_pos=(0.0, 0.3, 1.1), eef_force=(0.0, 0.0, 0.0), eef_rot=down),
        )
    )
    return {
        "single_arm_7d/allow/numpy": (g7, inside, calm),
        "single_arm_7d/allow/tuple": (g7, inside, calm_t),
        "single_arm_7d/modify(box)": (g7, inside_margin, outward),
        "single_arm_7d/modify(box+force+cap)": (g7, near_face, out_fast),
        "single_arm_7d/reject(nan)": (g7, inside, nan7),
        "single_arm_7d/governance_off/modify": (g7_off, near_face, out_fast),
        "two_arm_12d/allow/numpy": (g12, inside2, calm2),
        "two_arm_12d/modify(box+force+cap)": (g12, near2, out2),
        "task_phi_T1_7d/high/numpy": (gt, high, calm),
        "task_phi_T1_7d/work/numpy": (gt, work, calm),
        "task_phi_T6_12d/apart/numpy": (g6, apart, calm2),
        "reference_numpy_box_cap_7d": (_numpy_reference(phi), inside, calm),
    }


def live_states() -> dict[str, tuple[Any, Any, Any]]:
    """Real task states with proximity pairs: ``{name: (env, state, action)}``; the envs stay open."""
    import logging

    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    from capevo.runtime.tasks import Perturbations, make_task

    out: dict[str, tuple[Any, Any, Any]] = {}
    quiet = Perturbations.none()
    # (task, steps of a scripted approach: move towards target offset, then hold)
    for task, target_key, offset, steps in (
        ("T1", "Can_pos", (0.0, 0.0, 0.06), 40),
        ("T3", "cubeA_pos", (0.0, 0.0, 0.05), 30),
    ):
        env = make_task(task, seed=0, perturbations=quiet, terminate_on_success=False, horizon=100_000)
        env.reset(seed=0)
        for _ in range(steps):
            obs = env.obs_dict
            err = np.asarray(obs[target_key], dtype=np.float64) + np.array(offset) - obs["robot0_eef_pos"]
            env.step(np.array([*np.clip(err * 10.0, -1, 1), 0.0, 0.0, 0.0, -1.0]))
        state = env.robot_state()
        out[f"task_phi_{task}_7d/live_near_object/numpy"] = (
            env,
            state,
            np.array([0.3, -0.2, -1.0, 0.1, 0.0, 0.0, 1.0]),
        )
    env = make_task("T6", seed=0, perturbations=quiet, terminate_on_success=False, horizon=100_000)
    env.reset(seed=0)
    for _ in range(25):
        env.step(np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0] * 2))  # each arm towards the other (own frames)
    out["task_phi_T6_12d/live_hands_close/numpy"] = (env, env.robot_state(), np.array([0.0, 1.0, -0.3, 0.2, 0, 0] * 2))
    return out


def env_step_times(task: str, robots: str | list[str], steps: int) -> dict[str, Any]:
    import robosuite as suite
    from robosuite.controllers import load_composite_controller_config

    from capevo.runtime.governance.robosuite_state import robot_state

    env = suite.make(
        task,
        robots=robots,
        controller_configs=load_composite_controller_config(controller="BASIC", robot="Panda"),
        has_renderer=False,
        has_offscreen_renderer=False,
        use_camera_obs=False,
        ignore_done=True,
        horizon=100_000,
        control_freq=20,
    )
    env.reset()
    zero = np.zeros(env.action_dim)
    for _ in range(10):
        env.step(zero)
    step = _time_calls(lambda: env.step(zero), steps, 0)
    read = _time_calls(lambda: robot_state(env.robots), max(steps, 2000), 100)
    env.close()
    return {"env_step": step, "robot_state_read": read}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000, help="timed calls per governance case")
    ap.add_argument("--env-steps", type=int, default=300, help="timed env steps per task (0: skip robosuite)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "governance.json")
    args = ap.parse_args(argv)

    phi = Phi.default()
    results: dict[str, Any] = {
        "phi_hash": phi.hash,
        "python": sys.version.split()[0],
        "machine": platform.machine(),
        "processor": platform.processor() or platform.platform(),
        "timer_ns": _timer_overhead_ns(100_000),
        "load_average_1_5_15": list(os.getloadavg()),
        "cpus": os.cpu_count(),
        "n_per_case": args.n,
        "cases": {},
    }
    for name, (fn, state, action) in governance_cases(phi).items():
        results["cases"][name] = _time_calls(
            lambda fn=fn, s=state, a=action: fn(s, a), args.n, min(args.n, 20_000), batches=200
        )

    live = live_states()
    for name, (env, state, action) in live.items():
        govern = Phi.for_task(env).governor(env.task_spec.action_layout)
        results["cases"][name] = _time_calls(
            lambda g=govern, s=state, a=action: g(s, a), args.n, min(args.n, 20_000), batches=200
        )
        results["cases"][name]["pairs"] = [len(getattr(arm, "near", ())) for arm in state.arms]
    if args.env_steps:
        results["task_state_read"] = {}
        for name, (env, _, _) in live.items():
            task = name.split("_")[2]
            sensor = env._proximity
            arms = range(len(env.robosuite_env.robots))
            results["task_state_read"][task] = {
                "robot_state": _time_calls(env.robot_state, 5000, 500),
                "proximity": _time_calls(lambda s=sensor, arms=arms: [s.near(i) for i in arms], 5000, 500),
                "env_step": _time_calls(lambda e=env: e.step(np.zeros(e.action_space.shape)), args.env_steps, 0),
            }
    for env, _, _ in live.values():
        env.close()

    if args.env_steps:
        results["env"] = {
            "Lift/Panda (7d)": env_step_times("Lift", "Panda", args.env_steps),
            "TwoArmPegInHole/2xPanda (12d)": env_step_times("TwoArmPegInHole", ["Panda", "Panda"], args.env_steps),
        }
        step7 = results["env"]["Lift/Panda (7d)"]["env_step"]["p50_ms"]
        step12 = results["env"]["TwoArmPegInHole/2xPanda (12d)"]["env_step"]["p50_ms"]
        for name, r in results["cases"].items():
            two = name.startswith(("two_arm", "task_phi_T6"))
            r["pct_of_env_step"] = 100.0 * r["p50_ms"] / (step12 if two else step7)

    # The targets are the paper's Φ's; the per-task Φ's figures are reported beside them.
    governed = {k: v for k, v in results["cases"].items() if not k.startswith(("reference", "task_phi"))}
    results["meets_p50_target"] = all(r["p50_ms"] <= TARGET_P50_MS for r in governed.values())
    if args.env_steps:
        results["meets_pct_target"] = all(r["pct_of_env_step"] < TARGET_PCT_OF_STEP for r in governed.values())

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")

    load = ", ".join(f"{x:.1f}" for x in results["load_average_1_5_15"])
    print(
        f"Φ {phi.hash[:12]}…, python {results['python']}, timer overhead {results['timer_ns']:.0f} ns/call, "
        f"load average {load} on {results['cpus']} CPUs\n"
    )
    print("| case | p50 (ms) | p99 (ms) | mean (ms) | best 1000-call batch (ms/call) | % of env step (p50) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, r in results["cases"].items():
        pct = f"{r['pct_of_env_step']:.4f}%" if "pct_of_env_step" in r else "n/a"
        print(
            f"| {name} | {r['p50_ms']:.5f} | {r['p99_ms']:.5f} | {r['mean_ms']:.5f} "
            f"| {r['best_batch_mean_ms']:.5f} | {pct} |"
        )
    if args.env_steps:
        print()
        print("| robosuite | env.step p50 (ms) | env.step p99 (ms) | robot_state() read p50 (ms) |")
        print("|---|---:|---:|---:|")
        for name, r in results["env"].items():
            s, rd = r["env_step"], r["robot_state_read"]
            print(f"| {name} | {s['p50_ms']:.3f} | {s['p99_ms']:.3f} | {rd['p50_ms']:.5f} |")
    if "task_state_read" in results:
        print()
        print("| task (live state) | TaskEnv.step p50 (ms) | robot_state() p50 / p99 (ms) | proximity p50 / p99 (ms) |")
        print("|---|---:|---:|---:|")
        for task, r in results["task_state_read"].items():
            rs, px, st = r["robot_state"], r["proximity"], r["env_step"]
            print(
                f"| {task} | {st['p50_ms']:.3f} | {rs['p50_ms']:.4f} / {rs['p99_ms']:.4f} "
                f"| {px['p50_ms']:.4f} / {px['p99_ms']:.4f} |"
            )
    print(f"\ntargets: p50 <= {TARGET_P50_MS} ms: {results['meets_p50_target']}", end="")
    if args.env_steps:
        print(f"; < {TARGET_PCT_OF_STEP}% of an env step: {results['meets_pct_target']}")
    else:
        print()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
