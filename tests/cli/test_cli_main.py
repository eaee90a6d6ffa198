"""The main group: subcommands registered, heavy groups imported lazily, help and version."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable

from cli_support import REPO, subprocess_env
from click.testing import Result


def test_main_lists_every_group(cli: Callable[..., Result]) -> None:
    res = cli("--help")
    assert res.exit_code == 0
    commands = [ln.split()[0] for ln in res.stdout.split("Commands:")[1].splitlines() if ln.strip()]
    assert commands == ["ecm", "evolve", "experiment", "learner", "registry", "runtime", "trace"]
    res = cli("ecm", "--help")
    for sub in ("list", "show", "history", "publish", "promote", "rollback", "deprecate", "reject", "pull", "set"):
        assert f"  {sub} " in res.stdout
    res = cli("registry", "--help")
    assert all(f"  {sub} " in res.stdout for sub in ("serve", "verify", "demo"))


def test_trace_group_is_imported_only_when_used() -> None:
    code = (
        "import sys, capevo.cli as c; "
        "from click.testing import CliRunner; "
        "assert 'capevo.cli.trace' not in sys.modules; "
        "r = CliRunner().invoke(c.main, ['ecm', '--help']); assert r.exit_code == 0; "
        "assert 'capevo.cli.trace' not in sys.modules; "
        "r = CliRunner().invoke(c.main, ['trace', '--help']); assert r.exit_code == 0, r.output; "
        "assert 'capevo.cli.trace' in sys.modules"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=subprocess_env(), cwd=REPO)
    assert proc.returncode == 0, proc.stderr


def test_password_option_is_not_shown_with_a_value(cli: Callable[..., Result]) -> None:
    res = cli("ecm", "list", "--help", env={"CAPEVO_PASSWORD": "visible-if-leaked"})
    assert res.exit_code == 0
    assert "--password" in res.stdout and "visible-if-leaked" not in res.stdout
