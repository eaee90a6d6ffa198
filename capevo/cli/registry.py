"""``capevo registry ...``: run the registry service and verify a registry's integrity.

Invariants:
1. ``serve`` exits 0 on SIGTERM or SIGINT after the service has closed its Zenoh session.
2. ``verify`` exits 0 only when the report has no problems; otherwise it prints every
   problem and exits with the ``corrupt`` code (8).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
from rich.console import Console

from capevo.cli import (
    DEFAULT_NAMESPACE,
    DEFAULT_ROOT,
    EXIT_CODES,
    RegistryOptions,
    emit,
    json_option,
    log_level_option,
    log_to_stderr,
    make_table,
    registry_options,
    registry_session,
)
from capevo.errors import ErrorCode
from capevo.records import VerifyReport

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


@click.group()
def registry() -> None:
    """Run and check the ECM registry."""


@registry.command("serve")
@click.option(
    "--root",
    type=click.Path(file_okay=False, path_type=Path),
    envvar="CAPEVO_ROOT",
    default=DEFAULT_ROOT,
    show_default=True,
    help="Registry directory (created if missing; env CAPEVO_ROOT).",
)
@click.option(
    "--listen",
    multiple=True,
    metavar="ENDPOINT",
    help=f"Zenoh endpoint to listen on; repeatable. [default: from --config, else {DEFAULT_LISTEN}]",
)
@click.option("--connect", multiple=True, metavar="ENDPOINT", help="Zenoh router to join; repeatable.")
@click.option(
    "--namespace",
    default=None,
    envvar="CAPEVO_NAMESPACE",
    help=f"Zenoh key prefix. [default: from --config, else {DEFAULT_NAMESPACE}]",
)
@click.option(
    "--config",
    "config_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Registry config YAML (users, roles, credentials, endpoints).",
)
@click.option(
    "--multicast/--no-multicast",
    default=None,
    help="Zenoh UDP multicast scouting. [default: from --config, else off]",
)
@click.option(
    "--max-artifact-bytes",
    type=click.IntRange(min=0),
    default=None,
    help="Largest artifact accepted. [default: from --config, else 256 MiB]",
)
@log_level_option(default="INFO", help="Server log level (logs go to stderr).")
@json_option
def serve_cmd(
    root: Path,
    listen: tuple[str, ...],
    connect: tuple[str, ...],
    namespace: str | None,
    config_path: Path | None,
    multicast: bool | None,
    max_artifact_bytes: int | None,
    log_level: str,
    as_json: bool,
) -> None:
    """Serve the registry at --root over Zenoh until SIGTERM or Ctrl-C (then exit 0).

    Once it serves, prints one line on stdout: a summary, or with --json the server info
    (root, namespace, listen, zid, secured, pid) as JSON.
    """
    from capevo.registry.server_config import load_server_config
    from capevo.registry.service import ServeInfo, serve

    log_to_stderr(log_level)

    def announce(info: ServeInfo) -> None:
        if as_json:
            click.echo(json.dumps(info.to_dict()))
        else:
            secured = "access control on" if info.secured else "OPEN (no users configured)"
            click.echo(
                f"capevo registry serving {info.root} on {', '.join(info.listen)} "
                f"(namespace {info.namespace!r}, {secured}, pid {info.pid})"
            )
        sys.stdout.flush()

    config = load_server_config(config_path) if config_path is not None else None
    # None lets the config file (or the service's defaults) decide; explicit flags win.
    serve(
        root,
        listen=list(listen) or None,
        connect=list(connect) or None,
        namespace=namespace,
        config=config,
        ready=announce,
        multicast_scouting=multicast,
        max_artifact_bytes=max_artifact_bytes,
        handle_signals=True,
    )


@registry.command("verify")
@registry_options
def verify_cmd(*, opts: RegistryOptions) -> None:
    """Check the audit hash chain and every blob's sha256; exit 8 on any problem."""
    with registry_session(opts) as reg:
        report = reg.verify()
    emit(opts, report.to_dict(), lambda c: _render_report(c, report))
    if not report.ok:
        raise click.exceptions.Exit(EXIT_CODES[ErrorCode.CORRUPT])


def _render_report(console: Console, report: VerifyReport) -> None:
    status = "OK" if report.ok else f"{len(report.problems)} PROBLEM(S)"
    console.print(f"verify: {status}: {report.events_checked} audit events, {report.blobs_checked} blobs checked")
    if report.problems:
        table = make_table("#", "PROBLEM")
        for i, problem in enumerate(report.problems, 1):
            table.add_row(str(i), problem)
        console.print(table)


@registry.command("demo")
@click.option(
    "--root",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Registry directory to use (default: a fresh temporary one).",
)
@json_option
def demo_cmd(root: Path | None, as_json: bool) -> None:
    """Round trip over real Zenoh: serve a registry, publish, promote twice, roll back, print the history."""
    import tempfile

    from capevo.cli.ecm import _render_history
    from capevo.registry.roundtrip import DEMO_ECM, run_round_trip

    with tempfile.TemporaryDirectory(prefix="capevo-demo-") as scratch:
        result = run_round_trip(root if root is not None else scratch)

    def render(console: Console) -> None:
        console.print(f"registry served at {result.endpoint}; client published, promoted and rolled back {DEMO_ECM}")
        _render_history(console, DEMO_ECM, list(result.history))
        console.print(f"active version after rollback: v{result.active_version}")

    emit(
        as_json,
        {
            "endpoint": result.endpoint,
            "active_version": result.active_version,
            "history": [e.to_dict() for e in result.history],
        },
        render,
    )
