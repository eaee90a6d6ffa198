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


def test_traces_of_an_evaluation_say_which_ecm_the_failures_blame(cli: Callable[..., Result], root: Path) -> None:
    """``--trace-dir`` keeps the episodes' MCAP traces; ``capevo trace blame`` reads them as
    ``capevo evolve`` does: 20 steps are too few for v0 to get past ``pick.reach``, so both failed
    episodes end in it at the horizon and it takes their whole blame."""
    with LocalRegistry(root, actor="tests") as reg:
        seed_registry(reg, "pick")
    traces = root.parent / "traces"
    res = cli(
        "runtime", "evaluate", "--root", root, "--task", "T1", "--seeds", "7,3", "--horizon", "20",
        "--trace-dir", traces, "--json",
    )  # fmt: skip
    assert res.exit_code == 0, res.stderr
    rows = json.loads(res.stdout)
    assert all(r["trace_path"] and Path(r["trace_path"]).parent == traces for r in rows)

    blamed = cli("trace", "blame", traces, "--json")
    assert blamed.exit_code == 0, blamed.stderr
    doc = json.loads(blamed.stdout)
    assert (doc["task"], doc["episodes"], doc["successes"]) == ("pick", 2, 0)
    assert doc["blame"] == {"pick.reach": 2.0}
    assert [(f["seed"], f["steps"], f["ended"], f["last_ecm"]) for f in doc["failed"]] == [
        (7, 20, "horizon", "pick.reach"),
        (3, 20, "horizon", "pick.reach"),
    ]
    assert all(f["blamed"] == ["pick.reach"] and f["ecm_steps"] == {"pick.reach": 20} for f in doc["failed"])
    human = cli("trace", "blame", *doc["files"])
    assert human.exit_code == 0, human.stderr
    assert "task pick: 2 episodes in 1 file(s), 0 succeeded, 2 failed" in human.stdout
    assert "blame (1 per failed episode): reach 2" in human.stdout


def test_blame_refuses_what_it_cannot_judge(cli: Callable[..., Result], root: Path, tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    res = cli("trace", "blame", tmp_path / "empty")
    assert res.exit_code == 4 and "no *.mcap file under" in res.stderr
    res = cli("trace", "blame", tmp_path / "missing.mcap")
    assert res.exit_code == 4 and "no such trace" in res.stderr
    for task, name in (("T1", "pick"), ("T2", "place")):
        with LocalRegistry(root / task, actor="tests") as reg:
            seed_registry(reg, name)
        res = cli(
            "runtime", "evaluate", "--root", root / task, "--task", task, "--seeds", "1", "--horizon", "5",
            "--trace-dir", tmp_path / "mixed" / task,
        )  # fmt: skip
        assert res.exit_code == 0, res.stderr
    res = cli("trace", "blame", tmp_path / "mixed")
    assert res.exit_code == 3 and "the traces hold several tasks (pick, place): blame one at a time" in res.stderr
