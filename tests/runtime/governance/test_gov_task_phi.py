"""Per-task Φ: the paper's envelope plus each task's scene, and the scene numbers checked against robosuite."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.governance import (
    TASK_GEOMETRY,
    ArmSeparation,
    ObstacleApproach,
    Phi,
    ReachLimit,
    SurfaceApproach,
    VelocityCap,
    load_phi,
    phi_for_task,
)
from capevo.runtime.governance.task_phi import PANDA_HAND, PANDA_SHOULDER
from capevo.runtime.tasks import task_ids, task_spec

TASKS = ("T1", "T2", "T3", "T4", "T5", "T6")


def for_task(task_id: str, base: Phi | None = None) -> Phi:
    """The per-task Φ of a task id: ids are the tasks package's, so the caller resolves them."""
    return Phi.for_task(task_spec(task_id), base)


def test_the_papers_envelope_is_the_base_and_the_cap_still_acts_last() -> None:
    base = Phi.default()
    for task in TASKS:
        phi = for_task(task)
        assert phi.constraints[:2] == base.constraints[:2]  # workspace_box, contact_force
        assert phi.constraints[-1] == base.constraints[-1] and isinstance(phi.constraints[-1], VelocityCap)
        assert set(base.labels) <= set(phi.labels)
        assert load_phi(phi.to_yaml()) == phi and load_phi(phi.to_yaml()).hash == phi.hash


def test_each_task_gets_its_own_phi_and_hash() -> None:
    hashes = {for_task(t).hash for t in TASKS}
    # T1, T2 and T5 share the bins scene, so they share Φ.
    assert for_task("T1") == for_task("T2") == for_task("T5")
    assert len(hashes) == 4 and Phi.default().hash not in hashes
    assert Phi.for_task("pick") == for_task("T1") == phi_for_task("pick") == phi_for_task(task_spec("T1"))
    kinds = {t: [c.kind for c in for_task(t).constraints] for t in TASKS}
    assert "surface_approach" in kinds["T3"] and "surface_approach" not in kinds["T6"]
    assert all("obstacle_approach" in kinds[t] for t in ("T1", "T3", "T4"))  # walls, pegs, the mount
    assert kinds["T6"].count("obstacle_approach") == 2 and "arm_separation" in kinds["T6"]
    assert "arm_separation" not in kinds["T1"]


def test_a_custom_base_is_extended_before_its_cap() -> None:
    base = load_phi("constraints: [{kind: workspace_box, margin: 0.05}, {kind: velocity_cap, max_norm: 1.0}]")
    phi = for_task("T3", base)
    assert phi.constraints[0] == base.constraints[0] and phi.constraints[-1] == base.constraints[-1]
    # The two that add motion come first: the rest hold after them.
    assert [c.kind for c in phi.constraints[1:4]] == ["keep_clear", "stopping_distance", "closing_grip"]
    guard = phi.constraints[4]
    assert guard.kind == "workspace_guard" and guard.margin == 0.05


@pytest.mark.parametrize("task", ["T9", "T1", "lift"])
def test_an_unknown_task_is_refused_listing_the_known_ones(task: str) -> None:
    # A task id is the tasks package's to resolve: governance knows the scenes by task name only.
    with pytest.raises(Invalid) as e:
        Phi.for_task(task)
    assert e.value.code is ErrorCode.INVALID and e.value.details["field"] == "task"
    assert e.value.message == (
        f"task: no scene geometry for {task!r}; known tasks: pick, place, stack, nut_assembly, pick_place_multi, "
        "peg_in_hole (for a task id, pass its spec: capevo.runtime.tasks.task_spec(id))"
    )
    assert set(TASK_GEOMETRY) == set(task_ids().values())


# ---------------------------------------------------------------- the scene numbers, from the simulators


def _aabb(model: Any, data: Any, g: int) -> tuple[np.ndarray, np.ndarray]:
    """World axis-aligned box of geom ``g``."""
    c, h = model.geom_aabb[g][:3], model.geom_aabb[g][3:]
    r = data.geom_xmat[g].reshape(3, 3)
    mid = data.geom_xpos[g] + r @ c
    half = np.abs(r) @ h
    return mid - half, mid + half


def _inside(lo: np.ndarray, hi: np.ndarray, boxes: Any, tol: float = 1e-3) -> bool:
    return any(np.all(lo >= np.array(b.low) - tol) and np.all(hi <= np.array(b.high) + tol) for b in boxes)


