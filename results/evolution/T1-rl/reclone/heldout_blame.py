"""Re-run the held-out evaluation of the final T1 `rl` set with traces, and print where each failure ended.

Usage: ``python heldout_blame.py REGISTRY_DIR TRACE_DIR`` (seeds 250000-250029, default Φ, the
perturbations on), run on a copy of the evolution run's registry; see ``../heldout.md``.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from capevo.agent import DecompositionPolicy, IdentityMemory, identity_hash
from capevo.learner.experience import episode_ends, failed_activations
from capevo.registry.local import LocalRegistry
from capevo.runtime.evaluator import LocalEvaluator

DECOMPOSITION = ["pick.reach", "pick.grasp", "pick.lift"]


def main(root: Path, trace_dir: str) -> None:
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
            outcomes = evaluator.evaluate("T1", versions, list(range(250000, 250030)))
    unsafe = sum(o.unsafe_steps > 0 for o in outcomes)
    print(versions, sum(o.success for o in outcomes), "/", len(outcomes), "unsafe", unsafe)
    for end in episode_ends(outcomes):
        if not end.success:
            blame = failed_activations(end, DECOMPOSITION)
            print(end.seed, end.end_reason, end.plan, dict(end.ecm_steps), "blame", blame)


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2])
