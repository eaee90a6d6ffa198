"""``capevo ecm ...``: read, publish and move ECM versions in a registry.

Invariants:
1. Every NAME argument is checked with :func:`validate_name` before the registry is opened,
   so a bad name fails the same way (``invalid``, exit 3) locally and over Zenoh.
2. ``pull`` writes the output file atomically (temporary file in the same directory, fsync,
   rename): the target is either untouched or holds the complete artifact, whose sha256
   matches the version record (otherwise :class:`Corrupt`, and nothing is written).
3. ``publish`` never opens the registry when the descriptor or the artifact file is bad.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import secrets
import sys
from pathlib import Path
from typing import Any

import click
from rich.console import Console

from capevo.cli import (
    RegistryOptions,
    emit,
    fmt_bytes,
    fmt_opt,
    fmt_time,
    make_table,
    progress,
    registry_options,
    registry_session,
)
from capevo.errors import CapevoError, Corrupt, Invalid
from capevo.records import AuditEvent, CapabilitySet, EcmDetail, EcmSummary, EcmVersion, IOSpec, State
from capevo.records.names import validate_name
from capevo.registry.descriptor import parse_publish_spec
from capevo.storage.blobs import fsync_dir

# Above this size publish/pull show a spinner on a terminal.
_PROGRESS_BYTES = 4 * 1024 * 1024

_VERSION = click.IntRange(min=0)


@click.group()
def ecm() -> None:
    """Embodied Capability Modules: list, show, publish, promote, roll back, pull."""


# ---------------------------------------------------------------------------------------
# Reads
# ---------------------------------------------------------------------------------------


@ecm.command("list")
@registry_options
def list_cmd(*, opts: RegistryOptions) -> None:
    """List every ECM with its active and latest version."""
    with registry_session(opts) as reg:
        rows = reg.list_ecms()
    emit(opts, [r.to_dict() for r in rows], lambda c: _render_list(c, rows))


def _render_list(console: Console, rows: list[EcmSummary]) -> None:
    if not rows:
        console.print("no ECMs")
        return
    table = make_table("NAME", "ACTIVE", "LATEST", "VERSIONS")
    for r in rows:
        table.add_row(r.name, _v(r.active_version), _v(r.latest_version), str(r.n_versions))
    console.print(table)


@ecm.command("show")
@click.argument("name")
@click.option("--version", "version", type=_VERSION, default=None, help="Show this version's full record.")
@registry_options
def show_cmd(name: str, version: int | None, *, opts: RegistryOptions) -> None:
    """Show an ECM with all its versions (active marked), or one version's record."""
    validate_name(name)
    with registry_session(opts) as reg:
        if version is not None:
            record = reg.get_version(name, version)
            emit(opts, record.to_dict(), lambda c: _render_version(c, record))
            return
        detail = reg.get_ecm(name)
    emit(opts, detail.to_dict(), lambda c: _render_detail(c, detail))


def _render_detail(console: Console, detail: EcmDetail) -> None:
    active = _v(detail.active_version) if detail.active_version is not None else "none"
    table = make_table(
        "",
        "VERSION",
        "STATE",
        "KIND",
        "PARENT",
        "ORIGIN",
        "SIZE",
        "SHA256",
        "CREATED",
        "BY",
    )
    console.print(f"{detail.name}  (active: {active})")
    for v in detail.versions:
        mark = "*" if v.version == detail.active_version else ""
        table.add_row(
            mark,
            _v(v.version),
            v.state.value,
            v.kind.value,
            _v(v.parent),
            v.origin.value,
            fmt_bytes(v.artifact.size),
            v.artifact.sha256[:12],
            fmt_time(v.created_at),
            v.created_by,
        )
    console.print(table)
    if detail.active_version is not None:
        console.print("* active version")


def _render_version(console: Console, v: EcmVersion) -> None:
    console.print(f"{v.name} {_v(v.version)}")
    table = make_table("FIELD", "VALUE")
    rows: list[tuple[str, str]] = [
        ("name", v.name),
        ("version", str(v.version)),
        ("state", v.state.value),
        ("kind", v.kind.value),
        ("origin", v.origin.value),
        ("parent", fmt_opt(v.parent)),
        ("artifact.sha256", v.artifact.sha256),
        ("artifact.size", f"{v.artifact.size} ({fmt_bytes(v.artifact.size)})"),
        ("artifact.media_type", v.artifact.media_type),
        ("description", v.descriptor.description),
        ("applicability", _predicate(v.descriptor.applicability.text, v.descriptor.applicability.all)),
        ("termination", _predicate(v.descriptor.termination.text, v.descriptor.termination.all)),
        ("inputs", _io(v.interface.inputs)),
        ("outputs", _io(v.interface.outputs)),
        ("provenance.learner_id", fmt_opt(v.provenance.learner_id)),
        ("provenance.config_hash", fmt_opt(v.provenance.config_hash)),
        ("provenance.traces", ", ".join(v.provenance.traces) or "-"),
        ("gate_evidence", _mapping(v.gate_evidence)),
        ("created", f"{fmt_time(v.created_at)} by {v.created_by}"),
    ]
    for key, value in rows:
        table.add_row(key, value)
    console.print(table)


