"""capevo registry benchmark: resolve, promote/rollback and artifact throughput, over Zenoh and in process.

Over Zenoh the registry runs as ``python -m capevo registry serve`` in its own process
(loopback TCP, multicast scouting off) and this process is the client
(:class:`capevo.registry.client.Client`). For reference the same operations run against a
:class:`capevo.registry.local.LocalRegistry` in this process.

Measured:

* resolve active version: ``get_version(name)`` (version None = active), N after warm-up;
* promote and rollback, durable (SQLite WAL, ``synchronous=FULL``) and end to end: each
  round publishes a fresh candidate (untimed), promotes it with ``expected_active``
  (timed), and rolls back to the previous version (timed);
* publish and pull of 10 MiB and 64 MiB random artifacts, in MiB/s (each repetition uses
  fresh bytes so content addressing cannot skip the write).

Prints markdown tables and saves ``benchmarks/results/registry.json``.

Run::

    .venv/bin/python benchmarks/bench_registry.py [--n-resolve 2000] [--n-move 200] [--reps 3]
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import free_tcp_port, markdown_table, save_results, summarize_ms, time_calls  # noqa: E402

from capevo.registry.api import Registry  # noqa: E402
from capevo.registry.descriptor import parse_publish_spec  # noqa: E402

NAME = "bench"
SPEC = parse_publish_spec(
    """
kind: neural
description: benchmark policy
interface:
  inputs: [{name: obs, shape: [32]}]
  outputs: [{name: action, shape: [7], low: -1, high: 1}]
