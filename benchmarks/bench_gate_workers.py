"""The gate's wall time on T1 with one and with two runtime workers, in one run (issue 19).

A registry server process (``python -m capevo.registry.service``, loopback TCP, scouting off)
holds T1 pick's reach, grasp and lift (the runtime tests' code skills, promoted). Two runtime
workers (``capevo runtime serve --task T1 --idle``, each its own process and environment)
serve evaluations. Every round publishes a fresh candidate lift (origin ``clone``, so it runs
in the sandbox, as a learner's candidate does) and gates it twice, back to back, on the same
held-out gate seeds (``SeedPlan(0).gate(N, round=r)``):

* ``1 worker``: :class:`~capevo.runtime.gate.Gate` over ``RemoteEvaluator(worker_id=...)``:
  every episode of both sides on one worker;
* ``2 workers``: the same gate over ``RemoteEvaluator()``: each side's seeds split across both
  live workers (:mod:`capevo.runtime.fanout`).

The order of the two alternates from round to round, so drift on a shared machine hits both
alike; each gate run gets its own candidate version (a gate decision is final), and a promoted
one is rolled back so that every run compares against the same active lift. Timed: the whole
``Gate.run`` (both sides' evaluations, the statistics, the evidence write, the promotion or
rejection), wall clock. The two settings must produce the same episodes (seed, success,
reward, steps): the script checks it and stops if not, because a speed-up that changes results
is not one.

What the figure can show: with 2 workers the episodes of one side run two at a time, so the
ceiling is 2× on a machine with 2 idle cores, minus the registry, the client and the
sandboxed candidate's worker processes, which share those cores.

    .venv/bin/python benchmarks/bench_gate_workers.py [--rounds 3] [--episodes 10] [--horizon H]

``--episodes`` is the gate's N (10 is ``cpu-small``'s); ``--horizon`` defaults to T1's own.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
# Test support: the T1 code skills (tests/runtime) and the process helpers they use (tests/).
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "runtime"))

from _common import markdown_table, save_results, scratch_dir
from procs import start_server
from runtime_support import LIFT, Proc, publish, publish_pick, start_worker

from capevo.records import Origin
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.gate import Gate, GateConfig, SeedPlan
from capevo.runtime.remote_evaluator import RemoteEvaluator

WORKERS = ("bench-w1", "bench-w2")
ECM = "pick.lift"


class _Recording:
    """An evaluator that keeps every outcome its inner evaluator returned, in call order."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.calls: list[list[EpisodeOutcome]] = []

    def evaluate(self, task: str, versions: Mapping[str, int], seeds: Sequence[int]) -> list[EpisodeOutcome]:
        out = list(self.inner.evaluate(task, versions, seeds))
        self.calls.append(out)
        return out


def _episodes(calls: list[list[EpisodeOutcome]]) -> list[tuple[int, bool, float, int]]:
    return [(o.seed, o.success, o.reward, o.steps) for call in calls for o in call]