def _predicate(text: str, conds: Any) -> str:
    parts = [f"{c.signal} {c.op} {c.value:g}" for c in conds]
    body = " and ".join(parts)
    if text and body:
        return f"{text}  [{body}]"
    return text or body or "-"


def _io(specs: tuple[IOSpec, ...]) -> str:
    if not specs:
        return "-"
    out = []
    for s in specs:
        shape = "x".join(str(d) for d in s.shape) or "scalar"
        bounds = f" [{fmt_opt(s.low)}, {fmt_opt(s.high)}]" if s.low is not None or s.high is not None else ""
        units = f" {s.units}" if s.units else ""
        out.append(f"{s.name}: {s.dtype}[{shape}]{bounds}{units}")
    return "\n".join(out)


def _mapping(value: Any) -> str:
    if not value:
        return "-"
    return "\n".join(f"{k}: {v}" for k, v in value.items())


@ecm.command("history")
@click.argument("name")
@registry_options
def history_cmd(name: str, *, opts: RegistryOptions) -> None:
    """The audit history of an ECM, oldest first."""
    validate_name(name)
    with registry_session(opts) as reg:
        events = reg.history(name)
    emit(opts, [e.to_dict() for e in events], lambda c: _render_history(c, name, events))


def _render_history(console: Console, name: str, events: list[AuditEvent]) -> None:
    if not events:
        console.print(f"no history for {name}")
        return
    table = make_table("SEQ", "TIME", "ACTION", "VERSION", "FROM->TO", "ACTIVE", "ACTOR", "REASON")
    for e in events:
        states = (
            f"{_state(e.from_state)}->{_state(e.to_state)}"
            if e.from_state is not None or e.to_state is not None
            else "-"
        )
        active = (
            f"{_v(e.from_version, 'none')}->{_v(e.to_version, 'none')}"
            if e.from_version is not None or e.to_version is not None
            else "-"
        )
        table.add_row(
            str(e.seq), fmt_time(e.at), e.action.value, _v(e.version), states, active, e.actor, e.reason or "-"
        )
    console.print(table)


@ecm.command("set")
@click.option("--revision", type=click.IntRange(min=0), default=None, help="A past revision (default: current).")
@registry_options
def set_cmd(revision: int | None, *, opts: RegistryOptions) -> None:
    """The capability set C(t): every ECM's active version at a revision."""
    with registry_session(opts) as reg:
        cs = reg.capability_set(revision)
    emit(opts, cs.to_dict(), lambda c: _render_set(c, cs))


def _render_set(console: Console, cs: CapabilitySet) -> None:
    console.print(f"capability set at revision {cs.revision}")
    table = make_table("NAME", "ACTIVE")
    for name, version in sorted(cs.active.items()):
        table.add_row(name, _v(version))
    console.print(table)
    if not cs.active:
        console.print("(empty)")


# ---------------------------------------------------------------------------------------
# Publish and lifecycle moves
# ---------------------------------------------------------------------------------------


@ecm.command("publish")
@click.argument("name")
@click.option(
    "--artifact",
    "artifact_path",
    required=True,
    type=click.Path(path_type=Path),
    help="Artifact file (zip, .py, .txt).",
)
@click.option(
    "--descriptor",
    "descriptor_path",
    required=True,
    type=click.Path(path_type=Path),
    help="Descriptor YAML (kind, description, interface, ...).",
)
@registry_options
def publish_cmd(name: str, artifact_path: Path, descriptor_path: Path, *, opts: RegistryOptions) -> None:
    """Publish a new candidate version of NAME."""
    validate_name(name)
    spec_text = _read_file(descriptor_path, "--descriptor")
    try:
        spec = parse_publish_spec(spec_text)
    except Invalid as err:
        raise Invalid(f"descriptor {str(descriptor_path)!r}: {err.message}", details=err.details) from None
    data = _read_file(artifact_path, "--artifact")
    with (
        registry_session(opts, create=True) as reg,
        progress(f"publishing {name} ({fmt_bytes(len(data))})", enabled=len(data) >= _PROGRESS_BYTES),
    ):
        record = reg.publish(name, data, spec)
    emit(
        opts,
        record.to_dict(),
        lambda c: c.print(
            f"published {record.name} {_v(record.version)} ({record.state.value}, {record.kind.value}, "
            f"{fmt_bytes(record.artifact.size)}, sha256 {record.artifact.sha256[:12]})"
        ),
    )


