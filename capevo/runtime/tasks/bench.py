"""Measure the tasks: build time, env steps per second, per-call cost of ``signals()`` and
``robot_state()``, and the scripted references' success rates with perturbations on and off.

Run ``python -m capevo.runtime.tasks.bench [--steps N] [--episodes N] [--json PATH]``.
Timings belong here, never in pass/fail tests.

``--phi paper task`` also runs each reference through enforcing governance, the way the episode
loop does (state before the step, R(a, Φ), hold still on ⊥, the unsafe-step metric on the
state and the executed action): ``paper`` is ``Phi.default()``, ``task`` is ``Phi.for_task``.
``--steps 0`` skips the timings; ``--references-only`` skips the ungoverned reference runs.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any

import numpy as np

from capevo.runtime.tasks.perturbations import Perturbations
from capevo.runtime.tasks.registry import make_task, task_names
from capevo.runtime.tasks.scripted import REFERENCES

WARMUP_STEPS = 30
"""Untimed steps first: robosuite's first steps in a process pay one-off compilation costs."""


def bench_task(name: str, steps: int, repeats: int = 2) -> dict[str, Any]:
    """Timings of one task with default perturbations and random actions in [-0.5, 0.5].

    Steps per second is the best of ``repeats`` timed runs: on a shared machine the best run
    is the one least disturbed by other processes.
    """
    t0 = time.perf_counter()
    env = make_task(name, seed=0)
    build_s = time.perf_counter() - t0
    try:
        rng = np.random.default_rng(0)
        t0 = time.perf_counter()
        env.reset(seed=0)
        reset_s = time.perf_counter() - t0
        for _ in range(WARMUP_STEPS):
            env.step(np.zeros(env.action_space.shape))
        step_s = math.inf
        for _ in range(repeats):
            env.reset(seed=0)
            done, n, t0 = False, 0, time.perf_counter()
            while n < steps:
                if done:
                    env.reset()
                _, _, term, trunc, _ = env.step(rng.uniform(-0.5, 0.5, env.action_space.shape))
                done = term or trunc
                n += 1
            step_s = min(step_s, (time.perf_counter() - t0) / n)
        reps = 200
        t0 = time.perf_counter()
        for _ in range(reps):
            env.signals()
        signals_us = (time.perf_counter() - t0) / reps * 1e6
        t0 = time.perf_counter()
        for _ in range(reps):
            env.robot_state()
        state_us = (time.perf_counter() - t0) / reps * 1e6
    finally:
        env.close()
    return {
        "task": name,
        "build_s": round(build_s, 3),
        "reset_ms": round(reset_s * 1e3, 2),
        "steps_per_s": round(1.0 / step_s, 1),
        "signals_us": round(signals_us, 1),
        "robot_state_us": round(state_us, 1),
    }


def bench_reference(name: str, episodes: int, perturbed: bool) -> dict[str, Any]:
    """Success rate and mean episode length of the task's scripted reference, seeds 1000.."""
    env = make_task(name, seed=0, perturbations=Perturbations() if perturbed else Perturbations.none())
    policy = REFERENCES[name]
    wins, lengths = 0, []
    try:
        for ep in range(episodes):
            env.reset(seed=1000 + ep)
            done, info = False, {}
            while not done:
                _, _, term, trunc, info = env.step(policy(env.obs_dict))
                done = term or trunc
            wins += int(info["is_success"])
            lengths.append(env.elapsed_steps)
    finally:
        env.close()
    return {
        "task": name,
        "perturbations": "on" if perturbed else "off",
        "episodes": episodes,
        "success_rate": wins / episodes,
        "mean_steps": round(float(np.mean(lengths)), 1),
    }


