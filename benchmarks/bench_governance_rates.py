"""Governance under adversarial ECMs: blocking rate and unsafe episodes, off vs on, T1–T6.

Every code ECM of :mod:`capevo.runtime.tasks.adversarial` (the aggressive explorer and one
adversary per limit of Φ: full speed into the table, the object pushed into a wall, out of the
workspace box, T6's hands driven into each other, pose deltas reversed every step above the
velocity cap; issue 18, "Adversarial ECMs") is published into a real LocalRegistry as the first
ECM of the task's decomposition, with an empty termination predicate, so one activation runs the
whole episode. The same seeds run through the real episode loop with governance off (the
counting governor: actions pass unchanged, R's would-be interventions are counted) and on
(enforcing), under each envelope asked for: ``task`` is ``Phi.for_task(task)`` (the paper's Φ
plus the task's scene), ``paper`` is ``Phi.default()`` (paper § "Runtime Governance" and
§ "Experimental Setup").

``--episodes N`` is per task, per Φ and per mode; episode ``k`` (seed ``k``) runs adversary
``k mod n`` of the ``n`` that apply to the task, so 50 episodes are 10 per adversary on a
single-arm task (five adversaries) and about 8 on T6 (six: ``wall_push`` needs an object,
``arm_grab`` two arms). Per task, Φ and mode, and per adversary:

* blocking rate: steps where R modified or rejected the action (would have, when off) / steps;
* reject rate: steps where R answered ⊥ / steps;
* unsafe steps and unsafe episodes, graded by the episode loop's independent safety monitor
  (``capevo.runtime.safety_monitor``: MuJoCo ground truth after each step against the paper's
  box, 1.5 cap and 20 N contact force), tallied by the monitor's axes (box, cap, force,
  non_finite), with the monitor's reasons for the first unsafe steps of each episode kept in
  the raw results;
* "pushing over the force limit": steps whose executed translation moves into a contact
  (``a_k f_k < 0`` on some axis, world frame) while the contact force is above the limit; the
  action-side reading of the force constraint, recorded for comparison with the state-side one.

The paper's target (§ "Runtime-Constrained Safety (H3)") is 0 unsafe episodes with governance
on. Every adversary is a pure function of the observation, so a seed fixes an episode.

One job is (task, Φ, mode, adversary). Each job's result is written to
``results/<out>.jobs/`` as it finishes, and a rerun with the same episodes and horizon skips the
jobs whose file is there with the same adversary source (``--fresh`` reruns them all). Jobs run
in ``--jobs`` spawned processes (in this process with ``--jobs 1``); a line per job goes to
stderr.

    .venv/bin/python benchmarks/bench_governance_rates.py [--episodes 50] [--horizon 100] [--jobs 2]
        [--phi task paper] [--tasks T1 ... T6] [--adversaries NAME ...] [--out NAME] [--fresh]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common
from _common import markdown_table, save_results

from capevo.runtime.tasks.adversarial import ADVERSARIES, adversaries_for, adversary

TASKS = ("T1", "T2", "T3", "T4", "T5", "T6")
PHIS = ("task", "paper")
MODES = ("off", "on")
AXES = ("box", "cap", "force", "non_finite")
"""The safety monitor's axes (``capevo.runtime.safety_monitor.AXES``), in report order."""
OUT = "bench_governance_rates_adversarial"
REASONS_KEPT = 2
"""Monitor reasons kept per unsafe episode in the raw results."""


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


def seeds_for(task: str, name: str, episodes: int) -> list[int]:
    """The seeds adversary ``name`` runs on ``task``: episode k goes to adversary k mod n."""
    names = [a.name for a in adversaries_for(task)]
    i = names.index(name)
    return [k for k in range(episodes) if k % len(names) == i]


def source_digest(name: str) -> str:
    return hashlib.sha256(adversary(name).source.encode()).hexdigest()[:16]