def _gate_once(
    client: Any, evaluator: Any, config: GateConfig, seeds: list[int], candidate: int
) -> tuple[float, Any, list[list[EpisodeOutcome]]]:
    recording = _Recording(evaluator)
    gate = Gate(client, recording, config, actor="bench-gate")
    t0 = time.perf_counter()
    decision = gate.run(ECM, candidate, task="T1", seeds=seeds)
    wall = time.perf_counter() - t0
    if decision.promoted:  # every run must meet the same active lift
        client.rollback(ECM, reason="bench_gate_workers: back to the reference lift")
    return wall, decision, recording.calls


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=10, help="the gate's N (paired held-out seeds)")
    parser.add_argument("--horizon", type=int, default=None, help="episode length [default: T1's own]")
    parser.add_argument("--label", default="", help="free text stored with the results (e.g. the code state)")
    parser.add_argument("--out", default="gate_workers", help="results file name under benchmarks/results/")
    args = parser.parse_args(argv)
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)

    config = dataclasses.replace(GateConfig.cpu_small(), min_n=min(GateConfig.cpu_small().min_n, args.episodes))
    tmp = scratch_dir("bench-gate-workers-")
    registry = start_server(tmp / "registry")
    workers: list[Proc] = []
    rows: dict[int, list[dict[str, Any]]] = {1: [], 2: []}
    try:
        with registry.client(actor="bench") as client:
            publish_pick(client)
            extra = ["--idle", "--trace-dir", str(tmp / "traces"), "--cache-dir", str(tmp / "cache")]
            if args.horizon is not None:
                extra += ["--horizon", str(args.horizon)]
            for w in WORKERS:
                workers.append(
                    start_worker(
                        registry.endpoint,
                        task="T1",
                        log_path=tmp / f"{w}.log",
                        extra=["--worker-id", w, *extra],
                    )
                )
            with (
                RemoteEvaluator(registry.endpoint, worker_id=WORKERS[0], timeout=3600) as one,
                RemoteEvaluator(registry.endpoint, timeout=3600) as both,
            ):
                live = both.live_workers("T1")
                if live != sorted(WORKERS):
                    raise SystemExit(f"expected workers {sorted(WORKERS)} to serve T1, found {live}")
                plan = SeedPlan(base_seed=0)
                for r in range(args.rounds):
                    seeds = plan.gate(args.episodes, round=r)
                    order = (1, 2) if r % 2 == 0 else (2, 1)
                    episodes: dict[int, list[tuple[int, bool, float, int]]] = {}
                    for k in order:
                        # a fresh candidate per gate run; the comment keeps each artifact distinct
                        source = LIFT.replace('"speed": 1.0', '"speed": 0.8') + f"# round {r}, {k} worker(s)\n"
                        candidate = publish(client, ECM, source, origin=Origin.CLONE, promote=False).version
                        wall, decision, calls = _gate_once(client, one if k == 1 else both, config, seeds, candidate)
                        episodes[k] = _episodes(calls)
                        rows[k].append(
                            {
                                "round": r,
                                "wall_s": wall,
                                "episodes": len(episodes[k]),
                                "promoted": decision.promoted,
                                "workers": list(both.last_call["workers"]) if k == 2 else [WORKERS[0]],
                            }
                        )
                        print(f"round {r}: {k} worker(s): gate {wall:.1f} s, {len(episodes[k])} episodes", flush=True)
                    if episodes[1] != episodes[2]:
                        raise SystemExit(f"round {r}: 1 and 2 workers ran different episodes: {episodes}")
    finally:
        for proc in workers:
            proc.terminate()
        registry.stop()

    summary = {}
    for k, runs in rows.items():
        walls = [x["wall_s"] for x in runs]
        n_ep = sum(x["episodes"] for x in runs)
        summary[k] = {
            "median_s": statistics.median(walls),
            "min_s": min(walls),
            "max_s": max(walls),
            "episodes_per_s": n_ep / sum(walls),
        }
    speedup = summary[1]["median_s"] / summary[2]["median_s"]
    table = markdown_table(
        ["workers", "gate runs", "episodes per gate", "median s", "min s", "max s", "episodes/s", "speed-up"],
        [
            [
                k,
                len(rows[k]),
                rows[k][0]["episodes"],
                summary[k]["median_s"],
                summary[k]["min_s"],
                summary[k]["max_s"],
                summary[k]["episodes_per_s"],
                1.0 if k == 1 else speedup,
            ]
            for k in (1, 2)
        ],
    )
    print(f"\nGate wall time on T1, N = {args.episodes} paired seeds, horizon {args.horizon or 'T1 default'}:\n")
    print(table)
    print("\n1 and 2 workers ran the same episodes (seed, success, reward, steps) in every round.")
    path = save_results(
        args.out,
        {
            "label": args.label,
            "params": {"rounds": args.rounds, "episodes": args.episodes, "horizon": args.horizon, "task": "T1"},
            "command": "benchmarks/bench_gate_workers.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "summary": {str(k): v for k, v in summary.items()},
            "speedup_median": speedup,
            "runs": {str(k): v for k, v in rows.items()},
            "same_episodes": True,
        },
    )
    print(f"\nresults: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
