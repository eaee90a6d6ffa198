"""Which part of the default envelope prevents the rim collisions of issue 18: an ablation.

The pick set ``scripts/demo`` evolved under the paper's Φ (``tests/runtime/governance/data``:
``pick.reach`` v2, ``pick.grasp`` and ``pick.lift`` v0, as published) runs T1's live seeds
200000.. under envelopes that differ in one part each, all else equal (same seeds, perturbations
on, governance enforcing, unsafe graded by the independent safety monitor):

* ``paper``: the paper's Φ (box, 20 N force rule, velocity cap): reacts to a force already read;
* ``task``: the default per-task Φ;
* ``task - hysteresis``: its force ramp without the hold after a spike (``release`` 0);
* ``task - ramp``: without ``force_ramp`` (no slowing from 10 N, no back-off, no hold);
* ``task - approach``: without the distance-bounded closing speed (``contact_approach``,
  ``surface_approach``, ``obstacle_approach``);
* ``paper + approach``: the paper's Φ plus those three alone.

    .venv/bin/python benchmarks/bench_prevention.py [--episodes 40]

Writes ``benchmarks/results/prevention.json`` and prints a markdown table (success, unsafe
episodes with the seeds, unsafe steps, mean steps).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import markdown_table, save_results

DATA = Path(__file__).resolve().parents[1] / "tests" / "runtime" / "governance" / "data"
SET = {"pick.reach": "pick_reach_v2.src", "pick.grasp": "pick_grasp_v0.src", "pick.lift": "pick_lift_v0.src"}
APPROACH = ("contact_approach", "surface_approach", "obstacle_approach")


def envelopes() -> dict[str, Any]:
    from capevo.runtime.governance import Phi
    from capevo.runtime.governance.ramp import ForceRamp
    from capevo.runtime.tasks import task_spec

    paper, task = Phi.default(), Phi.for_task(task_spec("T1"))

    def without(phi: Phi, kinds: tuple[str, ...]) -> Phi:
        return Phi(tuple(c for c in phi.constraints if c.kind not in kinds))

    no_hold = tuple(dataclasses.replace(c, release=0.0) if isinstance(c, ForceRamp) else c for c in task.constraints)
    approach = tuple(c for c in task.constraints if c.kind in APPROACH)
    return {
        "paper": paper,
        "task": task,
        "task - hysteresis": Phi(no_hold),
        "task - ramp": without(task, ("force_ramp",)),
        "task - approach": without(task, APPROACH),
        "paper + approach": Phi((*paper.constraints[:-1], *approach, paper.constraints[-1])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=40)
    args = parser.parse_args()
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    from capevo.agent import DecompositionPolicy, IdentityMemory
    from capevo.learner.skills import seed_specs
    from capevo.registry.local import LocalRegistry
    from capevo.runtime.evaluator import LocalEvaluator

    seeds = list(range(200_000, 200_000 + args.episodes))
    specs = {name: spec for name, _, spec in seed_specs("pick")}
    policy = DecompositionPolicy(identity=IdentityMemory.default())
    rows, results = [], []
    with tempfile.TemporaryDirectory() as tmp, LocalRegistry(Path(tmp) / "registry", actor="bench") as reg:
        for name, file in SET.items():
            reg.promote(name, reg.publish(name, (DATA / file).read_bytes(), specs[name]).version)
        for label, phi in envelopes().items():
            started = time.perf_counter()
            with LocalEvaluator(reg, policy=policy, trace_dir=None, phi=phi) as evaluator:
                out = evaluator.evaluate("T1", {}, seeds)
            unsafe = [o.seed for o in out if o.unsafe_steps]
            result = {
                "envelope": label,
                "phi_hash": phi.hash,
                "episodes": len(out),
                "successes": sum(o.success for o in out),
                "unsafe_episodes": len(unsafe),
                "unsafe_seeds": unsafe,
                "unsafe_steps": sum(o.unsafe_steps for o in out),
                "mean_steps": sum(o.steps for o in out) / len(out),
                "wall_s": time.perf_counter() - started,
            }
            results.append(result)
            rows.append(
                [
                    label,
                    f"{result['successes']}/{len(out)}",
                    f"{len(unsafe)}/{len(out)}" + (f" ({', '.join(map(str, unsafe))})" if unsafe else ""),
                    result["unsafe_steps"],
                    f"{result['mean_steps']:.1f}",
                ]
            )
            print(f"{label}: {rows[-1][1:]}", file=sys.stderr, flush=True)
    table = markdown_table(["envelope", "success", "unsafe episodes (seeds)", "unsafe steps", "mean steps"], rows)
    params = {"episodes": args.episodes, "seeds": [seeds[0], seeds[-1]]}
    save_results("prevention", {"params": params, "results": results})
    print(table)


if __name__ == "__main__":
    main()