def run_governed(env: Any, policy: Any, phi: Any, seed: int) -> dict[str, Any]:
    """One reference episode through enforcing governance, judged by governance's own check
    (:func:`~capevo.runtime.governance.unsafe_reasons`; the episode loop's grader is the
    independent safety monitor).

    Returns success, steps, unsafe steps (by constraint) and interventions (by constraint).
    """
    from collections import Counter

    from capevo.runtime.episode import make_governor
    from capevo.runtime.governance import hold_action, unsafe_reasons

    governor = make_governor(env, phi)
    layout = env.task_spec.action_layout
    env.reset(seed=seed)
    done, info, last = False, {"is_success": False}, None
    unsafe = 0
    unsafe_by: Counter[str] = Counter()
    interventions: Counter[str] = Counter()
    while not done:
        action = policy(env.obs_dict)
        state = env.robot_state()
        governed, ivs = governor(state, action)
        # Plain floats, as the episode loop sends them (the allow path returns the policy's array).
        executed = hold_action(layout, last) if governed is None else tuple(float(v) for v in governed)
        interventions.update(iv.constraint for iv in ivs)
        why = unsafe_reasons(state, executed, phi, layout)
        if why:
            unsafe += 1
            unsafe_by.update(w.split(":", 1)[0] for w in why)
        last = executed
        _, _, term, trunc, info = env.step(np.asarray(executed, dtype=np.float64))
        done = term or trunc
    final = unsafe_reasons(env.robot_state(), None, phi, layout)
    if final:
        unsafe += 1
        unsafe_by.update(w.split(":", 1)[0] for w in final)
    return {
        "seed": seed,
        "success": bool(info["is_success"]),
        "steps": env.elapsed_steps,
        "unsafe_steps": unsafe,
        "unsafe_by_constraint": dict(unsafe_by),
        "interventions_by_constraint": dict(interventions),
    }


def bench_reference_governed(name: str, episodes: int, phi_kind: str, perturbed: bool = True) -> dict[str, Any]:
    """A reference under enforcing governance (``paper``: ``Phi.default()``; ``task``: ``Phi.for_task``),
    seeds 1000.."""
    from capevo.runtime.governance import Phi

    env = make_task(name, seed=0, perturbations=Perturbations() if perturbed else Perturbations.none())
    phi = Phi.default() if phi_kind == "paper" else Phi.for_task(name)
    try:
        runs = [run_governed(env, REFERENCES[name], phi, 1000 + ep) for ep in range(episodes)]
    finally:
        env.close()
    wins = [r for r in runs if r["success"]]
    return {
        "task": name,
        "phi": phi_kind,
        "perturbations": "on" if perturbed else "off",
        "episodes": episodes,
        "successes": len(wins),
        "mean_steps_success": round(float(np.mean([r["steps"] for r in wins])), 1) if wins else None,
        "unsafe_steps": sum(r["unsafe_steps"] for r in runs),
        "unsafe_episodes": sum(r["unsafe_steps"] > 0 for r in runs),
        "failed_seeds": [r["seed"] for r in runs if not r["success"]],
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run every measurement and print one line per result; optionally write JSON."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=300, help="env steps timed per task")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per scripted reference and setting")
    parser.add_argument("--json", default=None, help="write the results here")
    parser.add_argument("--tasks", nargs="*", default=None, help="subset of task names")
    parser.add_argument(
        "--phi", nargs="*", default=[], choices=("paper", "task"), help="also run the references under these Φ"
    )
    parser.add_argument("--references-only", action="store_true", help="skip the ungoverned reference runs")
    args = parser.parse_args(argv)
    names = args.tasks or list(task_names())
    results: dict[str, Any] = {"tasks": [], "references": [], "governed_references": []}
    for name in names if args.steps > 0 else ():
        r = bench_task(name, args.steps)
        results["tasks"].append(r)
        print(json.dumps(r), flush=True)
    for name in names:
        if name not in REFERENCES or args.episodes <= 0:
            continue
        for perturbed in () if args.references_only else (False, True):
            r = bench_reference(name, args.episodes, perturbed)
            results["references"].append(r)
            print(json.dumps(r), flush=True)
        for phi_kind in args.phi:
            r = bench_reference_governed(name, args.episodes, phi_kind)
            results["governed_references"].append(r)
            print(json.dumps(r), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
    return results


if __name__ == "__main__":
    main()
