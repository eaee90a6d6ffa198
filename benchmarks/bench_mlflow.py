"""MLflow model-registry baseline: alias resolve and alias set against a local ``mlflow server``.

Starts ``mlflow server`` as a subprocess on a loopback port with a SQLite backend store and
a temporary artifact root, registers one model with a few versions, then times

* ``MlflowClient.get_model_version_by_alias`` (the equivalent of resolving capevo's active
  version), N calls after warm-up;
* ``MlflowClient.set_registered_model_alias`` (the equivalent of a promote), N calls
  alternating between versions.

Prints a markdown table, saves ``benchmarks/results/mlflow.json`` and, when
``benchmarks/results/registry.json`` exists, the capevo/MLflow ratio.

Run::

    .venv/bin/pip install mlflow            # the optional ``bench`` extra
    .venv/bin/python benchmarks/bench_mlflow.py [--n 500] [--n-set 500] [--workers 1]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    free_tcp_port,
    load_results,
    markdown_table,
    save_results,
    summarize_ms,
    time_calls,
    wait_for_port,
)

MODEL = "capevo-bench-model"
ALIAS = "champion"


def start_server(tmp: Path, port: int, workers: int) -> subprocess.Popen[bytes]:
    mlflow_bin = Path(sys.executable).with_name("mlflow")
    cmd = [
        str(mlflow_bin),
        "server",
        "--backend-store-uri",
        f"sqlite:///{tmp / 'mlflow.db'}",
        "--default-artifact-root",
        str(tmp / "artifacts"),
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
        "--workers",
        str(workers),
    ]
    log = open(tmp / "server.log", "wb")  # noqa: SIM115 - lives as long as the server
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def stop_server(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=500, help="timed alias resolves")
    ap.add_argument("--n-set", type=int, default=500, help="timed alias sets")
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument("--versions", type=int, default=5)
    ap.add_argument("--workers", type=int, default=1, help="mlflow server worker processes")
    ap.add_argument("--out", default="mlflow", help="results name: benchmarks/results/<out>.json")
    args = ap.parse_args()

    os.environ.setdefault("MLFLOW_ENABLE_ASYNC_LOGGING", "false")
    from mlflow import __version__ as mlflow_version
    from mlflow.tracking import MlflowClient

    with tempfile.TemporaryDirectory(prefix="capevo-bench-mlflow-") as tmpdir:
        tmp = Path(tmpdir)
        (tmp / "artifacts").mkdir()
        port = free_tcp_port()
        proc = start_server(tmp, port, args.workers)
        try:
            wait_for_port(port, timeout=120, proc=proc)
            uri = f"http://127.0.0.1:{port}"
            client = MlflowClient(tracking_uri=uri, registry_uri=uri)
            _wait_ready(client)

            client.create_registered_model(MODEL)
            versions = []
            for i in range(args.versions):
                src = tmp / "artifacts" / f"model-{i}"
                src.mkdir()
                (src / "MLmodel").write_text("artifact_path: model\n")
                # The server accepts a local source only inside a run's artifact directory.
                run = client.create_run("0")
                client.log_artifacts(run.info.run_id, str(src), "model")
                client.set_terminated(run.info.run_id)
                mv = client.create_model_version(MODEL, source=f"{run.info.artifact_uri}/model", run_id=run.info.run_id)
                versions.append(int(mv.version))
            client.set_registered_model_alias(MODEL, ALIAS, str(versions[-1]))

            resolve = time_calls(lambda _i: client.get_model_version_by_alias(MODEL, ALIAS), args.n, warmup=args.warmup)
            set_alias = time_calls(
                lambda i: client.set_registered_model_alias(MODEL, ALIAS, str(versions[i % len(versions)])),
                args.n_set,
                warmup=min(args.warmup, 10),
            )
            got = client.get_model_version_by_alias(MODEL, ALIAS)
            assert int(got.version) in versions
        finally:
            stop_server(proc)

    res_resolve = summarize_ms(resolve)
    res_set = summarize_ms(set_alias)
    payload = {
        "mlflow_version": mlflow_version,
        "server": {"backend": "sqlite", "workers": args.workers, "transport": "http loopback"},
        "versions": args.versions,
        "warmup": args.warmup,
        "alias_resolve": res_resolve,
        "alias_set": res_set,
    }
    rows = [
        ["alias resolve (get_model_version_by_alias)", res_resolve["n"], res_resolve["p50_ms"], res_resolve["p99_ms"]],
        ["alias set (set_registered_model_alias)", res_set["n"], res_set["p50_ms"], res_set["p99_ms"]],
    ]
    print(f"\nMLflow {mlflow_version} model registry, `mlflow server` (SQLite, {args.workers} worker) on loopback\n")
    print(markdown_table(["operation", "N", "p50 ms", "p99 ms"], rows))

    capevo = load_results("registry")
    if capevo is not None:
        ratios = _ratios(capevo, res_resolve, res_set)
        payload["ratio_vs_capevo"] = ratios
        if ratios:
            print("\ncapevo (Zenoh) vs MLflow, p50 speed-up = MLflow p50 / capevo p50\n")
            print(
                markdown_table(
                    ["operation", "capevo p50 ms", "MLflow p50 ms", "speed-up x"],
                    [[k, v["capevo_p50_ms"], v["mlflow_p50_ms"], v["speedup"]] for k, v in ratios.items()],
                )
            )
    path = save_results(args.out, payload)
    print(f"\nsaved {path}")


def _ratios(capevo: dict, resolve: dict[str, float], set_alias: dict[str, float]) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    zen = capevo.get("zenoh", {})
    pairs = [("resolve active vs alias resolve", zen.get("resolve_active"), resolve)]
    pairs.append(("promote vs alias set", zen.get("promote"), set_alias))
    for label, ours, theirs in pairs:
        if ours:
            out[label] = {
                "capevo_p50_ms": ours["p50_ms"],
                "mlflow_p50_ms": theirs["p50_ms"],
                "speedup": theirs["p50_ms"] / ours["p50_ms"],
            }
    return out


def _wait_ready(client: object, timeout: float = 120.0) -> None:
    # The port opens before the app has finished importing; poll a cheap call.
    deadline = time.monotonic() + timeout
    last: Exception | None = None
    while time.monotonic() < deadline:
        try:
            client.search_registered_models(max_results=1)  # type: ignore[attr-defined]
            return
        except Exception as exc:  # the server answers 5xx/connection errors while booting
            last = exc
            time.sleep(0.25)
    raise TimeoutError(f"mlflow server not ready: {last}")


if __name__ == "__main__":
    main()
