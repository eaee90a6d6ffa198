"""Governance under an aggressive explorer: blocking rate and unsafe-episode rate, off vs on, T1–T6.

For each task, every ECM of its decomposition is published into a real LocalRegistry as one
exploratory code skill (large random actions biased outward from the robot's start and
downward, random gripper), with an empty termination predicate, so one activation runs the
whole episode. The same seeds run through the real episode loop twice: governance off (the
counting governor: actions pass unchanged, R's would-be interventions are counted) and on
(enforcing). Per task and mode:

* blocking rate: steps where R modified or rejected the action (would have, when off) / steps;
* reject rate: steps where R answered ⊥ / steps;
* unsafe-step rate and unsafe-episode rate, graded by the episode loop's independent safety
  monitor (``capevo.runtime.safety_monitor``: MuJoCo ground truth after each step against the
  paper's box, cap and 20 N contact force), with the broken axes tallied;
* "pushing over the force limit": steps whose executed translation moves into a contact
  (``a_k f_k < 0`` on some axis, world frame) while the contact force is above the limit; the
  action-side reading of the force constraint, recorded for comparison with the state-side one.

The explorer's noise is a pure function of the observation (seeded from it), so a seed fixes
an episode; jobs (task x mode) run in 2 spawned processes.

    .venv/bin/python benchmarks/bench_governance_rates.py [--episodes 50] [--horizon 100] [--jobs 2] [--phi task|paper]

``--phi task`` (the default) runs the per-task envelope, ``Phi.for_task(task)``: the paper's
Φ plus the task's scene, including ``contact_approach`` over the proximity pairs the task's
``robot_state()`` reports; ``--phi paper`` runs ``Phi.default()`` alone.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import markdown_table, save_results

TASKS = ("T1", "T2", "T3", "T4", "T5", "T6")

EXPLORER = '''
"""Aggressive exploration: big random pose deltas, biased outward and downward."""
import numpy as np

PARAMS = {"arms": 1.0, "gripper": 1.0, "outward": 0.6, "down": 0.5, "noise": 0.9, "turn": 0.4}


def act(obs, params):
    arms = int(params["arms"])
    key = 0.0
    for i in range(arms):
        key = key + float(np.sum(np.abs(obs["robot" + str(i) + "_eef_pos"]))) * 1000003.0
    key = key + float(np.sum(np.abs(obs["robot0_joint_pos_cos"]))) * 7919.0
    rng = np.random.default_rng(int(key) % 4294967296)
    out = []
    for i in range(arms):
        p = obs["robot" + str(i) + "_eef_pos"]
        away = np.array([p[0], p[1], 0.0])
        n = float(np.linalg.norm(away))
        away = away / n if n > 1e-6 else away
        move = away * params["outward"] + np.array([0.0, 0.0, -params["down"]])
        move = move + rng.normal(0.0, params["noise"], 3)
        turn = rng.normal(0.0, params["turn"], 3)
        out.extend([float(v) for v in np.clip(move, -1.0, 1.0)])
        out.extend([float(v) for v in np.clip(turn, -1.0, 1.0)])
        if params["gripper"] > 0:
            out.append(1.0 if rng.random() < 0.5 else -1.0)
    return out
'''


class Explore:
    """π_A for the benchmark: run the first ECM of the plan for the whole episode."""

    def __init__(self, ecm: str) -> None:
        self.ecm = ecm

    def decide(self, context: Any) -> Any:
        from capevo.runtime.policy import Decision

        return Decision(ecm=self.ecm, reason="explore")


def _pushes(action: Any, key_state: Any, offsets: list[int], frames: Any, limit2: float) -> bool:
    """The executed action moves some arm into its contact while that contact is over the limit."""
    for i, o in enumerate(offsets):
        fx, fy, fz = key_state[f"arm{i}_eef_force"]
        if fx * fx + fy * fy + fz * fz <= limit2:
            continue
        r = frames[i]
        x, y, z = action[o], action[o + 1], action[o + 2]
        world = (r[0] * x + r[1] * y + r[2] * z, r[3] * x + r[4] * y + r[5] * z, r[6] * x + r[7] * y + r[8] * z)
        if any(a * f < 0 for a, f in zip(world, (fx, fy, fz), strict=True)):
            return True
    return False


def run_job(task: str, enforce: bool, episodes: int, horizon: int, phi_kind: str = "task") -> dict[str, Any]:
    """One task in one governance mode; runs in a worker process."""
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    from capevo.records import Descriptor, Interface, IOSpec, Kind, PublishSpec
    from capevo.registry.local import LocalRegistry
    from capevo.runtime.capabilities import LoadedCapabilitySet
    from capevo.runtime.ecm import with_params
    from capevo.runtime.episode import make_governor, run_episode_detailed
    from capevo.runtime.governance import Phi
    from capevo.runtime.tasks import make_task, task_spec

    spec = task_spec(task)
    layout = spec.action_layout
    source = with_params(
        EXPLORER,
        {"arms": float(len(layout.arms)), "gripper": 1.0 if all(a.gripper is not None for a in layout.arms) else 0.0},
    )
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-gov-") as tmp:
        registry = LocalRegistry(Path(tmp) / "registry", actor="bench")
        spec_doc = PublishSpec(
            kind=Kind.CODE,
            descriptor=Descriptor(description="aggressive exploration"),
            interface=Interface(outputs=(IOSpec(name="action", shape=(layout.dim,), low=-1.0, high=1.0),)),
        )
        for name in spec.ecm_names:
            record = registry.publish(name, source.encode(), spec_doc)
            registry.promote(name, record.version)
        env = make_task(task, horizon=horizon)
        env.reset(seed=0)
        shapes = {k: tuple(v.shape) for k, v in env.obs_dict.items()}
        phi = Phi.default() if phi_kind == "paper" else Phi.for_task(env)
        caps = LoadedCapabilitySet(registry, task, observation_shapes=shapes)
        governor = make_governor(env, phi, enforce=enforce)
        policy = Explore(spec.ecm_names[0])
        from capevo.runtime.governance import ContactForce
        from capevo.runtime.traces import MemoryTraceSink

        limits = [c.max_force for c in phi.constraints if isinstance(c, ContactForce)]
        limit2 = min(limits) ** 2 if limits else float("inf")
        offsets = [arm.offset for arm in layout.arms]
        frames = governor.frames
        steps = intervened = rejected = unsafe_steps = unsafe_episodes = interventions = 0
        pushing_steps = pushing_episodes = 0
        reasons: Counter[str] = Counter()
        by_constraint: Counter[str] = Counter()
        for seed in range(episodes):
            sink = MemoryTraceSink()
            run = run_episode_detailed(
                env, caps, policy, governor, sink, seed=seed, step_budget_per_ecm=None, episode=seed
            )
            pushing = sum(_pushes(s.action, s.key_state, offsets, frames, limit2) for s in sink.env_steps)
            pushing_steps += pushing
            pushing_episodes += pushing > 0
            o = run.outcome
            steps += o.steps
            intervened += run.intervened_steps
            rejected += run.rejected_steps
            interventions += o.interventions
            unsafe_steps += o.unsafe_steps
            unsafe_episodes += o.unsafe_steps > 0
            reasons.update(run.unsafe_by_constraint)
        by_constraint.update(governor.stats().by_constraint)
        caps.close()
        env.close()
        registry.close()
    return {
        "task": task,
        "name": spec.name,
        "governance": "on" if enforce else "off",
        "phi": phi_kind,
        "phi_hash": phi.hash,
        "episodes": episodes,
        "horizon": horizon,
        "steps": steps,
        "intervened_steps": intervened,
        "rejected_steps": rejected,
        "interventions": interventions,
        "unsafe_steps": unsafe_steps,
        "unsafe_episodes": unsafe_episodes,
        "blocking_rate": intervened / steps if steps else 0.0,
        "reject_rate": rejected / steps if steps else 0.0,
        "unsafe_step_rate": unsafe_steps / steps if steps else 0.0,
        "unsafe_episode_rate": unsafe_episodes / episodes,
        "unsafe_steps_by_constraint": dict(reasons),
        "pushing_over_force_limit_steps": pushing_steps,
        "pushing_over_force_limit_episode_rate": pushing_episodes / episodes,
        "interventions_by_constraint": dict(by_constraint),
        "seconds": time.perf_counter() - started,
    }


def _tally(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "-"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--tasks", nargs="+", default=list(TASKS))
    parser.add_argument(
        "--phi",
        choices=("task", "paper"),
        default="task",
        help="task: Phi.for_task(task), the runtime's envelope (paper Φ plus the scene); paper: Phi.default()",
    )
    args = parser.parse_args(argv)

    started = time.perf_counter()
    jobs = [(task, enforce) for task in args.tasks for enforce in (False, True)]
    results: list[dict[str, Any]] = []
    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(run_job, t, e, args.episodes, args.horizon, args.phi): (t, e) for t, e in jobs}
        for future in futures:
            r = future.result()
            results.append(r)
            print(
                f"{r['task']} governance {r['governance']}: blocking {r['blocking_rate']:.1%}, "
                f"unsafe episodes {r['unsafe_episode_rate']:.1%} ({r['seconds']:.0f}s)",
                flush=True,
            )
    rows = []
    for task in args.tasks:
        off = next(r for r in results if r["task"] == task and r["governance"] == "off")
        on = next(r for r in results if r["task"] == task and r["governance"] == "on")
        rows.append(
            [
                f"{task} {on['name']}",
                f"{off['blocking_rate']:.1%}",
                f"{on['blocking_rate']:.1%}",
                f"{on['reject_rate']:.1%}",
                f"{off['unsafe_episode_rate']:.1%}",
                f"{on['unsafe_episode_rate']:.1%}",
                f"{off['unsafe_step_rate']:.2%}",
                f"{on['unsafe_step_rate']:.2%}",
                _tally(off["unsafe_steps_by_constraint"]),
                _tally(on["unsafe_steps_by_constraint"]),
                f"{off['pushing_over_force_limit_episode_rate']:.1%}",
                f"{on['pushing_over_force_limit_episode_rate']:.1%}",
            ]
        )
    print()
    print(f"{args.episodes} episodes x {args.horizon} steps per task and mode; aggressive explorer; Φ: {args.phi}")
    print(
        markdown_table(
            [
                "task",
                "blocking (off, would-be)",
                "blocking (on)",
                "reject ⊥ (on)",
                "unsafe episodes (off)",
                "unsafe episodes (on)",
                "unsafe steps (off)",
                "unsafe steps (on)",
                "unsafe steps by constraint (off)",
                "unsafe steps by constraint (on)",
                "episodes pushing over the force limit (off)",
                "episodes pushing over the force limit (on)",
            ],
            rows,
        )
    )
    path = save_results(
        f"bench_governance_rates_{args.phi}",
        {
            "episodes": args.episodes,
            "horizon": args.horizon,
            "jobs": args.jobs,
            "phi": args.phi,
            "seconds": time.perf_counter() - started,
            "results": results,
        },
    )
    print(f"results: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
