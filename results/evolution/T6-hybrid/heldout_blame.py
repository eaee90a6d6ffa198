"""Re-run the T6-hybrid held-out failures with traces, and print where each failure ended.

Usage: ``python heldout_blame.py REGISTRY_DIR TRACE_DIR SEEDS...`` (default Φ, the perturbations
on), on a copy of the run's registry (its set after the gate); see ``README.md``.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from capevo.agent import DecompositionPolicy, IdentityMemory, identity_hash
from capevo.learner.experience import episode_ends, failed_activations
from capevo.registry.local import LocalRegistry
from capevo.runtime.evaluator import LocalEvaluator

STEPS = ["orient_peg", "orient_hole", "approach_peg", "approach_hole", "align", "pre_insert", "insert", "hold"]
DECOMPOSITION = [f"peg_in_hole.{s}" for s in STEPS]


def main(root: Path, trace_dir: str, seeds: list[int]) -> None:
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    policy = DecompositionPolicy(identity=IdentityMemory.default())
    with LocalRegistry(root, actor="heldout-blame") as reg:
        versions = {n: reg.get_version(n).version for n in DECOMPOSITION}
        with LocalEvaluator(
            reg,
            policy=policy,
            phi="task",
            trace_dir=trace_dir,
            agent_identity_hash=identity_hash(policy, policy.identity),
            worker_id="heldout-blame",
        ) as evaluator:
            outcomes = evaluator.evaluate("T6", versions, seeds)
    print(versions, sum(o.success for o in outcomes), "/", len(outcomes))
    for end in episode_ends(outcomes):
        if not end.success:
            short = {k.split(".")[1]: v for k, v in end.ecm_steps.items()}
            plan = [p.split(".")[1] for p in end.plan]
            print(end.seed, end.end_reason, plan, short, "blame", failed_activations(end, DECOMPOSITION))


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2], [int(s) for s in sys.argv[3:]])
