"""Do the C parts earn their keep end to end? What each saves, as a share of episode wall time.

Issue 17 asks that each C extension be measured against its Python path in the real episode loop,
as a share of episode wall time, in one run, and be deleted when it saves less than 1 %. This runs
T1 (pick) and T6 (peg) episodes through :class:`LocalEvaluator` (the loop the runtime worker and
``capevo evolve`` run: the v0 code ECMs from a real LocalRegistry, governance on, perturbations on,
one MCAP trace per call), under the paper's Φ and the per-task Φ, in two configurations that
alternate seed by seed:

* ``c``: governance kernel on, trace hot path in C (the default while they existed);
* ``py``: governance in Python (``CAPEVO_GOVERNANCE_KERNEL=0``), traces in Python
  (``TraceWriter(native=False)``).

Each part's own time is clocked where it runs (``perf_counter`` around every governor call; around
every trace-writer call of the loop plus the writer's encoding and flushing, in whichever thread),
so its saving is ``(part time in py - part time in c) / episode wall time in py``, summed over the
same seeds: far less noisy than a difference of whole-episode times.

    .venv/bin/python benchmarks/bench_c_parts.py [--seeds 6] [--rounds 2]

It runs only on a tree that has the C parts (commit 96d5bee and earlier).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, save_results

from capevo.agent import DecompositionPolicy, IdentityMemory
from capevo.evolve.loop import ensure_v0
from capevo.registry.local import LocalRegistry
from capevo.runtime import evaluator as evaluator_module
from capevo.runtime.evaluator import LocalEvaluator
from capevo.runtime.governance import Phi
from capevo.runtime.governance.governor import Governor
from capevo.runtime.tasks import make_task, task_spec
from capevo.runtime.traces import writer as writer_module
from capevo.runtime.traces.writer import TraceWriter

CLOCK: dict[str, float] = defaultdict(float)
_LOCK = threading.Lock()


def _timed(key: str, fn: Any) -> Any:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            dt = time.perf_counter() - t0
            with _LOCK:
                CLOCK[key] += dt

    return wrapper


Governor.__call__ = _timed("governance", Governor.__call__)  # type: ignore[method-assign]
TraceWriter._encode_pending_locked = _timed("traces", TraceWriter._encode_pending_locked)  # type: ignore[method-assign]
TraceWriter._flush_locked = _timed("traces", TraceWriter._flush_locked)  # type: ignore[method-assign]
WRITES = (
    "write_env_step_row",
    "write_invocation_row",
    "write_plan_step",
    "write_invocation",
    "write_intervention",
    "write_env_step",
)


class TimedWriter:
    """A real TraceWriter whose loop-facing write calls are clocked (flushes and encoding are
    clocked on the class, wherever they run)."""

    def __init__(self, *args: Any, native: bool, **kwargs: Any) -> None:
        self._writer = TraceWriter(*args, native=native, **kwargs)
        for name in WRITES:
            setattr(self, name, _timed("traces", getattr(self._writer, name)))

    def write_episode_summary(self, record: Any) -> None:
        # Its flush is clocked by _flush_locked/_encode_pending_locked; the append itself here.
        self._writer.write_episode_summary(record)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._writer, name)

    def __enter__(self) -> TimedWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self._writer.close()


def _episode(registry, policy, phi, env, traces, task, versions, seed, c: bool) -> dict[str, float]:
    os.environ["CAPEVO_GOVERNANCE_KERNEL"] = "1" if c else "0"
    evaluator_module.TraceWriter = lambda *a, **k: TimedWriter(*a, native=c, **k)
    ev = LocalEvaluator(registry, policy=policy, phi=phi, trace_dir=traces, env=env)
    CLOCK.clear()
    t0 = time.perf_counter()
    (outcome,) = ev.evaluate(task, versions, [seed])
    wall = time.perf_counter() - t0
    return {"wall": wall, "steps": outcome.steps, **CLOCK}


def run(seeds: int, rounds: int) -> dict[str, Any]:
    assert writer_module.NATIVE is not None, "the trace C parts are not built here"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        registry = LocalRegistry(Path(tmp) / "reg")
        policy = DecompositionPolicy(identity=IdentityMemory.default())
        for task in ("T1", "T6"):
            ensure_v0(registry, task, modality="code")
            env = make_task(task)
            versions = {n: registry.get_ecm(n).active_version for n in task_spec(task).ecm_names}
            for phi_name in ("paper", "task"):
                phi = Phi.default() if phi_name == "paper" else Phi.for_task(env)
                for c in (True, False):  # warm-up, not counted
                    _episode(registry, policy, phi, env, Path(tmp) / "warm", task, versions, 899_999, c)
                got: dict[bool, list[dict[str, float]]] = {True: [], False: []}
                for r in range(rounds):
                    for s in range(seeds):
                        seed = 900_000 + 100 * r + s
                        for c in (True, False) if (r + s) % 2 == 0 else (False, True):
                            traces = Path(tmp) / "traces" / str(c)
                            got[c].append(_episode(registry, policy, phi, env, traces, task, versions, seed, c))
                steps = sum(e["steps"] for e in got[False])
                assert steps == sum(e["steps"] for e in got[True]), "the two configurations ran different episodes"
                wall_py = sum(e["wall"] for e in got[False])
                row: dict[str, Any] = {"task": task, "phi": phi_name, "episodes": len(got[False]), "steps": steps}
                row["ms_per_step_py"] = 1e3 * wall_py / steps
                row["ms_per_step_c"] = 1e3 * sum(e["wall"] for e in got[True]) / steps
                for part in ("governance", "traces"):
                    t_py = sum(e.get(part, 0.0) for e in got[False])
                    t_c = sum(e.get(part, 0.0) for e in got[True])
                    row[f"{part}_us_per_step_py"] = 1e6 * t_py / steps
                    row[f"{part}_us_per_step_c"] = 1e6 * t_c / steps
                    row[f"{part}_saving_pct"] = 100 * (t_py - t_c) / wall_py
                rows.append(row)
                print(
                    f"{task} {phi_name:5s} step {row['ms_per_step_py']:.2f} ms (py); "
                    f"governance {row['governance_us_per_step_py']:.1f} -> {row['governance_us_per_step_c']:.1f} us/step "
                    f"(saves {row['governance_saving_pct']:.2f} %); traces {row['traces_us_per_step_py']:.1f} -> "
                    f"{row['traces_us_per_step_c']:.1f} us/step (saves {row['traces_saving_pct']:.2f} %)",
                    flush=True,
                )
            env.close()
        registry.close()
    return {"rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    results = run(args.seeds, args.rounds)
    results["command"] = f"benchmarks/bench_c_parts.py --seeds {args.seeds} --rounds {args.rounds}"
    table = [
        [
            r["task"],
            r["phi"],
            r["episodes"],
            r["steps"],
            f"{r['ms_per_step_py']:.2f}",
            f"{r['governance_us_per_step_py']:.1f} / {r['governance_us_per_step_c']:.1f}",
            f"{r['governance_saving_pct']:.2f} %",
            f"{r['traces_us_per_step_py']:.1f} / {r['traces_us_per_step_c']:.1f}",
            f"{r['traces_saving_pct']:.2f} %",
        ]
        for r in results["rows"]
    ]
    headers = ["task", "Φ", "episodes", "steps", "ms/step", "governance µs/step py / C", "saves", "traces µs/step py / C", "saves"]
    print(markdown_table(headers, table))
    save_results("c_parts", results)


if __name__ == "__main__":
    main()
