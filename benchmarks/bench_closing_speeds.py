"""What the closing speeds of the proximity pairs, and ``stopping_distance``'s check, cost per step.

On a live T1 episode (seed 3, no perturbations, the arm driven down and sideways into the bin so
that pairs are near), at each of ``--steps`` states: ``ProximitySensor._near`` timed ``--reps``
times without the closing speeds (the anchor: the pairs alone, as before them) and with them,
alternating, and the rule's compiled check on that state's ``robot_state()``. Prints the p50 per
call and the pairs per step.

    .venv/bin/python benchmarks/bench_closing_speeds.py [--steps 60] [--reps 50]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import save_results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--reps", type=int, default=50)
    parser.add_argument("--out", default="closing_speeds")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.reps < 1:
        parser.error("--steps and --reps must be at least 1")
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    import numpy as np

    from capevo.baselines.governed_env import GovernedTaskEnv
    from capevo.runtime.governance import StoppingDistance
    from capevo.runtime.state import SINGLE_PANDA

    env = GovernedTaskEnv("T1", perturbations=False)
    try:
        env.reset(seed=3)
        sensor = env.task_env._proximity
        check = next(c for c in env.phi.constraints if isinstance(c, StoppingDistance)).compile(SINGLE_PANDA)
        without, with_speeds, rule, pairs = [], [], [], []
        action = [0.1] * 7
        for _ in range(args.steps):
            env.step(np.array([0.3, -0.2, -0.6, 0.1, 0.0, 0.2, 0.0]))
            for _ in range(args.reps):
                t0 = time.perf_counter()
                sensor._near(0, [])
                t1 = time.perf_counter()
                closing: list[float] = []
                sensor._near(0, [], closing)
                t2 = time.perf_counter()
                without.append(t1 - t0)
                with_speeds.append(t2 - t1)
            pairs.append(len(closing))
            arms = env.task_env.robot_state().arms
            for _ in range(args.reps):
                t0 = time.perf_counter()
                check(arms, action)
                rule.append(time.perf_counter() - t0)
    finally:
        env.close()
    out = {
        "pairs_per_step": statistics.fmean(pairs),
        "near_us_p50_without_closing": statistics.median(without) * 1e6,
        "near_us_p50_with_closing": statistics.median(with_speeds) * 1e6,
        "stopping_distance_check_us_p50": statistics.median(rule) * 1e6,
    }
    for k, v in out.items():
        print(f"{k}: {v:.1f}")
    command = "benchmarks/bench_closing_speeds.py " + " ".join(sys.argv[1:] if argv is None else argv)
    print(f"results: {save_results(args.out, {'command': command.strip(), **out})}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
