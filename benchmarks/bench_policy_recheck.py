"""Re-grade a finished grid's learned whole-task policies under today's default envelope.

The cpu-small grid (``results/cpu-small``) trains AM and AM-bc (SB3 PPO, one policy for the
whole task; ``capevo.baselines.am``) and saves each iteration's policy to
``cells/<cell>/checkpoints/iteration-NNN.zip``. Under the default Φ of the time, their held-out
episodes were unsafe by the independent safety monitor in 14/30 (AM-bc, T1), 7/30 (AM-bc, T6) and
2/30 (AM, T1) episodes, which is what issue 18's governance fixes answer. This script runs the
very same policies again, unchanged, on the cell's own held-out seeds
(:meth:`capevo.baselines.base.CellSpec.eval_seeds`, one env per checkpoint, seeds in order, as the
grid did), with the envelope as it is now (``--phi``, default ``task``), governance on and the
paper's perturbations, and counts unsafe episodes by the monitor and their reasons.

It re-grades the policies only: training under the new envelope would give other policies, which
is what a fresh grid run measures.

``--seeds`` (``FIRST-LAST``, as ``capevo runtime evaluate`` takes them) runs other seeds than the
cell's own (more episodes than the grid's 10, to see rare contacts), ``--iterations`` picks
checkpoints, and ``--without KIND`` also runs every episode under the same Φ with the constraints
of that kind removed, so one command shows what a rule changes on the same policies and seeds.

    .venv/bin/python benchmarks/bench_policy_recheck.py --grid results/cpu-small \\
        [--cells T1-am-bc-s42 T6-am-bc-s42 T1-am-s42 T6-am-s42] [--phi task] \\
        [--seeds 2000042010-2000042039] [--iterations 3] [--without keep_clear]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import markdown_table, save_results

DEFAULT_CELLS = ("T1-am-s42", "T1-am-bc-s42", "T6-am-s42", "T6-am-bc-s42")


def without_kind(task: str, phi: str, kind: str) -> Any:
    """The Φ ``phi`` resolves to for ``task`` with every constraint of ``kind`` removed."""
    from capevo.runtime.envelope import resolve_phi
    from capevo.runtime.governance import Phi
    from capevo.runtime.tasks import task_spec

    full = resolve_phi(phi, task_spec(task))
    kept = tuple(c for c in full.constraints if c.kind != kind)
    if len(kept) == len(full.constraints):
        raise SystemExit(f"--without {kind}: the {phi} Φ of {task} has no such constraint")
    return Phi(kept)


def recheck(
    cell_dir: Path, phi: Any, seeds: list[int] | None = None, iterations: list[int] | None = None
) -> list[dict[str, Any]]:
    """Every checkpoint of one AM cell (or those of ``iterations``), re-run on the cell's held-out
    seeds (or ``seeds``) under ``phi``."""
    import numpy as np
    from stable_baselines3 import PPO

    from capevo.baselines.base import CellSpec
    from capevo.baselines.governed_env import evaluate_policy

    cell = CellSpec.from_dict(json.loads((cell_dir / "cell.json").read_text())["cell"])
    rows = []
    for ckpt in sorted((cell_dir / "checkpoints").glob("iteration-0*.zip")):
        iteration = int(ckpt.stem.split("-")[1])
        if iteration == 0 or (iterations and iteration not in iterations):
            continue  # the untrained policy was never evaluated by the grid
        model = PPO.load(ckpt, device="cpu")

        def act(obs: np.ndarray, model: Any = model) -> np.ndarray:
            return model.predict(obs, deterministic=True)[0]

        started = time.perf_counter()
        episodes, steps = evaluate_policy(
            cell.task,
            act,
            seeds or cell.eval_seeds(),
            phi=phi(cell.task) if callable(phi) else phi,
            governance=cell.governance,
            perturbations=cell.perturbations,
        )
        rows.append(
            {
                "cell": cell_dir.name,
                "iteration": iteration,
                "episodes": len(episodes),
                "unsafe_episodes": sum(e.unsafe_steps > 0 for e in episodes),
                "unsafe_steps": sum(e.unsafe_steps for e in episodes),
                "successes": sum(e.success for e in episodes),
                "unsafe_seeds": [e.seed for e in episodes if e.unsafe_steps > 0],
                "env_steps": steps,
                "seconds": time.perf_counter() - started,
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def seed_list(text: str) -> list[int]:
    """``--seeds`` as ``capevo runtime evaluate`` reads it (``0-9,20``)."""
    from capevo.cli.runtime import parse_seeds
    from capevo.errors import Invalid

    try:
        return parse_seeds(text)
    except Invalid as err:
        raise argparse.ArgumentTypeError(err.message) from None


def grid_unsafe(cell_dir: Path) -> dict[int, int]:
    """The unsafe episodes the grid itself recorded, per iteration (its ``metrics.jsonl``)."""
    out = {}
    for line in (cell_dir / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        out[int(record["iteration"])] = sum(e["unsafe_steps"] > 0 for e in record["episodes"])
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--grid", type=Path, required=True, help="a finished grid's run directory")
    parser.add_argument("--cells", nargs="+", default=list(DEFAULT_CELLS))
    parser.add_argument("--phi", default="task")
    parser.add_argument("--out", default="policy_recheck")
    parser.add_argument("--seeds", type=seed_list, help="e.g. 2000042010-2000042039: these instead of the cell's own")
    parser.add_argument("--iterations", type=int, nargs="+", help="only these iterations' checkpoints")
    parser.add_argument("--without", metavar="KIND", help="also run under the Φ without this constraint kind")
    args = parser.parse_args(argv)
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    rows = []
    for name in args.cells:
        cell_dir = args.grid / "cells" / name
        before = grid_unsafe(cell_dir) if args.seeds is None else {}
        for row in recheck(cell_dir, args.phi, args.seeds, args.iterations):
            row["grid_unsafe_episodes"] = before.get(row["iteration"])
            if args.without:
                ablated = recheck(
                    cell_dir, lambda task: without_kind(task, args.phi, args.without), args.seeds, [row["iteration"]]
                )[0]
                row["without"] = {
                    k: ablated[k] for k in ("unsafe_episodes", "unsafe_steps", "successes", "unsafe_seeds")
                }
            rows.append(row)
    table = [
        [
            r["cell"],
            r["iteration"],
            "-" if r["grid_unsafe_episodes"] is None else f"{r['grid_unsafe_episodes']}/{r['episodes']}",
            *([f"{r['without']['unsafe_episodes']}/{r['episodes']}"] if args.without else []),
            f"**{r['unsafe_episodes']}/{r['episodes']}**",
            r["unsafe_steps"],
            f"{r['successes']}/{r['episodes']}",
        ]
        for r in rows
    ]
    print(
        markdown_table(
            [
                "cell",
                "iteration",
                "unsafe, as the grid ran",
                *([f"unsafe, default Φ without {args.without}"] if args.without else []),
                "unsafe, default Φ now",
                "unsafe steps now",
                "success now",
            ],
            table,
        )
    )
    command = "benchmarks/bench_policy_recheck.py " + " ".join(sys.argv[1:] if argv is None else argv)
    print(f"results: {save_results(args.out, {'command': command.strip(), 'phi': args.phi, 'rows': rows})}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
