"""Helpers shared by the CLI tests (imported as ``cli_support``; tests/cli is on sys.path)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from click.testing import Result

REPO = Path(__file__).resolve().parents[2]

DESCRIPTOR_YAML = """\
kind: code
description: Move the open gripper above the object.
applicability: {text: object on table, all: [{signal: object_height, op: "<", value: 0.05}]}
termination:   {text: above object,    all: [{signal: eef_object_xy_dist, op: "<", value: 0.01}]}
interface:
  inputs:  [{name: eef_pos, shape: [3], dtype: float32, units: m}]
  outputs: [{name: action, shape: [7], dtype: float32, low: -1, high: 1}]
"""


def artifact_bytes(tag: str) -> bytes:
    return f"def act(obs):  # {tag}\n    return [0.0] * 7\n".encode()


# Environment the CLI must not inherit from the developer's shell.
CLEAN_ENV = {k: None for k in ("CAPEVO_ROOT", "CAPEVO_CONNECT", "CAPEVO_USER", "CAPEVO_PASSWORD", "CAPEVO_DEBUG")}


def load_json(result: Result) -> Any:
    assert result.exit_code == 0, (result.exit_code, result.stderr, result.exception)
    return json.loads(result.stdout)


def subprocess_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in CLEAN_ENV}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env["COLUMNS"] = "200"
    env.update(extra or {})
    return env


def run_capevo(
    args: Sequence[Any], *, env: dict[str, str] | None = None, timeout: float = 60.0
) -> subprocess.CompletedProcess[str]:
    """Run ``python -m capevo ARGS`` as a real process and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "capevo", *[str(a) for a in args]],
        capture_output=True,
        text=True,
        env=subprocess_env(env),
        timeout=timeout,
        cwd=REPO,
    )


def assert_clean_error(stderr: str, code: str) -> str:
    """stderr is exactly one ``error [code]: ...`` line with no traceback; return the message."""
    assert "Traceback" not in stderr
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    prefix = f"error [{code}]: "
    assert lines[0].startswith(prefix), stderr
    return lines[0][len(prefix) :]