def _read_file(path: Path, option: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise Invalid(f"{option}: file {str(path)!r} does not exist", details={"field": option}) from None
    except IsADirectoryError:
        raise Invalid(f"{option}: {str(path)!r} is a directory, not a file", details={"field": option}) from None
    except OSError as exc:
        raise Invalid(f"{option}: cannot read {str(path)!r}: {exc.strerror}", details={"field": option}) from None


_EXPECTED = click.option(
    "--expected-active",
    type=_VERSION,
    default=None,
    help="Fail with a conflict unless this version is active now (compare-and-swap).",
)
_REASON = click.option("--reason", default="", help="Why; recorded in the audit history.")


@ecm.command("promote")
@click.argument("name")
@click.argument("version", type=_VERSION)
@_EXPECTED
@_REASON
@registry_options
def promote_cmd(name: str, version: int, expected_active: int | None, reason: str, *, opts: RegistryOptions) -> None:
    """Make candidate VERSION of NAME the active one."""
    validate_name(name)
    with registry_session(opts) as reg:
        record = reg.promote(name, version, expected_active=expected_active, reason=reason)
    _emit_move(opts, "promoted", record)


@ecm.command("rollback")
@click.argument("name")
@click.option("--to", "to", type=_VERSION, default=None, help="Version to restore (default: the previous active).")
@_EXPECTED
@_REASON
@registry_options
def rollback_cmd(name: str, to: int | None, expected_active: int | None, reason: str, *, opts: RegistryOptions) -> None:
    """Move NAME's active pointer back to a superseded version."""
    validate_name(name)
    with registry_session(opts) as reg:
        record = reg.rollback(name, to, expected_active=expected_active, reason=reason)
    _emit_move(opts, "rolled back", record)


@ecm.command("deprecate")
@click.argument("name")
@click.argument("version", type=_VERSION)
@_REASON
@registry_options
def deprecate_cmd(name: str, version: int, reason: str, *, opts: RegistryOptions) -> None:
    """Retire VERSION of NAME for good (it must not be active)."""
    validate_name(name)
    with registry_session(opts) as reg:
        record = reg.deprecate(name, version, reason=reason)
    _emit_move(opts, "deprecated", record)


@ecm.command("reject")
@click.argument("name")
@click.argument("version", type=_VERSION)
@_REASON
@registry_options
def reject_cmd(name: str, version: int, reason: str, *, opts: RegistryOptions) -> None:
    """Reject candidate VERSION of NAME."""
    validate_name(name)
    with registry_session(opts) as reg:
        record = reg.reject(name, version, reason=reason)
    _emit_move(opts, "rejected", record)


def _emit_move(opts: RegistryOptions, verb: str, record: EcmVersion) -> None:
    emit(
        opts,
        record.to_dict(),
        lambda c: c.print(f"{verb} {record.name} {_v(record.version)}: now {record.state.value}"),
    )


# ---------------------------------------------------------------------------------------
# Pull
# ---------------------------------------------------------------------------------------


@ecm.command("pull")
@click.argument("name")
@click.option("--version", "version", type=_VERSION, default=None, help="Version to fetch (default: the active one).")
@click.option(
    "-o",
    "--output",
    "output",
    required=True,
    type=click.Path(dir_okay=False, path_type=str),
    help="File to write ('-' for stdout); written atomically.",
)
@registry_options
def pull_cmd(name: str, version: int | None, output: str, *, opts: RegistryOptions) -> None:
    """Download the artifact of NAME (active version unless --version)."""
    validate_name(name)
    with registry_session(opts) as reg:
        # Pin the version first so the bytes and the record checked against them agree
        # even if the active pointer moves between the two calls.
        record = reg.get_version(name, version)
        with progress(
            f"pulling {name} ({fmt_bytes(record.artifact.size)})", enabled=record.artifact.size >= _PROGRESS_BYTES
        ):
            data = reg.get_artifact(name, record.version)
    digest = hashlib.sha256(data).hexdigest()
    if digest != record.artifact.sha256 or len(data) != record.artifact.size:
        raise Corrupt(
            f"artifact of {name} {_v(record.version)} has sha256 {digest} ({len(data)} bytes); "
            f"the record says {record.artifact.sha256} ({record.artifact.size} bytes)",
            details={"name": name, "version": record.version},
        )
    if output == "-":
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
        return
    path = Path(output)
    write_atomic(path, data)
    result = {**record.to_dict(), "path": str(path)}
    emit(
        opts,
        result,
        lambda c: c.print(
            f"pulled {record.name} {_v(record.version)} ({record.state.value}, {fmt_bytes(len(data))}, "
            f"sha256 {digest[:12]}) -> {path}"
        ),
    )


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so readers see the old file or the complete new one.

    Raises:
        CapevoError: (``internal``) when the directory is missing or not writable.
    """
    directory = path.parent if str(path.parent) else Path(".")
    tmp = directory / f".{path.name}.tmp-{secrets.token_hex(6)}"
    try:
        with open(tmp, "xb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise CapevoError(f"cannot write {str(path)!r}: {exc.strerror or exc}", details={"path": str(path)}) from None
    with contextlib.suppress(OSError):
        # The rename is durable only once the directory entry is.
        fsync_dir(directory)


def _v(version: int | None, missing: str = "-") -> str:
    return missing if version is None else f"v{version}"


def _state(state: State | None) -> str:
    return "none" if state is None else state.value