def _hand_corners(model: Any, data: Any, site: int, geoms: list[int]) -> np.ndarray:
    r, p = data.site_xmat[site].reshape(3, 3), data.site_xpos[site]
    out = []
    for g in geoms:
        c, h = model.geom_aabb[g][:3], model.geom_aabb[g][3:]
        rg, pg = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g]
        for sign in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
            out.append(r.T @ (pg + rg @ (c + h * sign) - p))
    return np.array(out)


@pytest.mark.slow
@pytest.mark.parametrize("task", ["pick", "stack", "nut_assembly", "peg_in_hole"])
def test_task_geometry_matches_the_live_simulator(task: str) -> None:
    from capevo.runtime.tasks import Perturbations, make_task

    env = make_task(task, seed=0, perturbations=Perturbations.none())
    try:
        env.reset(seed=0)
        rs = env.robosuite_env
        m, d, names = rs.sim.model._model, rs.sim.data._data, rs.sim.model
        geo = TASK_GEOMETRY[task]
        for base, robot in zip(geo.arm_bases, rs.robots, strict=True):
            root = names.body_name2id(robot.robot_model.root_body)
            assert np.allclose(d.xpos[root], base, atol=1e-6)
        phi = Phi.for_task(task)
        reach = next(c for c in phi.constraints if isinstance(c, ReachLimit))
        assert reach.centres == tuple((x, y, z + PANDA_SHOULDER) for x, y, z in geo.arm_bases)
        # Every collidable fixed geom above the surface (bins, pegs, mounts) lies in a listed obstacle.
        fixed = [
            g
            for g in range(m.ngeom)
            if (m.geom_contype[g] or m.geom_conaffinity[g]) and m.body_weldid[m.geom_bodyid[g]] == 0
        ]
        for g in fixed:
            lo, hi = _aabb(m, d, g)
            name = names.geom_id2name(g) or names.body_id2name(m.geom_bodyid[g])
            if geo.surface_height is not None and hi[2] <= geo.surface_height + 1e-6:
                continue  # the table or a bin floor: the surface rule's plane
            if hi[2] < 0.6 or name == "floor":
                continue  # below the workspace box floor
            if "mount" in name and "pedestal_col" not in name:
                continue  # the mount's low parts (feet, controller box) are under 0.81 m, behind the robot
            if name.startswith("robot"):
                continue  # the arm's own base: reach_limit's column keeps the hand away from it
            assert _inside(lo, hi, geo.obstacles), f"{task}: {name} {lo} {hi} is not covered"
        if geo.surface_height is not None:
            surface = next(c for c in phi.constraints if isinstance(c, SurfaceApproach))
            tops = [_aabb(m, d, g)[1][2] for g in fixed if (names.geom_id2name(g) or "").startswith("table")]
            if task == "pick":  # the bin floors
                tops = [_aabb(m, d, g)[1][2] for g in fixed if names.body_id2name(m.geom_bodyid[g]).startswith("bin")]
            assert surface.height == pytest.approx(min(tops), abs=1e-6)
        # The hands cover the gripper's collision geoms (or the held peg and plate), turned as they are now.
        for i, robot in enumerate(rs.robots):
            site = robot.eef_site_id["right"]
            if task == "peg_in_hole":
                geoms = [int(g) for g in env._held_geoms[i]]
            else:
                geoms = [
                    g
                    for g in range(m.ngeom)
                    if (m.geom_contype[g] or m.geom_conaffinity[g])
                    and names.body_id2name(m.geom_bodyid[g]).startswith("gripper0")
                ]
            corners = _hand_corners(m, d, site, geoms)
            hand = geo.hand(i)
            assert _inside(corners.min(axis=0), corners.max(axis=0), hand, tol=1e-3) or all(
                _inside(c, c, hand, tol=1e-3) for c in corners
            )
        if task == "peg_in_hole":
            sep = next(c for c in phi.constraints if isinstance(c, ArmSeparation))
            assert sep.hands == (geo.hand(0), geo.hand(1))
            rules = [c for c in phi.constraints if isinstance(c, ObstacleApproach)]
            assert [r.arm for r in rules] == [0, 1]
        else:
            assert geo.hand(0) == PANDA_HAND
    finally:
        env.close()
