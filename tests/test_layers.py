"""The layers only point down and nothing imports in a circle: import-linter's contracts in
pyproject.toml hold for the tree, and a back arrow or a circle added to a copy of it breaks them."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _lint_imports(tree: Path) -> subprocess.CompletedProcess[str]:
    """Run lint-imports on the ``capevo`` package under ``tree`` with the project's contracts."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache"], cwd=tree, env=env, capture_output=True, text=True, timeout=120
    )


@pytest.fixture
def tree_copy(tmp_path: Path) -> Path:
    shutil.copytree(ROOT / "capevo", tmp_path / "capevo", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def _append(path: Path, line: str) -> None:
    path.write_text(path.read_text() + f"\n{line}  # noqa\n")


def test_the_tree_keeps_every_contract(tree_copy: Path) -> None:
    result = _lint_imports(tree_copy)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Layers only point down KEPT" in result.stdout
    assert "No import circles, inside any subpackage either KEPT" in result.stdout


def test_an_import_from_storage_up_to_the_registry_breaks_the_layers(tree_copy: Path) -> None:
    _append(tree_copy / "capevo" / "storage" / "blobs.py", "import capevo.registry.api")
    result = _lint_imports(tree_copy)
    assert result.returncode != 0
    assert "Layers only point down BROKEN" in result.stdout
    assert "capevo.storage is not allowed to import capevo.registry" in result.stdout


def test_a_circle_inside_a_subpackage_breaks_the_acyclic_contract(tree_copy: Path) -> None:
    records = tree_copy / "capevo" / "records"
    _append(records / "audit.py", "import capevo.records.lifecycle")
    _append(records / "lifecycle.py", "import capevo.records.audit")
    result = _lint_imports(tree_copy)
    assert result.returncode != 0
    assert "No import circles, inside any subpackage either BROKEN" in result.stdout
    assert "No cycles are allowed in capevo.records" in result.stdout
