"""The whole ECM lifecycle through the CLI against a local --root, in JSON and as tables."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

from cli_support import artifact_bytes, load_json, run_capevo
from click.testing import Result


def _publish(cli: Callable[..., Result], root: Path, artifact: Path, descriptor: Path) -> dict:
    return load_json(
        cli("ecm", "publish", "reach", "--artifact", artifact, "--descriptor", descriptor, "--root", root, "--json")
    )


def test_full_lifecycle_json(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path], tmp_path: Path
) -> None:
    v0 = _publish(cli, root, make_artifact("v0"), descriptor)
    assert (v0["name"], v0["version"], v0["state"], v0["kind"]) == ("reach", 0, "candidate", "code")
    assert v0["artifact"]["sha256"] == hashlib.sha256(artifact_bytes("v0")).hexdigest()
    assert v0["descriptor"]["applicability"]["all"][0]["signal"] == "object_height"
    v1 = _publish(cli, root, make_artifact("v1"), descriptor)
    assert v1["version"] == 1

    promoted = load_json(cli("ecm", "promote", "reach", "0", "--reason", "first", "--root", root, "--json"))
    assert (promoted["version"], promoted["state"]) == (0, "active")
    promoted = load_json(cli("ecm", "promote", "reach", "1", "--expected-active", "0", "--root", root, "--json"))
    assert (promoted["version"], promoted["state"]) == (1, "active")

    listed = load_json(cli("ecm", "list", "--root", root, "--json"))
    assert listed == [{"name": "reach", "active_version": 1, "latest_version": 1, "n_versions": 2}]

    detail = load_json(cli("ecm", "show", "reach", "--root", root, "--json"))
    assert detail["active_version"] == 1
    assert [(v["version"], v["state"]) for v in detail["versions"]] == [(0, "superseded"), (1, "active")]
    one = load_json(cli("ecm", "show", "reach", "--version", "0", "--root", root, "--json"))
    assert (one["version"], one["state"]) == (0, "superseded")

    rolled = load_json(cli("ecm", "rollback", "reach", "--reason", "regressed", "--root", root, "--json"))
    assert (rolled["version"], rolled["state"]) == (0, "active")

    history = load_json(cli("ecm", "history", "reach", "--root", root, "--json"))
    assert [e["action"] for e in history] == ["publish", "publish", "promote", "promote", "rollback"]
    assert [e["seq"] for e in history] == [1, 2, 3, 4, 5]
    last = history[-1]
    assert (last["from_version"], last["to_version"], last["reason"]) == (1, 0, "regressed")

    cap_now = load_json(cli("ecm", "set", "--root", root, "--json"))
    assert cap_now["active"] == {"reach": 0}
    cap_1 = load_json(cli("ecm", "set", "--revision", "1", "--root", root, "--json"))
    assert cap_1 == {"revision": 1, "active": {"reach": 0}}
    cap_2 = load_json(cli("ecm", "set", "--revision", "2", "--root", root, "--json"))
    assert cap_2["active"] == {"reach": 1}

    out = tmp_path / "pulled.py"
    pulled = load_json(cli("ecm", "pull", "reach", "-o", out, "--root", root, "--json"))
    assert out.read_bytes() == artifact_bytes("v0")
    assert (pulled["version"], pulled["path"]) == (0, str(out))
    load_json(cli("ecm", "pull", "reach", "--version", "1", "-o", out, "--root", root, "--json"))
    assert out.read_bytes() == artifact_bytes("v1")

    v2 = _publish(cli, root, make_artifact("v2"), descriptor)
    rejected = load_json(
        cli("ecm", "reject", "reach", str(v2["version"]), "--reason", "fails gate", "--root", root, "--json")
    )
    assert rejected["state"] == "rejected"
    deprecated = load_json(cli("ecm", "deprecate", "reach", "1", "--root", root, "--json"))
    assert deprecated["state"] == "deprecated"
    history = load_json(cli("ecm", "history", "reach", "--root", root, "--json"))
    assert [e["action"] for e in history][-3:] == ["publish", "reject", "deprecate"]

    verify = load_json(cli("registry", "verify", "--root", root, "--json"))
    assert verify["ok"] is True and verify["events_checked"] == 8 and verify["problems"] == []


def test_lifecycle_tables(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path], tmp_path: Path
) -> None:
    res = cli("ecm", "publish", "reach", "--artifact", make_artifact("v0"), "--descriptor", descriptor, "--root", root)
    assert res.exit_code == 0, res.stderr
    assert res.stdout.startswith("published reach v0 (candidate, code,")
    cli("ecm", "publish", "reach", "--artifact", make_artifact("v1"), "--descriptor", descriptor, "--root", root)
    res = cli("ecm", "promote", "reach", "0", "--root", root)
    assert res.exit_code == 0 and res.stdout.strip() == "promoted reach v0: now active"
    res = cli("ecm", "promote", "reach", "1", "--root", root, "--reason", "better")
    assert res.exit_code == 0

    res = cli("ecm", "list", "--root", root)
    assert res.exit_code == 0
    header, _rule, row = res.stdout.splitlines()[:3]
    assert header.split() == ["NAME", "ACTIVE", "LATEST", "VERSIONS"]
    assert row.split() == ["reach", "v1", "v1", "2"]

    res = cli("ecm", "show", "reach", "--root", root)
    lines = res.stdout.splitlines()
    assert lines[0].strip() == "reach  (active: v1)"
    rows = {ln.split()[0] if not ln.startswith("*") else ln.split()[1]: ln for ln in lines[3:] if "v" in ln[:8]}
    assert rows["v1"].lstrip().startswith("*") and "active" in rows["v1"]
    assert not rows["v0"].lstrip().startswith("*") and "superseded" in rows["v0"]

    res = cli("ecm", "show", "reach", "--version", "0", "--root", root)
    fields = {ln.split()[0]: ln.split(None, 1)[1] for ln in res.stdout.splitlines()[3:] if ln.strip()}
    assert fields["state"].strip() == "superseded"
    # Predicates print verbatim, brackets included (no rich markup interpretation).
    assert "[object_height < 0.05]" in fields["applicability"]
    assert "action: float32[7] [-1, 1]" in fields["outputs"]

    res = cli("ecm", "rollback", "reach", "--root", root, "--reason", "regressed")
    assert res.exit_code == 0 and res.stdout.strip() == "rolled back reach v0: now active"

    res = cli("ecm", "history", "reach", "--root", root)
    lines = res.stdout.splitlines()
    assert lines[0].split() == ["SEQ", "TIME", "ACTION", "VERSION", "FROM->TO", "ACTIVE", "ACTOR", "REASON"]
    last = lines[-1].split()
    assert last[0] == "5" and last[3:5] == ["rollback", "v0"]
    assert "superseded->active" in last and "v1->v0" in last and last[-1] == "regressed"

    res = cli("ecm", "set", "--root", root)
    assert res.stdout.splitlines()[0] == "capability set at revision 3"
    assert res.stdout.splitlines()[-1].split() == ["reach", "v0"]

    res = cli("ecm", "pull", "reach", "-o", tmp_path / "a.py", "--root", root)
    assert res.exit_code == 0 and res.stdout.startswith("pulled reach v0 (active,")

    res = cli("registry", "verify", "--root", root)
    assert res.exit_code == 0 and res.stdout.startswith("verify: OK: 5 audit events, 2 blobs checked")


def test_empty_registry_tables(cli: Callable[..., Result], root: Path) -> None:
    root.mkdir()
    res = cli("ecm", "list", "--root", root)
    assert (res.exit_code, res.stdout.strip()) == (0, "no ECMs")
    assert load_json(cli("ecm", "list", "--root", root, "--json")) == []
    assert load_json(cli("ecm", "set", "--root", root, "--json")) == {"revision": 0, "active": {}}


def test_root_from_env_and_default(
    cli: Callable[..., Result],
    root: Path,
    descriptor: Path,
    make_artifact: Callable[[str], Path],
    tmp_path: Path,
    monkeypatch,
) -> None:
    env = {"CAPEVO_ROOT": str(root)}
    res = cli("ecm", "publish", "reach", "--artifact", make_artifact("v0"), "--descriptor", descriptor, env=env)
    assert res.exit_code == 0, res.stderr
    assert (root / "registry.sqlite3").exists()
    assert load_json(cli("ecm", "list", "--json", env=env))[0]["name"] == "reach"
    # Without --root or CAPEVO_ROOT the registry is ./capevo-data.
    monkeypatch.chdir(tmp_path)
    res = cli("ecm", "publish", "grasp", "--artifact", make_artifact("g"), "--descriptor", descriptor)
    assert res.exit_code == 0, res.stderr
    assert (tmp_path / "capevo-data" / "registry.sqlite3").exists()
    assert [e["name"] for e in load_json(cli("ecm", "list", "--json"))] == ["grasp"]


def test_pull_to_stdout(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    cli("ecm", "publish", "reach", "--artifact", make_artifact("v0"), "--descriptor", descriptor, "--root", root)
    cli("ecm", "promote", "reach", "0", "--root", root)
    res = cli("ecm", "pull", "reach", "-o", "-", "--root", root)
    assert res.exit_code == 0
    assert res.stdout_bytes == artifact_bytes("v0")


def test_pull_replaces_existing_file_atomically(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path], tmp_path: Path
) -> None:
    cli("ecm", "publish", "reach", "--artifact", make_artifact("v0"), "--descriptor", descriptor, "--root", root)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    target = out_dir / "policy.py"
    target.write_bytes(b"old contents that are longer than the new artifact" * 10)
    res = cli("ecm", "pull", "reach", "--version", "0", "-o", target, "--root", root)
    assert res.exit_code == 0, res.stderr
    assert target.read_bytes() == artifact_bytes("v0")
    assert sorted(p.name for p in out_dir.iterdir()) == ["policy.py"]  # no temp file left behind


def test_pull_into_missing_directory_fails_cleanly(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path], tmp_path: Path
) -> None:
    cli("ecm", "publish", "reach", "--artifact", make_artifact("v0"), "--descriptor", descriptor, "--root", root)
    res = cli("ecm", "pull", "reach", "--version", "0", "-o", tmp_path / "no" / "such" / "x.py", "--root", root)
    assert res.exit_code == 1
    assert res.stderr.startswith("error [internal]: cannot write ") and "No such file or directory" in res.stderr


def test_python_dash_m_capevo_runs_the_cli(root: Path, descriptor: Path, make_artifact: Callable[[str], Path]) -> None:
    proc = run_capevo(
        [
            "ecm",
            "publish",
            "reach",
            "--artifact",
            make_artifact("v0"),
            "--descriptor",
            descriptor,
            "--root",
            root,
            "--json",
        ]
    )
    assert proc.returncode == 0, proc.stderr
    proc = run_capevo(["ecm", "list", "--root", root])
    assert proc.returncode == 0 and proc.stdout.splitlines()[2].split() == ["reach", "-", "v0", "1"]
    proc = run_capevo(["--version"])
    assert proc.returncode == 0 and "capevo" in proc.stdout


def test_user_is_the_audit_actor_with_a_local_root(
    cli: Callable[..., Result], root: Path, descriptor: Path, make_artifact: Callable[[str], Path]
) -> None:
    res = cli(
        "ecm",
        "publish",
        "reach",
        "--artifact",
        make_artifact("v0"),
        "--descriptor",
        descriptor,
        "--root",
        root,
        "--user",
        "alice",
    )
    assert res.exit_code == 0, res.stderr
    res = cli("ecm", "promote", "reach", "0", "--root", root, env={"CAPEVO_USER": "bob"})
    assert res.exit_code == 0, res.stderr
    history = load_json(cli("ecm", "history", "reach", "--root", root, "--json"))
    assert [e["actor"] for e in history] == ["alice", "bob"]
    assert load_json(cli("ecm", "show", "reach", "--root", root, "--json"))["versions"][0]["created_by"] == "alice"
