"""capevo resolve against a raw Zenoh get, with 1, 4 and 16 client processes, and against MLflow.

Issue 21: resolving an ECM's active version is the registry's most frequent job, so its floor
is a bare Zenoh get. In one run this measures, for each client count, side by side and
alternating:

* **raw Zenoh get**: a queryable in its own process (router mode, loopback TCP) that replies
  the very bytes a resolve replies, asked by client-mode sessions that only take the payload;
* **capevo resolve**: ``Client.get_version(name)`` (version None = active) against
  ``capevo registry serve`` in its own process, decoded into an :class:`EcmVersion`;

each client a spawned process of its own that calls in a closed loop for ``--seconds``
(throughput = calls completed by all of them / seconds; p50 and p99 over every call). Then:

* **reads during 64 MiB sends**: one process resolves while another publishes fresh 64 MiB
  artifacts back to back, against resolves with no publish; and, as the floor, one process
  does raw gets while another sends 64 MiB queries to a raw queryable that replies without
  reading them (what moving the bytes alone costs the reads on this machine);
* **MLflow's alias resolve** (``bench_mlflow.py``), when an interpreter with mlflow is given
  (``--mlflow-python``; mlflow is the ``bench`` extra, best kept in a venv of its own).

Prints markdown tables and saves ``benchmarks/results/registry_clients.json`` (MLflow's own
figures: ``mlflow_resolve_clients.json``).

Run::

    .venv/bin/python benchmarks/bench_resolve_clients.py [--clients 1 4 16] [--seconds 5]
        [--mlflow-python /path/to/venv-with-mlflow/bin/python]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import free_tcp_port, load_results, markdown_table, percentile, save_results  # noqa: E402
from bench_registry import NAME, SPEC, artifact, start_server, stop_server  # noqa: E402

RAW_KEY = "floor/echo"
RAW_SINK_KEY = "floor/sink"
MIB = 1 << 20
SPAWN = mp.get_context("spawn")  # never fork a process that may hold a Zenoh session
GOALS = {"single_client_p50_vs_raw_max": 1.3, "clients16_throughput_vs_raw_min": 0.8, "vs_mlflow_min": 30.0}

_RAW_SERVER = """
import sys, zenoh
from capevo.registry.zconfig import router_config
payload = open(sys.argv[2], "rb").read()
session = zenoh.open(router_config(listen=[sys.argv[1]]))
q = session.declare_queryable(sys.argv[3], lambda query: query.reply(query.key_expr, payload))
# takes 64 MiB queries without reading them: the transport's own cost, nothing of Python's
sink = session.declare_queryable(sys.argv[4], lambda query: query.reply(query.key_expr, b""))
print("READY", flush=True)
sys.stdin.read()
sink.undeclare()
q.undeclare()
session.close()
"""


def start_raw_server(endpoint: str, reply: bytes, tmp: Path) -> subprocess.Popen[str]:
    """The raw floor: a queryable replying ``reply`` at once, in its own process."""
    body = tmp / "raw-reply.json"
    body.write_bytes(reply)
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen(
        [sys.executable, "-c", _RAW_SERVER, endpoint, str(body), RAW_KEY, RAW_SINK_KEY],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    if proc.stdout.readline().strip() != "READY":
        raise RuntimeError("raw Zenoh server did not start")
    return proc


def reader(kind: str, endpoint: str, *, timeout: float) -> tuple[Callable[[], None], Callable[[], None]]:
    """``(call, close)``: one read of the record-sized reply, ``raw`` (a bare Zenoh get, the
    payload taken) or ``capevo`` (``Client.get_version``, decoded into an EcmVersion)."""
    if kind == "raw":
        import zenoh

        from capevo.registry.zconfig import client_config

        session = zenoh.open(client_config(connect=[endpoint]))

        def raw_call() -> None:
            for reply in session.get(RAW_KEY, timeout=timeout):
                if reply.ok is None:
                    raise RuntimeError("raw query failed")
                reply.ok.payload.to_bytes()

        return raw_call, session.close
    from capevo.registry.client import Client

    client = Client([endpoint], timeout=timeout)

    def capevo_call() -> None:
        client.get_version(NAME)

    return capevo_call, client.close


def client_loop(kind: str, endpoint: str, seconds: float, warmup: int, ready: Any, go: Any, results: Any) -> None:
    """One client process: warm up, wait for ``go``, call in a closed loop for ``seconds``.

    Puts ``(latencies_s, error)`` on ``results``. Importable by name for ``spawn``.
    """
    latencies: list[float] = []
    try:
        call, close = reader(kind, endpoint, timeout=10.0)
        try:
            for _ in range(warmup):
                call()
            ready.put(os.getpid())
            go.wait(120)
            clock = time.perf_counter
            end = clock() + seconds
            while True:
                t0 = clock()
                if t0 >= end:
                    break
                call()
                latencies.append(clock() - t0)
        finally:
            close()
        results.put((latencies, None))
    except Exception as exc:  # reported to the parent, which fails on it
        results.put((latencies, f"{type(exc).__name__}: {exc}"))


def run_clients(kind: str, endpoint: str, n: int, seconds: float, warmup: int) -> dict[str, Any]:
    """``n`` client processes of ``kind`` released together; their pooled figures."""
    ready, go, results = SPAWN.Queue(), SPAWN.Event(), SPAWN.Queue()
    procs = [
        SPAWN.Process(target=client_loop, args=(kind, endpoint, seconds, warmup, ready, go, results)) for _ in range(n)
    ]
    for p in procs:
        p.start()
    try:
        for _ in procs:
            ready.get(timeout=180)
        go.set()
        outcomes = [results.get(timeout=seconds + 120) for _ in procs]
    finally:
        for p in procs:
            p.join(timeout=30)
            if p.is_alive():
                p.kill()
    errors = [err for _, err in outcomes if err]
    if errors:
        raise RuntimeError(f"{kind} clients failed: {errors[:3]}")
    ms = [s * 1000.0 for lat, _ in outcomes for s in lat]
    return {
        "clients": n,
        "calls": len(ms),
        "seconds": seconds,
        "throughput_per_s": len(ms) / seconds,
        "p50_ms": percentile(ms, 50),
        "p99_ms": percentile(ms, 99),
    }


def during_big_sends(kind: str, endpoint: str, seconds: float) -> dict[str, Any]:
    """Closed-loop latency of one client with nothing else going on, then while another process
    sends 64 MiB back to back to the same server.

    ``capevo``: resolves while fresh 64 MiB artifacts are published (``Client.publish``, in parts).
    ``raw``: raw gets of the record-sized reply while 64 MiB queries go to a raw queryable that
    replies without reading them: what the transport alone costs the reads on this machine.
    """
    call, close = reader(kind, endpoint, timeout=30.0)

    def loop(until: float) -> list[float]:
        out: list[float] = []
        while time.perf_counter() < until:
            t0 = time.perf_counter()
            call()
            out.append((time.perf_counter() - t0) * 1000.0)
        return out

    try:
        loop(time.perf_counter() + 0.5)  # warm-up
        quiet = loop(time.perf_counter() + seconds)
        channel = SPAWN.Queue()
        sender = SPAWN.Process(target=send_loop, args=(kind, endpoint, seconds, channel))
        sender.start()
        started = channel.get(timeout=120)
        if started != "started":
            raise RuntimeError(f"sender failed: {started}")
        busy = loop(time.perf_counter() + seconds)
        outcome = channel.get(timeout=seconds + 300)
        sender.join(timeout=30)
    finally:
        close()
    if isinstance(outcome, str):
        raise RuntimeError(f"sender failed: {outcome}")

    def summary(ms: list[float]) -> dict[str, float]:
        return {"n": len(ms), "p50_ms": percentile(ms, 50), "p99_ms": percentile(ms, 99), "max_ms": max(ms)}

    return {"quiet": summary(quiet), "during_64mib_sends": summary(busy), "sends": len(outcome), "send_s": outcome}


def send_loop(kind: str, endpoint: str, seconds: float, out: Any) -> None:
    """Send fresh 64 MiB back to back for ``seconds`` (capevo: publish; raw: a query to the sink);
    put their durations (s). Importable by name for ``spawn``."""
    try:
        data = bytearray(os.urandom(64 * MIB))
        durations: list[float] = []
        if kind == "raw":
            import zenoh

            from capevo.registry.zconfig import client_config

            session = zenoh.open(client_config(connect=[endpoint]))

            def send(body: bytes) -> None:
                for reply in session.get(RAW_SINK_KEY, payload=body, timeout=120.0):
                    if reply.ok is None:
                        raise RuntimeError("raw send failed")

            close = session.close
        else:
            from capevo.registry.client import Client

            client = Client([endpoint], timeout=120.0)

            def send(body: bytes) -> None:
                client.publish("big", body, SPEC)

            close = client.close
        try:
            out.put("started")
            end = time.perf_counter() + seconds
            i = 0
            while time.perf_counter() < end:
                data[:8] = i.to_bytes(8, "little")  # fresh bytes: content addressing cannot skip the write
                t0 = time.perf_counter()
                send(bytes(data))
                durations.append(time.perf_counter() - t0)
                i += 1
        finally:
            close()
        out.put(durations)
    except Exception as exc:
        out.put(f"{type(exc).__name__}: {exc}")


def mlflow_resolve(python: str, n: int) -> dict[str, Any] | None:
    """MLflow's alias resolve, by ``bench_mlflow.py`` under ``python`` (an interpreter with mlflow)."""
    script = Path(__file__).resolve().parent / "bench_mlflow.py"
    out = "mlflow_resolve_clients"
    done = subprocess.run([python, str(script), "--n", str(n), "--out", out], capture_output=True, text=True)
    if done.returncode != 0:
        print(done.stdout[-2000:], done.stderr[-4000:], file=sys.stderr)
        return None
    result = load_results(out)
    return None if result is None else {"version": result["mlflow_version"], **result["alias_resolve"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--seconds", type=float, default=5.0, help="closed-loop time per measurement")
    ap.add_argument("--warmup", type=int, default=200, help="untimed calls per client before the run")
    ap.add_argument("--rounds", type=int, default=2, help="raw/capevo alternations per client count")
    ap.add_argument("--publish-seconds", type=float, default=6.0, help="0 skips resolves during publishes")
    ap.add_argument("--mlflow-python", help="python of a venv with mlflow; omitted: no MLflow row")
    ap.add_argument("--mlflow-n", type=int, default=500)
    ap.add_argument("--out", default="registry_clients")
    args = ap.parse_args(argv)

    from capevo.registry.local import LocalRegistry
    from capevo.registry.wire import dumps

    results: dict[str, Any] = {"params": vars(args), "goals": GOALS, "load_before": list(os.getloadavg())}
    with tempfile.TemporaryDirectory(prefix="capevo-bench-resolve-") as tmpdir:
        tmp = Path(tmpdir)
        root = tmp / "registry"
        with LocalRegistry(root) as local:
            local.publish(NAME, artifact(0), SPEC)
            local.publish(NAME, artifact(1), SPEC)
            reply = dumps(local.promote(NAME, 0).to_dict())
        results["reply_bytes"] = len(reply)
        raw_endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        raw = start_raw_server(raw_endpoint, reply, tmp)
        server, endpoint = start_server(root, free_tcp_port())
        try:
            rows: list[dict[str, Any]] = []
            for n in args.clients:
                per: dict[str, list[dict[str, Any]]] = {"raw": [], "capevo": []}
                for r in range(args.rounds):
                    # Alternate which goes first, so drifting machine load hits both alike.
                    order = ("raw", "capevo") if r % 2 == 0 else ("capevo", "raw")
                    for kind in order:
                        print(f"[{n} clients] {kind} round {r + 1}", file=sys.stderr)
                        per[kind].append(
                            run_clients(kind, raw_endpoint if kind == "raw" else endpoint, n, args.seconds, args.warmup)
                        )
                rows.append({"clients": n, **{k: _pooled(v) for k, v in per.items()}, "rounds": per})
            results["by_clients"] = rows
            if args.publish_seconds > 0:
                during: dict[str, Any] = {}
                for kind in ("raw", "capevo"):
                    print(f"[64 MiB sends] {kind}", file=sys.stderr)
                    during[kind] = during_big_sends(
                        kind, raw_endpoint if kind == "raw" else endpoint, args.publish_seconds
                    )
                results["during_64mib_sends"] = during
        finally:
            assert raw.stdin is not None
            raw.stdin.close()
            raw.wait(timeout=20)
            results["server_exit_code"] = stop_server(server)
    if args.mlflow_python:
        print("[mlflow] alias resolve", file=sys.stderr)
        results["mlflow_alias_resolve"] = mlflow_resolve(args.mlflow_python, args.mlflow_n)
    results["load_after"] = list(os.getloadavg())
    _report(results)
    path = save_results(args.out, results)
    print(f"saved {path}")
    return 0


def _pooled(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Median of the rounds' throughputs and percentiles (each round is one closed-loop run)."""

    def mid(key: str) -> float:
        xs = sorted(r[key] for r in rounds)
        return xs[len(xs) // 2] if len(xs) % 2 else (xs[len(xs) // 2 - 1] + xs[len(xs) // 2]) / 2

    return {k: mid(k) for k in ("throughput_per_s", "p50_ms", "p99_ms")}


def _report(results: dict[str, Any]) -> None:
    table = []
    for row in results["by_clients"]:
        raw, cap = row["raw"], row["capevo"]
        table.append(
            [
                row["clients"],
                f"{raw['throughput_per_s']:.0f}/s, p50 {raw['p50_ms']:.2f}, p99 {raw['p99_ms']:.2f}",
                f"{cap['throughput_per_s']:.0f}/s, p50 {cap['p50_ms']:.2f}, p99 {cap['p99_ms']:.2f}",
                f"{100 * cap['throughput_per_s'] / raw['throughput_per_s']:.0f} %",
                f"{cap['p50_ms'] / raw['p50_ms']:.2f}×",
            ]
        )
    print(f"\nresolve vs raw Zenoh get ({results['reply_bytes']} B reply), ms\n")
    print(markdown_table(["clients", "raw Zenoh get", "capevo resolve", "throughput vs raw", "p50 vs raw"], table))
    one = next((r for r in results["by_clients"] if r["clients"] == 1), None)
    many = next((r for r in results["by_clients"] if r["clients"] == 16), None)
    met: dict[str, Any] = {}
    if one:
        met["single_client_p50_vs_raw"] = one["capevo"]["p50_ms"] / one["raw"]["p50_ms"]
    if many:
        met["clients16_throughput_vs_raw"] = many["capevo"]["throughput_per_s"] / many["raw"]["throughput_per_s"]
    during = results.get("during_64mib_sends")
    if during:
        rows = []
        for kind, what in (
            ("raw", "raw Zenoh get, 64 MiB raw queries to a sink"),
            ("capevo", "capevo resolve, 64 MiB publishes"),
        ):
            d = during[kind]
            q, b = d["quiet"], d["during_64mib_sends"]
            rows.append([what, "none", q["n"], q["p50_ms"], q["p99_ms"], q["max_ms"]])
            rows.append([what, f"{d['sends']} back to back", b["n"], b["p50_ms"], b["p99_ms"], b["max_ms"]])
        print("\none client's reads, alone and while another process sends 64 MiB (ms)\n")
        print(markdown_table(["reads", "64 MiB sends", "N", "p50", "p99", "max"], rows))
    ml = results.get("mlflow_alias_resolve")
    if ml and one:
        met["vs_mlflow"] = ml["p50_ms"] / one["capevo"]["p50_ms"]
        print(f"\nMLflow {ml['version']} alias resolve p50 {ml['p50_ms']:.2f} ms, p99 {ml['p99_ms']:.2f} ms")
    results["measured_against_goals"] = met
    print(f"\ngoals {GOALS}\nmeasured {json.dumps(met)}")


if __name__ == "__main__":
    sys.exit(main())
