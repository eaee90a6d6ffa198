"""Does DAgger make behaviour-cloned T1 skills compose? (issue 19, modality ``il``)

The ``il`` modality clones random-init neural ECMs from the task's scripted reference and the
set's own successful traces (:class:`capevo.learner.bc.BcLearner`). On T1 its three seed plans
ended at 27, 20 and 15 of 30 held-out (``results/evolution/T1-il``). This script takes the loop
out of the question: in a scratch registry with the random-init v0 of every T1 ECM, it clones
``pick.reach``, ``pick.grasp`` and ``pick.lift`` one after another, promoting each before the next
is cloned (so each learns from the states its cloned predecessor leaves, as in the loop), and
evaluates the composed set on 30 episodes of seeds 600000–600029, which no seed plan uses.

``--rounds R`` adds R rounds of DAgger (Ross, Gordon & Bagnell 2011) to each clone: the clone
acts for ``--episodes`` episodes in the ECM's training environment, the scripted reference labels
every observation it visited, and the clone is fitted again on everything so far. Everything else
is the ``cpu-small`` preset (20 scripted demonstration episodes, 200 epochs), the default
envelope and the paper's perturbations, as ``capevo evolve --modality il`` uses them.

    .venv/bin/python benchmarks/diag_bc_dagger.py --rounds 0
    .venv/bin/python benchmarks/diag_bc_dagger.py --rounds 3 --episodes 10
    .venv/bin/python benchmarks/diag_bc_dagger.py --rounds 0 --scripted 50   # as many episodes, no DAgger

Each run appends one row to ``benchmarks/results/bc_dagger.json`` and prints it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common

FIRST_SEED = 600_000


def run(
    rounds: int,
    episodes: int,
    work: Path,
    *,
    preset_name: str = "cpu-small",
    eval_episodes: int = 30,
    seed: int = 0,
    scripted: int | None = None,
) -> dict[str, Any]:
    import torch

    from capevo.agent import DecompositionPolicy, IdentityMemory
    from capevo.evolve import ensure_v0
    from capevo.learner.base import LearnRequest
    from capevo.learner.bc import BcLearner
    from capevo.learner.presets import make_preset
    from capevo.registry.local import LocalRegistry
    from capevo.runtime.evaluator import LocalEvaluator
    from capevo.runtime.tasks import Perturbations, task_spec

    torch.set_num_threads(1)
    seeds = range(FIRST_SEED, FIRST_SEED + eval_episodes)
    preset = make_preset(preset_name).with_seed(seed).with_perturbations(Perturbations())
    config = dataclasses.replace(preset.bc, dagger_rounds=rounds, dagger_episodes=episodes)
    # training episodes of seed s start 1,000 episodes after those of seed s - 1: no overlap
    env = dataclasses.replace(preset.env, phi="task", seed=1000 * seed)
    spec = task_spec("T1")
    scripted = preset.scripted_episodes if scripted is None else scripted
    row: dict[str, Any] = {
        "preset": preset_name,
        "seed": seed,
        "scripted": scripted,
        "rounds": rounds,
        "episodes": episodes,
        "ecms": {},
    }
    started = time.perf_counter()
    with LocalRegistry(work / "data", actor="diag") as reg:
        ensure_v0(reg, "T1", modality="il", seed=seed)
        for ecm in spec.ecm_names:
            request = LearnRequest(
                task=spec.name, ecm=ecm, parent=reg.get_version(ecm), source="", train_seeds=(), outcomes=()
            )
            learner = BcLearner(config=config, env_config=env, registry=reg, scripted_episodes=scripted)
            candidate = learner.learn(request)
            version = candidate.publish(reg)
            reg.promote(ecm, version.version, reason="diag_bc_dagger: composed clone")
            row["ecms"][ecm] = {
                "demos": candidate.notes["demos"],
                "dagger": candidate.notes["dagger"],
                "loss_after": candidate.notes["bc"]["loss_after"],
            }
            print(ecm, row["ecms"][ecm], flush=True)
        policy = DecompositionPolicy(identity=IdentityMemory.default())
        with LocalEvaluator(reg, policy=policy, phi="task", trace_dir=work / "traces") as evaluator:
            outcomes = evaluator.evaluate("T1", {}, list(seeds))
    row["seeds"] = f"{seeds.start}-{seeds.stop - 1}"
    row["success"] = [bool(o.success) for o in outcomes]
    row["unsafe"] = [int(o.unsafe_steps) > 0 for o in outcomes]
    row["steps"] = [int(o.steps) for o in outcomes]
    row["learner_env_steps"] = sum(e["demos"]["new_samples"] + e["dagger"]["env_steps"] for e in row["ecms"].values())
    row["seconds"] = round(time.perf_counter() - started, 1)
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=0, help="DAgger rounds per ECM (0: plain cloning)")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per DAgger round")
    parser.add_argument("--preset", default="cpu-small", help="learner preset (capevo.learner.presets)")
    parser.add_argument("--eval-episodes", type=int, default=30, help="evaluation episodes, from seed 600000")
    parser.add_argument(
        "--seed", type=int, default=0, help="seeds v0's weights and cloning; training episodes start at 1,000 × SEED"
    )
    parser.add_argument(
        "--scripted", type=int, default=None, help="scripted demonstration episodes per ECM (default: the preset's)"
    )
    parser.add_argument("--out", default="bc_dagger", help="benchmarks/results/<out>.json")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="capevo-dagger-") as tmp:
        row = run(
            args.rounds,
            args.episodes,
            Path(tmp),
            preset_name=args.preset,
            eval_episodes=args.eval_episodes,
            seed=args.seed,
            scripted=args.scripted,
        )
    row["machine"] = _common.machine()
    path = _common.RESULTS_DIR / f"{args.out}.json"
    rows = json.loads(path.read_text()) if path.exists() else []
    rows.append(row)
    path.write_text(json.dumps(rows, indent=1) + "\n")
    n = len(row["success"])
    print(f"success {sum(row['success'])}/{n}, unsafe {sum(row['unsafe'])}, {row['seconds']} s -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
