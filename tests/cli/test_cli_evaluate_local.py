"""``capevo runtime evaluate --root``: real episodes on a local registry, with Wilson intervals."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from click.testing import Result

from capevo.learner.skills import seed_registry
from capevo.registry.local import LocalRegistry
from capevo.runtime.envelope import resolve_phi
from capevo.runtime.tasks import task_spec


def test_local_evaluation_runs_the_active_set_under_the_chosen_envelope(cli: Callable[..., Result], root: Path) -> None:
    with LocalRegistry(root, actor="tests") as reg:
        seed_registry(reg, "pick")
    args = ("runtime", "evaluate", "--root", root, "--task", "T1", "--seeds", "7,3", "--horizon", "20")
    res = cli(*args)
    assert res.exit_code == 0, res.stderr
    assert "success 0/2 = 0.0% [95% Wilson 0.0%, 65.8%]; unsafe episodes 0/2" in res.stdout
    for phi in ("task", "paper"):
        res = cli(*args, "--phi", phi, "--json")
        assert res.exit_code == 0, res.stderr
        rows = json.loads(res.stdout)
        assert [r["seed"] for r in rows] == [7, 3] and all(r["steps"] == 20 for r in rows)
        assert {r["phi_hash"] for r in rows} == {resolve_phi(phi, task_spec("T1")).hash}
        assert all(r["capability_set"] == {"pick.reach": 0, "pick.grasp": 0, "pick.lift": 0} for r in rows)


def test_a_missing_registry_is_refused(cli: Callable[..., Result], tmp_path: Path) -> None:
    res = cli("runtime", "evaluate", "--root", tmp_path / "nothing", "--task", "T1")
    assert res.exit_code == 3
    assert "no registry at" in res.stderr and not (tmp_path / "nothing").exists()
