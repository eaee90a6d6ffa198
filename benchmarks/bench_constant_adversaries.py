"""Constant full-speed pushes on T1 under the default Φ, over several seeds, with and without a rule.

``tests/runtime/governance/test_gov_robosuite.py`` pushes T1's arm along each axis at full speed
for 100 steps on one seed. One seed can pass by luck: this script runs the same adversaries
(``make_task("T1")`` without perturbations, a governor of the Φ, the pose delta held every step,
the gripper closed) on ``--seeds`` and counts the steps the paper's hard limits call unsafe
(``capevo.runtime.governance.is_unsafe``), per seed, under the default per-task Φ and, with
``--without KIND``, under that Φ with every constraint of that kind removed.

    .venv/bin/python benchmarks/bench_constant_adversaries.py [--seeds 8] [--steps 100] \\
        [--without stopping_distance] [--out constant_adversaries]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import markdown_table, save_results

PUSHES = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "-z": (0.0, 0.0, -1.0),
}


def unsafe_steps(env: Any, phi: Any, push: tuple[float, float, float], seed: int, steps: int) -> int:
    """Steps of one pushed episode whose state and executed action break a hard limit of ``phi``."""
    import numpy as np

    from capevo.runtime.governance import hold_action, is_unsafe
    from capevo.runtime.governance.robosuite_state import action_frames

    env.reset(seed=seed)
    layout = env.task_spec.action_layout
    govern = phi.governor(layout, frames=action_frames(env.robosuite_env.robots))
    proposed = np.array([*push, 0.0, 0.0, 0.0, -1.0])
    count, last = 0, None
    for _ in range(steps):
        state = env.robot_state()
        governed, _ = govern(state, proposed)
        executed = hold_action(layout, last) if governed is None else governed
        count += is_unsafe(state, executed, phi, layout)
        env.step(np.clip(np.asarray(executed, dtype=np.float64), -1.0, 1.0))
        last = executed
    return count


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=8, help="seeds 0..N-1")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--without", metavar="KIND", help="also run under the default Φ without this kind")
    parser.add_argument("--out", default="constant_adversaries")
    args = parser.parse_args(argv)
    if args.seeds < 1 or args.steps < 1:
        parser.error("--seeds and --steps must be at least 1")
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    from capevo.runtime.governance import Phi
    from capevo.runtime.tasks import Perturbations, make_task

    env = make_task("T1", seed=0, perturbations=Perturbations.none(), terminate_on_success=False)
    try:
        full = Phi.for_task(env)
        phis = {"default Φ": full}
        if args.without:
            kept = tuple(c for c in full.constraints if c.kind != args.without)
            if len(kept) == len(full.constraints):
                parser.error(f"--without {args.without}: the default Φ of T1 has no such constraint")
            phis = {f"without {args.without}": Phi(kept), **phis}
        rows: dict[str, dict[str, list[int]]] = {}
        for name, push in PUSHES.items():
            rows[name] = {
                label: [unsafe_steps(env, phi, push, s, args.steps) for s in range(args.seeds)]
                for label, phi in phis.items()
            }
            print(name, rows[name], flush=True)
    finally:
        env.close()
    table = [
        [name, *(f"{sum(c > 0 for c in counts)} ({sum(counts)})" for counts in per.values())]
        for name, per in rows.items()
    ]
    print(markdown_table(["push", *(f"unsafe episodes (steps), {label}" for label in phis)], table))
    command = "benchmarks/bench_constant_adversaries.py " + " ".join(sys.argv[1:] if argv is None else argv)
    payload = {"command": command.strip(), "seeds": args.seeds, "steps": args.steps, "rows": rows}
    print(f"results: {save_results(args.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
