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
        [--iterations N] [--live-episodes N] [--updates-per-iteration K] [--parallel] [--seed 0] \\
        [--work-dir DIR] [--no-perturbations] [--phi task|paper] [--heldout 30]

Every episode (live, learner, gate, final) runs under ``--phi`` (default: the per-task envelope,
the runtime's default); after each run the final capability set also runs ``--heldout`` episodes
on fresh held-out seeds (:func:`heldout_evaluation`), reported with 95 % Wilson intervals and the
safety monitor's unsafe-episode count.

``--parallel`` starts every task's run at once (each run's CPU time is still its own, from
``wait4``); the load average at the start and end of each run is recorded with it.

Writes ``benchmarks/results/evolution.json`` and ``benchmarks/results/evolution.md`` after
every task (so an interrupted run keeps what finished) and prints the markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
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
HELDOUT_SEED = 250_000
"""First seed of the held-out evaluation (see :func:`heldout_evaluation`)."""


def evolve_command() -> list[str]:
    from capevo.cli import main

    registered = "evolve" in getattr(main, "commands", {}) or "evolve" in getattr(main, "lazy_subcommands", {})
    return [sys.executable, "-m", "capevo", "evolve"] if registered else [sys.executable, "-m", "capevo.cli.evolve"]


def start_task(task: str, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """Start one task's ``capevo evolve`` run (output to files under ``work/task``)."""
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
        "--phi",
        args.phi,
        "--modality",
        args.modality,
    ]
    for flag, value in (
        ("--iterations", args.iterations),
        ("--live-episodes", args.live_episodes),
        ("--gate-extension", args.gate_extension),
        ("--updates-per-iteration", args.updates_per_iteration),
    ):
        if value is not None:
            cmd += [flag, str(value)]
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAPEVO_")}
    print(f"[{task}] {' '.join(cmd[1:])}", flush=True)
    (work / task).mkdir(parents=True, exist_ok=True)
    out_path, err_path = work / task / "stdout.json", work / task / "stderr.txt"
    with open(out_path, "w") as out, open(err_path, "w") as err:
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=env, cwd=work)
    return {"task": task, "proc": proc, "t0": time.perf_counter(), "load0": os.getloadavg(), "work": work}


def finish_task(run: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """Wait for a started run and read its results."""
    task, work = run["task"], run["work"]
    # wait4: this child's own CPU time, even while other runs are going
    _, status, usage = os.wait4(run["proc"].pid, 0)
    run["proc"].returncode = os.waitstatus_to_exitcode(status)
    wall, cpu = time.perf_counter() - run["t0"], usage.ru_utime + usage.ru_stime
    load = {"loadavg_start": list(run["load0"]), "loadavg_end": list(os.getloadavg())}
    stderr = (work / task / "stderr.txt").read_text()
    if run["proc"].returncode != 0:
        print(stderr[-3000:], file=sys.stderr)
        return {"task": task, "error": stderr.strip().splitlines()[-1:] or ["?"], "wall_s": wall, "cpu_s": cpu, **load}
    report = work / task / "report"
    s = json.loads((work / task / "stdout.json").read_text())
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
        "monitor_not_confirmed": len(s.get("monitor_not_confirmed") or ()),
        "live_success_per_iteration": [r["live"]["success_rate"] for r in rows],
        "learner_episodes": sum(r["learner_episodes"] for r in rows),
        "identity_hash": s["identity_hash"],
        "delta_pi": s["delta_pi"],
        # the run's own wall time: with --parallel, a run may end before the one waited on first
        "wall_s": float(s.get("wall_s") or wall),
        "wall_waited_s": wall,
        "cpu_s": cpu,
        **load,
        "iteration_wall_s": [r["wall_s"] for r in rows],
        "chains": [[r.get("ecm_updated"), *(u.get("ecm") for u in r.get("further") or [])] for r in rows],
        "report": str(report / "report.md") if args.keep else None,
    }
    if args.heldout:
        out["heldout"] = heldout_evaluation(task, work / task / "data", args)
        if args.modality == "code":  # the hand-set row is code parameters set by hand
            out["hand_set_heldout"] = hand_set_evaluation(task, work / task, args)
    print(
        f"[{task}] v0 {out['v0_successes']} -> final {out['final_successes']}; "
        f"{out['promoted']} promoted, {out['rejected']} rejected; {wall:.0f} s wall, {cpu:.0f} s CPU",
        flush=True,
    )
    return out


