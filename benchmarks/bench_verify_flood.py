"""capevo verify-flood benchmark: resolve latency with and without concurrent ``verify`` loops.

``verify`` re-hashes every blob the registry holds; any role may ask for it. This measures
whether a client flooding it can starve everyone else (issue 22): a secured registry server
runs in its own process (loopback TCP, multicast scouting off, Zenoh usrpwd + access
control), ``flooders`` spawned processes run ``loops`` threads between them, each calling
``verify`` in a tight loop as user ``flood`` (a reader), and this process resolves the active
version ``n_resolve`` times as user ``probe`` (another reader), first with no flood, then
during it.

Measured: resolve p50/p99/max with and without the flood, resolves refused (any
``CapevoError``, e.g. ``unavailable: registry busy``), and how the flood fared (verifies
answered, refused busy, other errors).

Prints a markdown table and saves ``benchmarks/results/verify_flood.json``.

Run::

    .venv/bin/python benchmarks/bench_verify_flood.py [--loops 70] [--n-resolve 500] [--blob-mib 4]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import free_tcp_port, markdown_table, save_results, summarize_ms  # noqa: E402
from bench_registry import start_server, stop_server  # noqa: E402

from capevo.errors import CapevoError  # noqa: E402
from capevo.registry.client import Client  # noqa: E402
from capevo.registry.descriptor import parse_publish_spec  # noqa: E402

NAME = "flood"
SPEC = parse_publish_spec("kind: neural\ndescription: verify flood benchmark payload\n")
MIB = 1 << 20
PASSWORDS = {"op": "op-secret", "flood": "flood-secret", "probe": "probe-secret"}
CONFIG = f"""
users:
  op: {{password: {PASSWORDS["op"]}, roles: [operator]}}
  flood: {{password: {PASSWORDS["flood"]}, roles: [reader]}}
  probe: {{password: {PASSWORDS["probe"]}, roles: [reader]}}
"""


def flood(endpoint: str, threads: int, ready: Any, stop: Any, results: Any) -> None:
    """Run ``threads`` tight ``verify`` loops on one session until ``stop``; put a Counter of outcomes.

    Runs in a spawned process (importable by name), so the flood has its own GIL and sessions.
    """
    outcomes: Counter[str] = Counter()
    lock = threading.Lock()
    with Client([endpoint], user="flood", password=PASSWORDS["flood"], timeout=30.0) as client:

        def loop() -> None:
            while not stop.is_set():
                try:
                    client.verify()
                    key = "ok"
                except CapevoError as exc:
                    key = "busy" if "busy" in exc.message else exc.code.value
                with lock:
                    outcomes[key] += 1

        workers = [threading.Thread(target=loop, daemon=True) for _ in range(threads)]
        for w in workers:
            w.start()
        ready.put(threads)
        for w in workers:
            w.join()
    results.put(dict(outcomes))


def resolve_latencies(client: Client, n: int) -> tuple[list[float], list[str]]:
    """Time ``n`` resolves of the active version; failures are kept, not raised."""
    times: list[float] = []
    failures: list[str] = []
    for _ in range(n):
        t0 = time.perf_counter()
        try:
            client.get_version(NAME)
        except CapevoError as exc:
            failures.append(f"{exc.code.value}: {exc.message}"[:200])
            continue
        times.append(time.perf_counter() - t0)
    return times, failures


def _summary(times: list[float], failures: list[str]) -> dict[str, Any]:
    empty = {"n": 0, "p50_ms": float("nan"), "p99_ms": float("nan"), "max_ms": float("nan")}
    return {**(summarize_ms(times) if times else empty), "failures": len(failures)}


def measure(
    *,
    loops: int = 70,
    flooders: int = 2,
    n_resolve: int = 500,
    blobs: int = 8,
    blob_mib: float = 4.0,
    flood_warmup_s: float = 1.0,
) -> dict[str, Any]:
    """Run the benchmark once; returns the figures (see the module docstring).

    Args:
        loops: Concurrent ``verify`` loops in all.
        flooders: Processes the loops are spread over.
        n_resolve: Resolves timed in each phase.
        blobs, blob_mib: Versions published first, so one ``verify`` hashes ``blobs * blob_mib`` MiB.
        flood_warmup_s: How long the flood runs before resolves are timed.
    """
    ctx = multiprocessing.get_context("spawn")
    with tempfile.TemporaryDirectory(prefix="capevo-bench-flood-") as tmp:
        config = Path(tmp) / "registry.yaml"
        config.write_text(CONFIG)
        proc, endpoint = start_server(Path(tmp) / "registry", free_tcp_port(), config=config)
        try:
            with Client([endpoint], user="op", password=PASSWORDS["op"], timeout=60.0) as op:
                for i in range(blobs):
                    op.publish(NAME, i.to_bytes(8, "little") + os.urandom(int(blob_mib * MIB)), SPEC)
                op.promote(NAME, 0)
            with Client([endpoint], user="probe", password=PASSWORDS["probe"], timeout=30.0) as probe:
                resolve_latencies(probe, 20)  # warm-up
                quiet, quiet_failures = resolve_latencies(probe, n_resolve)
                ready, results, stop = ctx.Queue(), ctx.Queue(), ctx.Event()
                shares = [loops // flooders + (1 if i < loops % flooders else 0) for i in range(flooders)]
                children = [
                    ctx.Process(target=flood, args=(endpoint, share, ready, stop, results), daemon=True)
                    for share in shares
                ]
                for child in children:
                    child.start()
                try:
                    for _ in children:
                        ready.get(timeout=60)
                    time.sleep(flood_warmup_s)
                    flooded, flooded_failures = resolve_latencies(probe, n_resolve)
                finally:
                    stop.set()
                outcomes: Counter[str] = Counter()
                for _ in children:
                    outcomes.update(results.get(timeout=120))
                for child in children:
                    child.join(timeout=60)
        finally:
            stop_server(proc)
    return {
        "loops": loops,
        "flooders": flooders,
        "verify_mib": blobs * blob_mib,
        "quiet": _summary(quiet, quiet_failures),
        "flooded": _summary(flooded, flooded_failures),
        "failure_samples": (quiet_failures + flooded_failures)[:5],
        "flood_outcomes": dict(outcomes),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--loops", type=int, default=70)
    parser.add_argument("--flooders", type=int, default=2)
    parser.add_argument("--n-resolve", type=int, default=500)
    parser.add_argument("--blobs", type=int, default=8)
    parser.add_argument("--blob-mib", type=float, default=4.0)
    args = parser.parse_args(argv)
    result = measure(
        loops=args.loops,
        flooders=args.flooders,
        n_resolve=args.n_resolve,
        blobs=args.blobs,
        blob_mib=args.blob_mib,
    )
    rows = [
        [phase, r["n"], f"{r['p50_ms']:.2f}", f"{r['p99_ms']:.2f}", f"{r['max_ms']:.2f}", r["failures"]]
        for phase, r in (("no flood", result["quiet"]), (f"{args.loops} verify loops", result["flooded"]))
    ]
    print(markdown_table(["resolve", "n", "p50 ms", "p99 ms", "max ms", "refused"], rows))
    print(f"\nflood outcomes: {result['flood_outcomes']} (each verify hashes {result['verify_mib']:g} MiB)")
    path = save_results("verify_flood", result)
    print(f"saved {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