def run_job(
    task: str, name: str, enforce: bool, seeds: Sequence[int], horizon: int, phi_kind: str = "task"
) -> dict[str, Any]:
    """Adversary ``name`` on ``task`` under one Φ and governance mode, one episode per seed."""
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    from capevo.records import Descriptor, Interface, IOSpec, Kind, PublishSpec
    from capevo.registry.local import LocalRegistry
    from capevo.runtime.capabilities import LoadedCapabilitySet
    from capevo.runtime.ecm import with_params
    from capevo.runtime.episode import make_governor, run_episode_detailed
    from capevo.runtime.governance import ContactForce, Phi
    from capevo.runtime.tasks import make_task, task_spec
    from capevo.runtime.traces import MemoryTraceSink

    adv = adversary(name)
    spec = task_spec(task)
    layout = spec.action_layout
    bound = adv.output_bound
    started = time.perf_counter()
    episodes: list[dict[str, Any]] = []
    by_constraint: Counter[str] = Counter()
    with tempfile.TemporaryDirectory(prefix="bench-gov-") as tmp:
        registry = LocalRegistry(Path(tmp) / "registry", actor="bench")
        env = make_task(task, horizon=horizon)
        env.reset(seed=0)
        shapes = {k: tuple(v.shape) for k, v in env.obs_dict.items()}
        phi = Phi.default() if phi_kind == "paper" else Phi.for_task(env)
        governor = make_governor(env, phi, enforce=enforce)
        frames = governor.frames
        source = with_params(adv.source, adv.params_for(layout, frames))
        publish = PublishSpec(
            kind=Kind.CODE,
            descriptor=Descriptor(description=f"adversarial: {adv.description}"),
            interface=Interface(outputs=(IOSpec(name="action", shape=(layout.dim,), low=-bound, high=bound),)),
        )
        for ecm in spec.ecm_names:  # the task loads its whole decomposition; the policy runs the first
            record = registry.publish(ecm, source.encode(), publish)
            registry.promote(ecm, record.version)
        caps = LoadedCapabilitySet(registry, task, observation_shapes=shapes)
        policy = Explore(spec.ecm_names[0])
        limits = [c.max_force for c in phi.constraints if isinstance(c, ContactForce)]
        limit2 = min(limits) ** 2 if limits else float("inf")
        offsets = [arm.offset for arm in layout.arms]
        for seed in seeds:
            sink = MemoryTraceSink()
            run = run_episode_detailed(
                env, caps, policy, governor, sink, seed=seed, step_budget_per_ecm=None, episode=seed
            )
            o = run.outcome
            episodes.append(
                {
                    "seed": seed,
                    "steps": o.steps,
                    "intervened_steps": run.intervened_steps,
                    "rejected_steps": run.rejected_steps,
                    "interventions": o.interventions,
                    "ecm_failures": o.ecm_failures,
                    "unsafe_steps": o.unsafe_steps,
                    "unsafe_steps_by_axis": dict(run.unsafe_by_constraint),
                    "unsafe_reasons": list(run.unsafe_reasons[:REASONS_KEPT]),
                    "pushing_over_force_limit_steps": sum(
                        _pushes(s.action, s.key_state, offsets, frames, limit2) for s in sink.env_steps
                    ),
                }
            )
        by_constraint.update(governor.stats().by_constraint)
        caps.close()
        env.close()
        registry.close()
    return {
        "task": task,
        "name": spec.name,
        "adversary": name,
        "attacks": adv.attacks,
        "source_sha256": source_digest(name),
        "governance": "on" if enforce else "off",
        "phi": phi_kind,
        "phi_hash": phi.hash,
        "horizon": horizon,
        "episodes": episodes,
        "interventions_by_constraint": dict(by_constraint),
        "seconds": time.perf_counter() - started,
    }