"""
)
MIB = 1 << 20
TARGETS = {"resolve_p50_ms": 0.5, "resolve_p99_ms": 2.0, "promote_p50_ms": 5.0}


def start_server(root: Path, port: int, *, config: Path | None = None) -> tuple[subprocess.Popen[str], str]:
    """``capevo registry serve`` on loopback ``port`` (users and roles from ``config``, if given)."""
    endpoint = f"tcp/127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "capevo",
            "registry",
            "serve",
            "--root",
            str(root),
            "--listen",
            endpoint,
            "--no-multicast",
            "--json",
            "--log-level",
            "WARNING",
            *(["--config", str(config)] if config is not None else []),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
        cwd=REPO,
    )
    assert proc.stdout is not None
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if select.select([proc.stdout], [], [], 0.2)[0]:
            line = proc.stdout.readline()
            if line:
                json.loads(line)  # the ready line
                return proc, endpoint
        if proc.poll() is not None:
            break
    proc.kill()
    raise RuntimeError("registry server did not become ready")


def stop_server(proc: subprocess.Popen[str]) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


def artifact(i: int, size: int = 4096) -> bytes:
    return i.to_bytes(8, "little") + os.urandom(size - 8)


def bench_resolve(reg: Registry, n: int, warmup: int) -> dict[str, float]:
    def call(_i: int) -> None:
        v = reg.get_version(NAME)
        if v.version is None:  # pragma: no cover - keeps the result used
            raise RuntimeError

    return summarize_ms(time_calls(call, n, warmup=warmup))


def bench_moves(reg: Registry, n: int, warmup: int) -> tuple[dict[str, float], dict[str, float]]:
    promote_s: list[float] = []
    rollback_s: list[float] = []
    base = reg.get_version(NAME).version
    for i in range(warmup + n):
        cand = reg.publish(NAME, artifact(10_000 + i), SPEC).version
        t0 = time.perf_counter()
        reg.promote(NAME, cand, expected_active=base, reason="bench")
        t1 = time.perf_counter()
        back = reg.rollback(NAME, base, expected_active=cand, reason="bench")
        t2 = time.perf_counter()
        if back.version != base:
            raise RuntimeError(f"rollback landed on v{back.version}, expected v{base}")
        if i >= warmup:
            promote_s.append(t1 - t0)
            rollback_s.append(t2 - t1)
    return summarize_ms(promote_s), summarize_ms(rollback_s)


def bench_transfer(reg: Registry, size_mib: int, reps: int) -> dict[str, Any]:
    size = size_mib * MIB
    pub_s: list[float] = []
    pull_s: list[float] = []
    name = f"blob{size_mib}"
    for r in range(reps + 1):  # the first round is warm-up
        data = os.urandom(size)
        t0 = time.perf_counter()
        v = reg.publish(name, data, SPEC).version
        t1 = time.perf_counter()
        got = reg.get_artifact(name, v)
        t2 = time.perf_counter()
        if len(got) != size:
            raise RuntimeError("short artifact")
        del got, data
        if r > 0:
            pub_s.append(t1 - t0)
            pull_s.append(t2 - t1)

    def mibs(samples: list[float]) -> dict[str, float]:
        rates = [size_mib / s for s in samples]
        return {
            "median_mib_s": statistics.median(rates),
            "min_mib_s": min(rates),
            "max_mib_s": max(rates),
            "median_s": statistics.median(samples),
        }

    return {"size_mib": size_mib, "reps": reps, "publish": mibs(pub_s), "pull": mibs(pull_s)}


def run_suite(reg: Registry, args: argparse.Namespace, label: str) -> dict[str, Any]:
    print(f"[{label}] setup", file=sys.stderr)
    reg.publish(NAME, artifact(0), SPEC)
    reg.publish(NAME, artifact(1), SPEC)
    reg.promote(NAME, 0)
    print(f"[{label}] resolve x{args.n_resolve}", file=sys.stderr)
    resolve = bench_resolve(reg, args.n_resolve, args.warmup)
    print(f"[{label}] promote/rollback x{args.n_move}", file=sys.stderr)
    promote, rollback = bench_moves(reg, args.n_move, warmup=10)
    out: dict[str, Any] = {"resolve_active": resolve, "promote": promote, "rollback": rollback, "transfer": []}
    for size in args.sizes:
        print(f"[{label}] transfer {size} MiB x{args.reps}", file=sys.stderr)
        out["transfer"].append(bench_transfer(reg, size, args.reps))
    return out


def timed_cli(endpoint: str, n: int) -> dict[str, float]:
    """Wall time of whole ``python -m capevo ecm show`` processes (interpreter start included)."""
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}

    def call(_i: int) -> None:
        subprocess.run(
            [sys.executable, "-m", "capevo", "ecm", "show", NAME, "--connect", endpoint, "--json"],
            check=True,
            capture_output=True,
            env=env,
            cwd=REPO,
        )

    return summarize_ms(time_calls(call, n, warmup=1))


_FLOOR_SERVER = """
import sys, threading, zenoh
from capevo.registry.zconfig import router_config
payload = b"x" * int(sys.argv[2])
session = zenoh.open(router_config(listen=[sys.argv[1]]))
q = session.declare_queryable("floor/echo", lambda query: query.reply(query.key_expr, payload))
print("READY", flush=True)
sys.stdin.read()
q.undeclare()
session.close()
"""


def zenoh_floor(n: int, warmup: int, payload_bytes: int) -> dict[str, float]:
    """Round trip of a bare Zenoh get to a queryable in another process that replies at once.

    Same transport, session modes and reply size as a resolve, none of the registry's work:
    the floor under the resolve figure.
    """
    import zenoh

    from capevo.registry.zconfig import client_config

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen(
        [sys.executable, "-c", _FLOOR_SERVER, endpoint, str(payload_bytes)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        if proc.stdout.readline().strip() != "READY":
            raise RuntimeError("floor server did not start")
        session = zenoh.open(client_config(connect=[endpoint]))
        try:

            def call(_i: int) -> None:
                for reply in session.get("floor/echo", timeout=10.0):
                    if reply.ok is None:
                        raise RuntimeError("floor query failed")

            return summarize_ms(time_calls(call, n, warmup=warmup))
        finally:
            session.close()
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        proc.wait(timeout=20)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n-resolve", type=int, default=2000)
    ap.add_argument("--n-move", type=int, default=200, help="promote+rollback rounds")
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--reps", type=int, default=3, help="repetitions per artifact size")
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 64], help="artifact sizes in MiB")
    ap.add_argument("--n-cli", type=int, default=5, help="whole-CLI invocations timed")
    args = ap.parse_args()

    from capevo.registry.client import Client
    from capevo.registry.local import LocalRegistry

    results: dict[str, Any] = {"params": vars(args)}
    with tempfile.TemporaryDirectory(prefix="capevo-bench-registry-") as tmpdir:
        tmp = Path(tmpdir)
        proc, endpoint = start_server(tmp / "served", free_tcp_port())
        try:
            with Client([endpoint], timeout=30.0) as client:
                results["zenoh"] = run_suite(client, args, "zenoh")
                resolve_reply_bytes = len(json.dumps(client.get_version(NAME).to_dict()))
            results["zenoh"]["cli_show_process"] = timed_cli(endpoint, args.n_cli) if args.n_cli else None
        finally:
            results["server_exit_code"] = stop_server(proc)
        with LocalRegistry(tmp / "local") as local:
            results["local"] = run_suite(local, args, "local")
        print("[floor] bare zenoh get", file=sys.stderr)
        results["zenoh_floor_get"] = zenoh_floor(args.n_resolve, args.warmup, resolve_reply_bytes)
        results["zenoh_floor_get"]["reply_bytes"] = resolve_reply_bytes

    z, loc = results["zenoh"], results["local"]
    results["targets"] = TARGETS
    results["meets_targets"] = {
        "resolve_p50": z["resolve_active"]["p50_ms"] <= TARGETS["resolve_p50_ms"],
        "resolve_p99": z["resolve_active"]["p99_ms"] <= TARGETS["resolve_p99_ms"],
        "promote_p50": z["promote"]["p50_ms"] <= TARGETS["promote_p50_ms"],
    }

    rows = []
    for key, label in (
        ("resolve_active", "resolve active version"),
        ("promote", "promote (durable)"),
        ("rollback", "rollback (durable)"),
    ):
        rows.append([label, z[key]["n"], z[key]["p50_ms"], z[key]["p99_ms"], loc[key]["p50_ms"], loc[key]["p99_ms"]])
    f = results["zenoh_floor_get"]
    rows.append([f"bare Zenoh get, {f['reply_bytes']} B reply (floor)", f["n"], f["p50_ms"], f["p99_ms"], "", ""])
    if z.get("cli_show_process"):
        c = z["cli_show_process"]
        rows.append(["`capevo ecm show` whole process", c["n"], c["p50_ms"], c["p99_ms"], "", ""])
    print("\ncapevo registry latency (ms); Zenoh = server in another process over loopback TCP\n")
    print(markdown_table(["operation", "N", "Zenoh p50", "Zenoh p99", "in-process p50", "in-process p99"], rows))

    trows = []
    for zt, lt in zip(z["transfer"], loc["transfer"], strict=True):
        trows.append(
            [
                f"{zt['size_mib']} MiB",
                zt["reps"],
                zt["publish"]["median_mib_s"],
                zt["pull"]["median_mib_s"],
                lt["publish"]["median_mib_s"],
                lt["pull"]["median_mib_s"],
            ]
        )
    print("\nartifact throughput (MiB/s, median of reps)\n")
    print(
        markdown_table(
            ["artifact", "reps", "Zenoh publish", "Zenoh pull", "in-process publish", "in-process pull"], trows
        )
    )
    print(f"\ntargets {TARGETS}: {results['meets_targets']}")
    path = save_results("registry", results)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
