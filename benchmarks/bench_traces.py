"""Cost of trace logging per control step: TraceWriter.write_env_step and friends.

Target: logging one env step (50-float obs, 7-float action) costs <= 20 µs and < 1 % of a
robosuite env step (T1's raw robosuite step: about 6 ms of CPU on the reference box, 130-190
steps/s in bench_worker.py; it was taken as 16 ms before robosuite was measured there).

Each writing case writes to a real MCAP file in a temporary directory with the default
writer settings (lz4, 256 KiB chunks, 1 s flush interval, background flusher on), so chunk
compression and flushes are included. The calls are split into ``--rounds`` rounds run
interleaved across the cases (a shared machine's slow phases then hit every case alike).
In each round, ``steps/rounds`` calls are timed one by one with ``time.perf_counter_ns``
(p50/p99: wall clock, so they include time the OS gave to other processes), then as many
again as a batch: ``cpu_mean_us`` is process CPU time / calls (all threads, so the
background flusher counts; immune to other processes; flushes and compression amortised),
the median over rounds. "best round" columns are the least disturbed round. The env-step
share uses the CPU mean.

Cases:
- ``env_step``: the runtime loop: this step's obs is the previous step's next_obs tuple.
- ``env_step_fresh``: every vector is a new tuple (no encoding reuse).
- ``env_step_record+write``: ``env_step`` plus building the record from numpy arrays
  (``tuple(arr.tolist())``), what the runtime pays in total.
- ``env_step_zstd`` / ``env_step_nocompress``: other chunk compressions.
- ``encode_only`` / ``encode_only_fresh``: the fast encoder without MCAP, with and without
  obs reuse; ``encode_json_dumps``: the generic ``json`` path on the same records.
- ``invocation``: ``write_invocation`` with a 50-float input and 7-float output.
- ``env_step_record+write, cold`` / ``invocation, cold``: the same calls with the CPU caches
  flushed before each one (an untimed 48 MB memory sweep, 1.5 x this box's last-level
  cache). That is the state the episode loop finds after each robosuite step, which walks
  megabytes of MuJoCo and Python data: why a trace write costs several times more inside
  the loop (bench_worker.py's breakdown) than in the warm loops above. ``--cold-calls``
  calls each (fewer: every sweep takes milliseconds).

Usage::

    .venv/bin/python benchmarks/bench_traces.py [--steps 20000] [--out-dir benchmarks/results]

Writes ``traces.json`` and ``traces.md`` to the output directory and prints the
markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capevo.registry.records import CapabilitySet
from capevo.runtime.traces import EcmInvocation, EnvStep, Outcome, TraceMetadata, TraceWriter, codec

ENV_STEP_MS = 6.0
TARGET_US = 20.0
OBS_DIM = 50
ACT_DIM = 7


@dataclass(frozen=True, slots=True, kw_only=True)
class CaseResult:
    name: str
    calls: int
    p50_us: float
    p50_best_round_us: float
    p99_us: float
    max_us: float
    mean_us: float
    cpu_mean_us: float
    cpu_mean_best_round_us: float
    bytes_per_call: float | None

    @property
    def share_of_env_step(self) -> float:
        """CPU cost of one call as a share of one env step."""
        return self.cpu_mean_us / (ENV_STEP_MS * 1000.0)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "calls": self.calls,
            "p50_us": round(self.p50_us, 2),
            "p50_best_round_us": round(self.p50_best_round_us, 2),
            "p99_us": round(self.p99_us, 2),
            "max_us": round(self.max_us, 1),
            "mean_us": round(self.mean_us, 2),
            "cpu_mean_us": round(self.cpu_mean_us, 2),
            "cpu_mean_best_round_us": round(self.cpu_mean_best_round_us, 2),
            "cpu_share_of_env_step_pct": round(100 * self.share_of_env_step, 4),
            "bytes_per_call": None if self.bytes_per_call is None else round(self.bytes_per_call, 1),
        }


def metadata() -> TraceMetadata:
    return TraceMetadata.collect(
        run_id="bench",
        task="Lift",
        capability_set=CapabilitySet(revision=1, active={"reach": 1}),
        phi_hash="0" * 64,
        agent_identity_hash="0" * 64,
        seeds=(0,),
    )


def observations(n: int, seed: int = 0) -> np.ndarray:
    """A smooth float32 trajectory, like proprioception (compresses like real obs)."""
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0, 0.01, size=(n + 1, OBS_DIM)), axis=0)
    return walk.astype(np.float32)


def env_step_record(
    i: int, obs: tuple[float, ...], next_obs: tuple[float, ...], action: tuple[float, ...], reward: float = 0.5
) -> EnvStep:
    """The i-th env step of a run of 500-step episodes."""
    return EnvStep(
        episode=i // 500,
        step=i % 500,
        ecm="reach",
        version=3,
        obs=obs,
        action=action,
        reward=reward,
        next_obs=next_obs,
        key_state={"arm0_eef_pos": next_obs[:3]},
    )


def invocation_record(i: int, inputs: tuple[float, ...], output: tuple[float, ...]) -> EcmInvocation:
    return EcmInvocation(
        episode=0,
        step=i,
        ecm="reach",
        version=3,
        input_state=inputs,
        output=output,
        duration_s=0.0004,
        outcome=Outcome.OK,
    )


Call = Callable[[int], object]


@dataclass(slots=True)
class Case:
    """One benchmark case: ``call(i)`` does the i-th operation; ``finish()`` returns bytes/call."""

    name: str
    call: Call
    finish: Callable[[], float | None]
    next_i: int = 0
    per_call_ns: list[int] = dataclasses.field(default_factory=list)
    round_p50_us: list[float] = dataclasses.field(default_factory=list)
    round_wall_us: list[float] = dataclasses.field(default_factory=list)
    round_cpu_us: list[float] = dataclasses.field(default_factory=list)

    def run(self, n: int) -> None:
        for _ in range(n):
            self.call(self.next_i)
            self.next_i += 1

    def timed_round(self, n: int) -> None:
        """n calls timed one by one, then n more timed as a batch (wall and process CPU)."""
        clock = time.perf_counter_ns
        samples = []
        for _ in range(n):
            t0 = clock()
            self.call(self.next_i)
            samples.append(clock() - t0)
            self.next_i += 1
        self.per_call_ns.extend(samples)
        self.round_p50_us.append(statistics.median(samples) / 1000.0)
        # CPU time covers all threads of this process (the background flusher counts) and
        # not the other processes competing for the cores.
        c0, t0 = time.process_time(), time.perf_counter()
        self.run(n)
        self.round_wall_us.append((time.perf_counter() - t0) / n * 1e6)
        self.round_cpu_us.append((time.process_time() - c0) / n * 1e6)

    def result(self) -> CaseResult:
        us = sorted(x / 1000.0 for x in self.per_call_ns)
        return CaseResult(
            name=self.name,
            calls=len(us),
            p50_us=statistics.median(us),
            p50_best_round_us=min(self.round_p50_us),
            p99_us=us[min(len(us) - 1, int(0.99 * len(us)))],
            max_us=us[-1],
            mean_us=statistics.mean(self.round_wall_us),
            cpu_mean_us=statistics.median(self.round_cpu_us),
            cpu_mean_best_round_us=min(self.round_cpu_us),
            bytes_per_call=self.finish(),
        )


def env_step_case(tmp: Path, total: int, *, name: str, compression: str, mode: str) -> Case:
    obs = observations(total)
    obs_t = [tuple(row.tolist()) for row in obs]
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, size=(total, ACT_DIM)).astype(np.float32)
    act_t = [tuple(a.tolist()) for a in actions]
    rewards = rng.normal(size=total).tolist()
    path = tmp / f"{name}.mcap"
    w = TraceWriter(path, metadata(), compression=compression)

    def record(i: int, o: tuple[float, ...], no: tuple[float, ...], a: tuple[float, ...]) -> EnvStep:
        return env_step_record(i, o, no, a, rewards[i])

    if mode == "reuse":  # obs is the previous step's next_obs tuple
        records = [record(i, obs_t[i], obs_t[i + 1], act_t[i]) for i in range(total)]

        def call(i: int) -> None:
            w.write_env_step(records[i])

    elif mode == "fresh":  # every vector a new tuple
        records = [record(i, tuple(obs[i].tolist()), tuple(obs[i + 1].tolist()), act_t[i]) for i in range(total)]

        def call(i: int) -> None:
            w.write_env_step(records[i])

    else:  # "build": the runtime's full cost, numpy arrays -> record -> write
        state = {"obs": tuple(obs[0].tolist())}

        def call(i: int) -> None:
            next_obs = tuple(obs[i + 1].tolist())
            w.write_env_step(record(i, state["obs"], next_obs, tuple(actions[i].tolist())))
            state["obs"] = next_obs

    def finish() -> float:
        w.close()
        return os.path.getsize(path) / w.messages_written

    return Case(name, call, finish)


def encode_cases(total: int) -> list[Case]:
    obs = observations(total)
    records = [
        env_step_record(i, tuple(obs[i].tolist()), tuple(obs[i + 1].tolist()), tuple(obs[i, :ACT_DIM].tolist()))
        for i in range(total)
    ]
    reuse = [dataclasses.replace(r, obs=records[i - 1].next_obs) if i else r for i, r in enumerate(records)]
    fast, fast_fresh = codec.RecordEncoder(), codec.RecordEncoder()
    return [
        Case("encode_only", lambda i: fast.env_step(reuse[i]), lambda: None),
        Case("encode_only_fresh", lambda i: fast_fresh.env_step(records[i]), lambda: None),
        Case("encode_json_dumps", lambda i: codec.encode_dict(records[i].to_dict()), lambda: None),
    ]


def invocation_case(tmp: Path, total: int) -> Case:
    obs = observations(total)
    records = [invocation_record(i, tuple(obs[i].tolist()), tuple(obs[i, :ACT_DIM].tolist())) for i in range(total)]
    path = tmp / "invocation.mcap"
    w = TraceWriter(path, metadata())

    def finish() -> float:
        w.close()
        return os.path.getsize(path) / w.messages_written

    return Case("invocation", lambda i: w.write_invocation(records[i]), finish)


def cold_cases(tmp: Path, calls: int, sweep_mb: int) -> list[CaseResult]:
    """The record+write and invocation paths, each call timed after flushing the caches."""
    sweep = np.zeros(sweep_mb * 1024 * 1024 // 8)
    obs = observations(calls)
    actions = np.random.default_rng(2).uniform(-1, 1, size=(calls, ACT_DIM))
    step_writer = TraceWriter(tmp / "cold_env_step.mcap", metadata())
    call_writer = TraceWriter(tmp / "cold_invocation.mcap", metadata())
    state = {"obs": tuple(obs[0].tolist())}

    def env_step(i: int) -> None:
        next_obs = tuple(obs[i + 1].tolist())
        step_writer.write_env_step(env_step_record(i, state["obs"], next_obs, tuple(actions[i].tolist())))
        state["obs"] = next_obs

    def invocation(i: int) -> None:
        call_writer.write_invocation(invocation_record(i, tuple(obs[i].tolist()), tuple(actions[i].tolist())))

    out = []
    for name, fn, writer in (
        ("env_step_record+write, cold", env_step, step_writer),
        ("invocation, cold", invocation, call_writer),
    ):
        wall_ns: list[int] = []
        cpu_s: list[float] = []
        for i in range(calls):
            sweep += 1.0  # evict: the call below finds its code and data in DRAM
            c0, t0 = time.process_time(), time.perf_counter_ns()
            fn(i)
            wall_ns.append(time.perf_counter_ns() - t0)
            cpu_s.append(time.process_time() - c0)
        writer.close()
        us = sorted(x / 1000.0 for x in wall_ns)
        cpu_us = statistics.mean(cpu_s) * 1e6
        out.append(
            CaseResult(
                name=name,
                calls=calls,
                p50_us=statistics.median(us),
                p50_best_round_us=statistics.median(us),
                p99_us=us[min(len(us) - 1, int(0.99 * len(us)))],
                max_us=us[-1],
                mean_us=statistics.mean(us),
                cpu_mean_us=cpu_us,
                cpu_mean_best_round_us=cpu_us,
                bytes_per_call=os.path.getsize(writer.path) / writer.messages_written,
            )
        )
    return out


def markdown(results: list[CaseResult], env: dict[str, Any]) -> str:
    lines = [
        f"Trace logging cost: {env['calls']} timed calls per case in {env['rounds']} interleaved rounds; "
        f"Python {env['python']}, {env['cpus']} CPUs, load average {env['load_avg']} at start; "
        f"reference env step {ENV_STEP_MS:.0f} ms; target <= {TARGET_US:.0f} µs.",
        "",
        "| case | p50 µs | best-round p50 µs | p99 µs | CPU µs/call | best-round CPU µs/call "
        "| % of env step | bytes/call |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        b = "-" if r.bytes_per_call is None else f"{r.bytes_per_call:.0f}"
        lines.append(
            f"| {r.name} | {r.p50_us:.1f} | {r.p50_best_round_us:.1f} | {r.p99_us:.1f} | {r.cpu_mean_us:.1f} | "
            f"{r.cpu_mean_best_round_us:.1f} | {100 * r.share_of_env_step:.3f} | {b} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--steps", type=int, default=20000, help="timed calls per case (per-call timing)")
    parser.add_argument("--rounds", type=int, default=10, help="interleaved rounds the calls are split into")
    parser.add_argument("--warmup", type=int, default=500)
    parser.add_argument("--cold-calls", type=int, default=1000, help="calls per cold-cache case")
    parser.add_argument("--sweep-mb", type=int, default=48, help="memory swept before each cold call")
    parser.add_argument("--out-dir", type=Path, default=Path(__file__).with_name("results"))
    args = parser.parse_args()
    per_round = max(1, args.steps // args.rounds)
    total = args.warmup + 2 * per_round * args.rounds + 1
    load = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cases = [
            env_step_case(tmp, total, name="env_step", compression="lz4", mode="reuse"),
            env_step_case(tmp, total, name="env_step_fresh", compression="lz4", mode="fresh"),
            env_step_case(tmp, total, name="env_step_record+write", compression="lz4", mode="build"),
            env_step_case(tmp, total, name="env_step_zstd", compression="zstd", mode="reuse"),
            env_step_case(tmp, total, name="env_step_nocompress", compression="none", mode="reuse"),
            *encode_cases(total),
            invocation_case(tmp, total),
        ]
        for case in cases:
            case.run(args.warmup)
        for r in range(args.rounds):
            # Rotate the order so slow phases of a shared machine hit every case alike.
            for case in cases[r % len(cases) :] + cases[: r % len(cases)]:
                case.timed_round(per_round)
        results = [case.result() for case in cases]
        results += cold_cases(tmp, args.cold_calls, args.sweep_mb)
    env = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load_avg": f"{load[0]:.2f}",
        "calls": per_round * args.rounds,
        "rounds": args.rounds,
        "obs_dim": OBS_DIM,
        "action_dim": ACT_DIM,
        "env_step_ms": ENV_STEP_MS,
        "target_us": TARGET_US,
        "cold_calls": args.cold_calls,
        "sweep_mb": args.sweep_mb,
        "unix_time": round(time.time()),
    }
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / "traces.json").write_text(
        json.dumps({"env": env, "results": [r.to_dict() for r in results]}, indent=2) + "\n"
    )
    table = markdown(results, env)
    (args.out_dir / "traces.md").write_text(table)
    print(table)


if __name__ == "__main__":
    main()
