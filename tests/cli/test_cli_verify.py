"""``capevo registry verify`` passes an intact registry and catches a tampered one."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable
from pathlib import Path

from cli_support import run_capevo
from click.testing import Result


def _populate(cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]) -> None:
    for tag in ("v0", "v1"):
        res = cli(
            "ecm", "publish", "reach", "--artifact", make_artifact(tag), "--descriptor", descriptor, "--root", root
        )
        assert res.exit_code == 0, res.stderr
    assert cli("ecm", "promote", "reach", "0", "--root", root).exit_code == 0


def _blob_files(root: Path) -> list[Path]:
    return sorted(p for p in (root / "blobs").rglob("*") if p.is_file() and not p.name.startswith(".tmp-"))


def test_verify_intact(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    _populate(cli, root, descriptor, make_artifact)
    res = cli("registry", "verify", "--root", root, "--json")
    assert res.exit_code == 0
    assert json.loads(res.stdout) == {"events_checked": 3, "blobs_checked": 2, "problems": [], "ok": True}


def test_verify_detects_tampered_blob(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    _populate(cli, root, descriptor, make_artifact)
    blobs = _blob_files(root)
    assert len(blobs) == 2
    victim = blobs[0]
    sha = victim.parent.name + victim.name
    data = bytearray(victim.read_bytes())
    data[0] ^= 0x01  # same size, different bytes
    victim.write_bytes(bytes(data))

    res = cli("registry", "verify", "--root", root)
    assert res.exit_code == 8
    assert res.stdout.startswith("verify: 1 PROBLEM(S):")
    assert sha in res.stdout

    res = cli("registry", "verify", "--root", root, "--json")
    assert res.exit_code == 8
    report = json.loads(res.stdout)
    assert report["ok"] is False and len(report["problems"]) == 1 and sha in report["problems"][0]

    # The same in a real process; pulling the tampered version is refused as corrupt.
    proc = run_capevo(["registry", "verify", "--root", root])
    assert proc.returncode == 8 and sha in proc.stdout and "Traceback" not in proc.stderr
    record = {
        v["artifact"]["sha256"]: v["version"]
        for v in json.loads(cli("ecm", "show", "reach", "--json", "--root", root).stdout)["versions"]
    }
    res = cli("ecm", "pull", "reach", "--version", record[sha], "-o", root.parent / "x", "--root", root)
    assert res.exit_code == 8
    assert res.stderr.startswith("error [corrupt]: ")
    assert not (root.parent / "x").exists()


def test_verify_detects_deleted_blob(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    _populate(cli, root, descriptor, make_artifact)
    _blob_files(root)[1].unlink()
    res = cli("registry", "verify", "--root", root, "--json")
    assert res.exit_code == 8
    assert len(json.loads(res.stdout)["problems"]) >= 1


def test_verify_detects_edited_audit_event(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    _populate(cli, root, descriptor, make_artifact)
    db = sqlite3.connect(root / "registry.sqlite3")
    tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")]
    audit = next(t for t in tables if "audit" in t or "event" in t)
    cols = [r[1] for r in db.execute(f"PRAGMA table_info({audit})")]
    assert "reason" in cols
    with db:
        db.execute(f"UPDATE {audit} SET reason = 'rewritten history' WHERE seq = 3")
    db.close()
    res = cli("registry", "verify", "--root", root)
    assert res.exit_code == 8
    assert "seq 3" in res.stdout