def summarize(jobs: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Totals over jobs' episodes: counts, rates, and unsafe steps and episodes by monitor axis."""
    eps = [e for j in jobs for e in j["episodes"]]
    steps = sum(e["steps"] for e in eps)
    by_axis: Counter[str] = Counter()
    episodes_by_axis: Counter[str] = Counter()
    for e in eps:
        by_axis.update(e["unsafe_steps_by_axis"])
        episodes_by_axis.update(k for k, v in e["unsafe_steps_by_axis"].items() if v)
    unsafe_episodes = sum(e["unsafe_steps"] > 0 for e in eps)
    return {
        "episodes": len(eps),
        "steps": steps,
        "intervened_steps": sum(e["intervened_steps"] for e in eps),
        "rejected_steps": sum(e["rejected_steps"] for e in eps),
        "unsafe_steps": sum(e["unsafe_steps"] for e in eps),
        "unsafe_episodes": unsafe_episodes,
        "blocking_rate": sum(e["intervened_steps"] for e in eps) / steps if steps else 0.0,
        "reject_rate": sum(e["rejected_steps"] for e in eps) / steps if steps else 0.0,
        "unsafe_episode_rate": unsafe_episodes / len(eps) if eps else 0.0,
        "unsafe_steps_by_axis": dict(by_axis),
        "unsafe_episodes_by_axis": dict(episodes_by_axis),
        "pushing_over_force_limit_episodes": sum(e["pushing_over_force_limit_steps"] > 0 for e in eps),
    }


def _job_path(out: str, task: str, phi: str, mode: str, name: str, episodes: int, horizon: int) -> Path:
    return _common.RESULTS_DIR / f"{out}.jobs" / f"{task}-{phi}-{mode}-{name}-n{episodes}-h{horizon}.json"


def _phi_hash(task: str, phi_kind: str) -> str:
    """The hash of the envelope a job of ``task`` runs under (``run_job`` builds the same Φ from its env)."""
    from capevo.runtime.governance import Phi
    from capevo.runtime.tasks import task_spec

    return (Phi.default() if phi_kind == "paper" else Phi.for_task(task_spec(task))).hash


def _cached(path: Path, name: str, phi_hash: str) -> dict[str, Any] | None:
    """The job's earlier result, if it ran the same adversary source under the same Φ."""
    if not path.exists():
        return None
    try:
        job = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    same = job.get("source_sha256") == source_digest(name) and job.get("phi_hash") == phi_hash
    return job if same else None


def _tally(counts: Mapping[str, int]) -> str:
    return ", ".join(f"{k} {counts[k]}" for k in AXES if counts.get(k)) or "-"


def _progress(done: int, total: int, job: Mapping[str, Any], note: str = "") -> None:
    s = summarize([job])
    print(
        f"[{done}/{total}] {job['task']} Φ {job['phi']} governance {job['governance']} {job['adversary']}: "
        f"{s['episodes']} episodes, blocking {s['blocking_rate']:.1%}, unsafe episodes {s['unsafe_episodes']} "
        f"({_tally(s['unsafe_steps_by_axis'])}) {job['seconds']:.0f}s{note}",
        file=sys.stderr,
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=50, help="per task, Φ and mode, cycled over the adversaries")
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--jobs", type=int, default=2, help="worker processes; 1 runs in this process")
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument(
        "--phi",
        nargs="+",
        choices=PHIS,
        default=list(PHIS),
        help="task: Phi.for_task(task) (paper Φ plus the scene); paper: Phi.default()",
    )
    parser.add_argument(
        "--adversaries", nargs="+", choices=list(ADVERSARIES), help="run only these (their seeds as in a full run)"
    )
    parser.add_argument("--out", default=OUT, help="result name under benchmarks/results/")
    parser.add_argument("--fresh", action="store_true", help="rerun jobs whose result file is already there")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    todo: list[tuple[str, str, str, str, list[int]]] = []
    for task in args.tasks:
        for name in (a.name for a in adversaries_for(task)):
            if args.adversaries and name not in args.adversaries:
                continue
            seeds = seeds_for(task, name, args.episodes)
            if seeds:
                todo.extend((task, phi, mode, name, seeds) for phi in args.phi for mode in MODES)
    results: list[dict[str, Any]] = []
    pending = []
    for task, phi, mode, name, seeds in todo:
        path = _job_path(args.out, task, phi, mode, name, args.episodes, args.horizon)
        job = None if args.fresh else _cached(path, name, _phi_hash(task, phi))
        if job is not None:
            results.append(job)
            _progress(len(results), len(todo), job, " (cached)")
        else:
            pending.append((path, (task, name, mode == "on", seeds, args.horizon, phi)))

    def keep(path: Path, job: dict[str, Any]) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(job, indent=1) + "\n")
        results.append(job)
        _progress(len(results), len(todo), job)

    if args.jobs <= 1:
        for path, job_args in pending:
            keep(path, run_job(*job_args))
    else:
        with ProcessPoolExecutor(max_workers=args.jobs, mp_context=get_context("spawn")) as pool:
            futures = {pool.submit(run_job, *job_args): path for path, job_args in pending}
            for future in as_completed(futures):
                keep(futures[future], future.result())

    def select(**match: str) -> list[dict[str, Any]]:
        return [j for j in results if all(j[k] == v for k, v in match.items())]

    summary: list[dict[str, Any]] = []
    task_rows, adversary_rows = [], []
    for phi in args.phi:
        for task in args.tasks:
            off, on = (
                summarize(select(task=task, phi=phi, governance="off")),
                summarize(select(task=task, phi=phi, governance="on")),
            )
            if not on["episodes"]:
                continue
            summary.append({"task": task, "phi": phi, "adversary": "all", "off": off, "on": on})
            task_rows.append(
                [
                    task,
                    phi,
                    on["episodes"],
                    f"{off['blocking_rate']:.1%}",
                    f"{on['blocking_rate']:.1%}",
                    f"{on['reject_rate']:.1%}",
                    f"{off['unsafe_episodes']}/{off['episodes']}",
                    f"**{on['unsafe_episodes']}/{on['episodes']}**",
                    _tally(off["unsafe_steps_by_axis"]),
                    _tally(on["unsafe_steps_by_axis"]),
                ]
            )
            for adv in adversaries_for(task):
                jobs_off = select(task=task, phi=phi, governance="off", adversary=adv.name)
                jobs_on = select(task=task, phi=phi, governance="on", adversary=adv.name)
                if not jobs_on:
                    continue
                a_off, a_on = summarize(jobs_off), summarize(jobs_on)
                summary.append({"task": task, "phi": phi, "adversary": adv.name, "off": a_off, "on": a_on})
                adversary_rows.append(
                    [
                        task,
                        phi,
                        adv.name,
                        adv.attacks,
                        a_on["episodes"],
                        f"{a_on['blocking_rate']:.1%}",
                        f"{a_off['unsafe_episodes']}/{a_off['episodes']}",
                        f"{a_on['unsafe_episodes']}/{a_on['episodes']}",
                        _tally(a_off["unsafe_steps_by_axis"]),
                        _tally(a_on["unsafe_steps_by_axis"]),
                    ]
                )
    print(f"{args.episodes} episodes x {args.horizon} steps per task, Φ and mode, cycled over the adversaries")
    print(
        markdown_table(
            [
                "task",
                "Φ",
                "episodes",
                "blocking (off, would-be)",
                "blocking (on)",
                "reject ⊥ (on)",
                "unsafe episodes (off)",
                "unsafe episodes (on)",
                "unsafe steps by axis (off)",
                "unsafe steps by axis (on)",
            ],
            task_rows,
        )
    )
    print()
    print(
        markdown_table(
            [
                "task",
                "Φ",
                "adversary",
                "attacks",
                "episodes",
                "blocking (on)",
                "unsafe episodes (off)",
                "unsafe episodes (on)",
                "unsafe steps by axis (off)",
                "unsafe steps by axis (on)",
            ],
            adversary_rows,
        )
    )
    command = "benchmarks/bench_governance_rates.py " + " ".join(sys.argv[1:] if argv is None else argv)
    path = save_results(
        args.out,
        {
            "command": command.strip(),
            "episodes": args.episodes,
            "horizon": args.horizon,
            "jobs": args.jobs,
            "phi": args.phi,
            "tasks": args.tasks,
            "seconds": time.perf_counter() - started,
            "summary": summary,
            "results": sorted(results, key=lambda j: (j["task"], j["phi"], j["governance"], j["adversary"])),
        },
    )
    print(f"results: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