def heldout_evaluation(task: str, root: Path, args: argparse.Namespace) -> dict[str, Any]:
    """The final capability set on ``args.heldout`` fresh seeds, by ``capevo runtime evaluate --root``.

    The seeds start at ``HELDOUT_SEED`` (250000): inside the seed plan's live block but past every
    seed a run of these sizes uses there (live episodes of iteration ``i`` are 200000 + ``i`` x
    live_episodes), and outside its training (0-99999) and gate (100000-199999) blocks, so no
    learner, gate decision or ECM choice ever saw them.
    """
    from capevo.runtime.gate_stats import wilson_interval

    first = HELDOUT_SEED + args.seed * 300_000
    seeds = f"{first}-{first + args.heldout - 1}"
    cmd = [sys.executable, "-m", "capevo", "runtime", "evaluate", "--root", str(root), "--task", task]
    cmd += ["--seeds", seeds, "--phi", args.phi, "--json"]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        return {"seeds": seeds, "error": done.stderr.strip().splitlines()[-1:]}
    rows = json.loads(done.stdout)
    n, ok = len(rows), sum(r["success"] for r in rows)
    unsafe = sum(r["unsafe_steps"] > 0 for r in rows)
    ci = wilson_interval(ok, n, alpha=0.025)
    strict = [r.get("strict_success") for r in rows if r.get("strict_success") is not None]
    return {
        # the task's stricter check beside robosuite's success (T6: the peg through the plate)
        "strict_successes": sum(strict) if strict else None,
        "seeds": seeds,
        "episodes": n,
        "successes": ok,
        "wilson95": [ci.low, ci.high],
        "unsafe_episodes": unsafe,
        "mean_steps": sum(r["steps"] for r in rows) / n,
        "command": " ".join(["capevo", *cmd[3:]]),
    }


def hand_set_evaluation(task: str, work: Path, args: argparse.Namespace) -> dict[str, Any]:
    """The best hand-set parameters (:mod:`capevo.learner.skills.hand_set`: v0's listed weaknesses
    fixed by hand, no search) on the same held-out seeds, in a registry of their own: what search
    adds beyond them (issue 19)."""
    from capevo.learner.skills.hand_set import hand_set_overrides, seed_hand_set
    from capevo.registry.local import LocalRegistry

    root = work / "hand-set"
    shutil.rmtree(root, ignore_errors=True)
    with LocalRegistry(root, actor="bench-hand-set") as registry:
        seed_hand_set(registry, task)
    out = heldout_evaluation(task, root, args)
    out["overrides"] = hand_set_overrides(task)
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
        "held-out success [95% Wilson]",
        "held-out unsafe episodes",
        "hand-set params, held-out [95% Wilson]",
        "hand-set unsafe episodes",
        "promoted",
        "rejected",
        "rollbacks",
        "learner episodes",
        "wall s",
        "CPU s",
        "load avg (start-end)",
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
                    "",
                    "",
                    "",
                    "",
                    f"{r['wall_s']:.0f}",
                    f"{r['cpu_s']:.0f}",
                    _load(r),
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
                *_heldout(r.get("heldout")),
                *_heldout(r.get("hand_set_heldout")),
                r["promoted"],
                r["rejected"],
                r["rollbacks"],
                r["learner_episodes"],
                f"{r['wall_s']:.0f}",
                f"{r['cpu_s']:.0f}",
                _load(r),
            ]
        )
    return markdown_table(headers, rows)


def _heldout(h: dict[str, Any] | None) -> list[str]:
    if not h:
        return ["-", "-"]
    if "error" in h:
        return ["error: " + " ".join(h["error"]), "-"]
    low, high = h["wilson95"]
    strict = "" if h.get("strict_successes") is None else f"; strict check {h['strict_successes']}/{h['episodes']}"
    return [
        f"{h['successes']}/{h['episodes']} [{low:.0%}, {high:.0%}]{strict}",
        f"{h['unsafe_episodes']}/{h['episodes']}",
    ]


