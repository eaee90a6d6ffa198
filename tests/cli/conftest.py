from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_support import CLEAN_ENV, DESCRIPTOR_YAML, artifact_bytes
from click.testing import CliRunner, Result

from capevo.cli import main


@pytest.fixture
def descriptor(tmp_path: Path) -> Path:
    path = tmp_path / "reach.yaml"
    path.write_text(DESCRIPTOR_YAML)
    return path


@pytest.fixture
def make_artifact(tmp_path: Path) -> Callable[[str], Path]:
    def make(tag: str) -> Path:
        path = tmp_path / f"reach-{tag}.py"
        path.write_bytes(artifact_bytes(tag))
        return path

    return make


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return tmp_path / "registry"


@pytest.fixture
def cli() -> Callable[..., Result]:
    """Run the click app in process: ``cli("ecm", "list", "--root", root, env={...})``."""
    runner = CliRunner()

    def run(*args: Any, env: dict[str, str | None] | None = None, input: bytes | None = None) -> Result:
        return runner.invoke(
            main, [str(a) for a in args], env={**CLEAN_ENV, **(env or {})}, input=input, catch_exceptions=True
        )

    return run
