"""The main job, measured: ``capevo evolve`` on T1, T2, T3 at cpu-small with perturbations on.

For each task, in a fresh registry and report directory, one real command-line run::

    python -m capevo evolve --task T --preset cpu-small --root WORK/T/data --report-dir WORK/T/report --json

(``python -m capevo.cli.evolve`` until the ``evolve`` command is registered in ``capevo``). It
creates version 0 (the built-in untuned skills), runs the closed loop for the preset's
iterations, and finally runs the final capability set on iteration 0's live seeds. Recorded per
task: success at v0 (iteration 0's live episodes) and after evolution (the same seeds), the
paired McNemar p-value of that difference, gate decisions, rollbacks, wall time, and the CPU
time of the run (user + system of the child; on a shared machine wall time moves with the load,
CPU time much less).

Usage::

    .venv/bin/python benchmarks/bench_evolution.py [--tasks T1 T2 T3] [--preset cpu-small] \\
        [--iterations N] [--seed 0] [--work-dir DIR] [--no-perturbations]

Writes ``benchmarks/results/evolution.json`` and ``benchmarks/results/evolution.md`` after
every task (so an interrupted run keeps what finished) and prints the markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _common import RESULTS_DIR, markdown_table, save_results

NAME = "evolution"


def evolve_command() -> list[str]:
    from capevo.cli import main

    registered = "evolve" in getattr(main, "commands", {}) or "evolve" in getattr(main, "lazy_subcommands", {})
    return [sys.executable, "-m", "capevo", "evolve"] if registered else [sys.executable, "-m", "capevo.cli.evolve"]


def _cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_task(task: str, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    root, report = work / task / "data", work / task / "report"
    cmd = [
        *evolve_command(),
        "--task",
        task,
        "--preset",
        args.preset,
        "--root",
        str(root),
        "--report-dir",
        str(report),
        "--seed",
        str(args.seed),
        "--json",
        "--perturbations" if args.perturbations else "--no-perturbations",
    ]
    if args.iterations is not None:
        cmd += ["--iterations", str(args.iterations)]
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAPEVO_")}
    print(f"[{task}] {' '.join(cmd[1:])}", flush=True)
    cpu0, t0 = _cpu_children(), time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=work)
    wall, cpu = time.perf_counter() - t0, _cpu_children() - cpu0
    if done.returncode != 0:
        print(done.stderr[-3000:], file=sys.stderr)
        return {"task": task, "error": done.stderr.strip().splitlines()[-1:] or ["?"], "wall_s": wall, "cpu_s": cpu}
    s = json.loads(done.stdout)
    rows = [json.loads(line) for line in (report / "metrics.jsonl").read_text().splitlines()]
    start, final = s["start"], s["final"]
    comparison = _comparison(report)
    out = {
        "task": task,
        "iterations": s["iterations"],
        "v0_success": start["successes"] / start["episodes"] if start else None,
        "v0_successes": f"{start['successes']}/{start['episodes']}" if start else None,
        "final_success": final["successes"] / final["episodes"] if final else None,
        "final_successes": f"{final['successes']}/{final['episodes']}" if final else None,
        "v0_reward": start["reward_mean"] if start else None,
        "final_reward": final["reward_mean"] if final else None,
        "paired_p_success": comparison.get("p_success") if comparison else None,
        "start_versions": s["start_versions"],
        "final_versions": s["final_versions"],
        "gate": [
            {
                k: g.get(k)
                for k in (
                    "iteration",
                    "ecm",
                    "candidate_version",
                    "decision",
                    "n",
                    "candidate_successes",
                    "active_successes",
                    "p_success",
                    "p_noninferiority",
                    "p_reward",
                )
            }
            for g in s["gate"]
        ],
        "promoted": sum(1 for g in s["gate"] if g["decision"] == "promote"),
        "rejected": sum(1 for g in s["gate"] if g["decision"] == "reject"),
        "rollbacks": len(s["rollbacks"]),
        "live_success_per_iteration": [r["live"]["success_rate"] for r in rows],
        "learner_episodes": sum(r["learner_episodes"] for r in rows),
        "identity_hash": s["identity_hash"],
        "delta_pi": s["delta_pi"],
        "wall_s": wall,
        "cpu_s": cpu,
        "iteration_wall_s": [r["wall_s"] for r in rows],
        "report": str(report / "report.md") if args.keep else None,
    }
    print(
        f"[{task}] v0 {out['v0_successes']} -> final {out['final_successes']}; "
        f"{out['promoted']} promoted, {out['rejected']} rejected; {wall:.0f} s wall, {cpu:.0f} s CPU",
        flush=True,
    )
    return out


def _comparison(report: Path) -> dict[str, Any] | None:
    """The paired start-vs-final statistics the report computed (None without a final run)."""
    journal = report / "journal.jsonl"
    if not journal.exists():
        return None
    from capevo.evolve.metrics import read_metrics
    from capevo.runtime.evaluation import EpisodeOutcome
    from capevo.runtime.gate_stats import paired_stats

    finals = [json.loads(x) for x in journal.read_text().splitlines() if '"event":"final"' in x]
    rows = read_metrics(report)
    if not finals or not rows:
        return None
    start = [EpisodeOutcome.from_dict(e) for e in rows[0].episodes]
    final = [EpisodeOutcome.from_dict(o) for o in finals[-1]["outcomes"]]
    return paired_stats(start, final, alpha=0.05).to_dict()


def table(results: list[dict[str, Any]]) -> str:
    headers = [
        "task",
        "iterations",
        "v0 success",
        "final success",
        "paired p",
        "promoted",
        "rejected",
        "rollbacks",
        "learner episodes",
        "wall s",
        "CPU s",
    ]
    rows = []
    for r in results:
        if "error" in r:
            rows.append(
                [
                    r["task"],
                    "error: " + " ".join(r["error"]),
                    "",
                    "",
                    "",
                    "",
                    "",
                    "",
                    "",
                    f"{r['wall_s']:.0f}",
                    f"{r['cpu_s']:.0f}",
                ]
            )
            continue
        p = r["paired_p_success"]
        rows.append(
            [
                r["task"],
                r["iterations"],
                r["v0_successes"],
                r["final_successes"],
                "-" if p is None else f"{p:.3g}",
                r["promoted"],
                r["rejected"],
                r["rollbacks"],
                r["learner_episodes"],
                f"{r['wall_s']:.0f}",
                f"{r['cpu_s']:.0f}",
            ]
        )
    return markdown_table(headers, rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["T1", "T2", "T3"])
    parser.add_argument("--preset", default="cpu-small")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work-dir", type=Path, default=None, help="keep registries and reports here")
    parser.add_argument("--perturbations", action=argparse.BooleanOptionalAction, default=True)
    args = parser.parse_args()
    args.keep = args.work_dir is not None
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="capevo-bench-evolution-"))
    work.mkdir(parents=True, exist_ok=True)
    results: list[dict[str, Any]] = []
    params = {
        "tasks": args.tasks,
        "preset": args.preset,
        "iterations": args.iterations,
        "seed": args.seed,
        "perturbations": args.perturbations,
    }
    try:
        for task in args.tasks:
            results.append(run_task(task, args, work))
            save_results(NAME, {"params": params, "results": results})
            md = table(results)
            (RESULTS_DIR / f"{NAME}.md").write_text(
                f"# capevo evolve, preset {args.preset}, perturbations {'on' if args.perturbations else 'off'}\n\n"
                + md
                + "\n"
            )
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print()
    print(table(results))


if __name__ == "__main__":
    main()