def _load(r: dict[str, Any]) -> str:
    a, b = r.get("loadavg_start"), r.get("loadavg_end")
    return f"{a[0]:.1f}-{b[0]:.1f}" if a and b else "-"


def _write(name: str, params: dict[str, Any], results: list[dict[str, Any]]) -> None:
    save_results(name, {"params": params, "results": results})
    (RESULTS_DIR / f"{name}.md").write_text(
        f"# capevo evolve, preset {params['preset']}, modality {params.get('modality', 'code')}, "
        f"perturbations {'on' if params['perturbations'] else 'off'}, Φ {params['phi']}\n\n"
        f"`.venv/bin/python {params['command']}`, {params['date']}, "
        f"{params['cores']} cores.\n\n" + table(results) + "\n"
    )


def add_hand_set_rows(args: argparse.Namespace) -> None:
    """Add the hand-set row to results saved by a run made before that row existed."""
    if args.work_dir is None:
        raise SystemExit("--hand-set-only needs the --work-dir of the earlier run")
    saved = json.loads((RESULTS_DIR / f"{args.name}.json").read_text())
    params = saved["params"]
    args.phi, args.seed = params["phi"], params["seed"]
    for r in saved["results"]:
        if r["task"] in args.tasks and "error" not in r:
            r["hand_set_heldout"] = hand_set_evaluation(r["task"], args.work_dir / r["task"], args)
    params["hand_set_command"] = " ".join(["benchmarks/bench_evolution.py", *sys.argv[1:]])
    _write(args.name, params, saved["results"])
    print(table(saved["results"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["T1", "T2", "T3"])
    parser.add_argument("--preset", default="cpu-small")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--live-episodes", type=int, default=None, help="also the final evaluation's episodes")
    parser.add_argument("--updates-per-iteration", type=int, default=None)
    parser.add_argument("--gate-extension", type=int, default=None, help="paired seeds of the gate's second look")
    parser.add_argument("--parallel", action="store_true", help="run the tasks at the same time")
    parser.add_argument("--name", default=NAME, help="results file name under benchmarks/results")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work-dir", type=Path, default=None, help="keep registries and reports here")
    parser.add_argument("--perturbations", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--phi", default="task", help="the envelope of every episode: task (default) or paper")
    parser.add_argument(
        "--modality", default="code", help="code (default), rl, il, hybrid, or a combination such as il+rl"
    )
    parser.add_argument(
        "--heldout", type=int, default=30, help="episodes of the final set on fresh held-out seeds (0: none)"
    )
    parser.add_argument(
        "--hand-set-only",
        action="store_true",
        help="only add the hand-set row to the existing results --name (from --work-dir's runs)",
    )
    args = parser.parse_args()
    if args.hand_set_only:
        add_hand_set_rows(args)
        return
    args.keep = args.work_dir is not None
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="capevo-bench-evolution-"))
    work.mkdir(parents=True, exist_ok=True)
    results: list[dict[str, Any]] = []
    params = {
        "tasks": args.tasks,
        "preset": args.preset,
        "iterations": args.iterations,
        "live_episodes": args.live_episodes,
        "updates_per_iteration": args.updates_per_iteration,
        "gate_extension": args.gate_extension,
        "parallel": args.parallel,
        "seed": args.seed,
        "perturbations": args.perturbations,
        "phi": args.phi,
        "modality": args.modality,
        "heldout": args.heldout,
        "cores": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d", time.gmtime()),
        "command": " ".join(["benchmarks/bench_evolution.py", *sys.argv[1:]]),
    }
    try:
        started = [start_task(t, args, work) for t in args.tasks] if args.parallel else []
        for i, task in enumerate(args.tasks):
            run = started[i] if args.parallel else start_task(task, args, work)
            results.append(finish_task(run, args))
            _write(args.name, params, results)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print()
    print(table(results))


if __name__ == "__main__":
    main()
