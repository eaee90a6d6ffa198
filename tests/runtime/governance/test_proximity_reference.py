"""The proximity sensor against a straightforward reference, on real robosuite states.

:meth:`ProximitySensor.near` runs its broad phase as a few array operations over every
candidate pair at once (its cost is per call, not per pair). The reference here does the same
thing one pair at a time, in plain floats, exactly as the sensor's docstring says it: the hand
(with every geom of what it holds), the others (fixed scene first, then the moving geoms, less
what the hand holds), each pair kept when the larger of two lower bounds on its distance (the
two world boxes' gap, and a sphere around the hand geom's box against the other's world box) is
below ``reach``, then measured by ``mj_geomDistance`` or, for two boxes, the sensor's box bound.
The two must report the same pairs, in the same order, to the bit, on every step of episodes of
every task (scripted references that grasp and carry, random motion, T6's two arms).

The narrow phase's helpers (the box bound, the retry with growing margins, the contact lookup)
are the sensor's own: this test is about which pairs reach them and what is then reported.
"""

from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np
import pytest

from capevo.runtime.governance.proximity import Near, ProximitySensor
from capevo.runtime.tasks import make_task, scripted

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("quiet")]


def _world_box(sensor: ProximitySensor, g: int) -> tuple[list[float], list[float]]:
    """Geom ``g``'s bounding box in the world, axis-aligned: ``(centre, half size)``."""
    d = sensor.data
    r = d.geom_xmat[g].tolist()
    p = d.geom_xpos[g].tolist()
    c = sensor._centre[g].tolist()
    e = sensor._half[g].tolist()
    centre, half = [], []
    for k in range(3):
        row = r[3 * k : 3 * k + 3]
        centre.append(p[k] + (row[0] * c[0] + row[1] * c[1] + row[2] * c[2]))
        half.append(abs(row[0]) * e[0] + abs(row[1]) * e[1] + abs(row[2]) * e[2])
    return centre, half


def _broad_gap(sensor: ProximitySensor, h: int, o: int) -> float:
    """The larger of the two lower bounds on the distance of hand geom ``h`` and geom ``o``."""
    c, e = _world_box(sensor, h)
    oc, oe = _world_box(sensor, o)
    sep2 = out2 = 0.0
    for k in range(3):
        lo, hi = oc[k] - oe[k], oc[k] + oe[k]
        sep = max(lo - c[k] - e[k], c[k] - e[k] - hi, 0.0)
        sep2 += sep * sep
        out = min(max(c[k], lo), hi) - c[k]
        out2 += out * out
    return max(math.sqrt(sep2), math.sqrt(out2) - float(sensor._radius[h]))


def reference_near(sensor: ProximitySensor, arm: int) -> tuple[Near, ...]:
    """:meth:`ProximitySensor.near`, one pair at a time."""
    m, d, reach = sensor.model, sensor.data, sensor.reach
    hand, static, moving = sensor._arms[arm]
    held = [g for obj in sensor.held(arm) for g in sensor._object_geoms[obj]]
    hand = list(hand) + held
    others = static.tolist() + [g for g in moving.tolist() if g not in held]
    site = d.site_xpos[sensor._sites[arm]].tolist()
    ft = np.zeros(6)
    out: list[Near] = []
    for h in hand:
        for o in others:
            if not _broad_gap(sensor, h, o) < reach:
                continue
            if sensor._is_box[h] and sensor._is_box[o]:
                pair = sensor._box_to_box(h, o, sensor._frame(h), sensor._frame(o))
                if pair is None:
                    continue
                dist, *points = pair
            else:
                dist = mujoco.mj_geomDistance(m, d, h, o, reach, ft)
                if dist <= 0.0 and not sensor._touching(h, o):
                    pair = sensor._retry(h, o)
                    if pair is None:
                        continue
                    dist, *points = pair
                else:
                    points = ft.tolist()
            if not dist < reach:
                continue
            p1x, p1y, p1z, p2x, p2y, p2z = points
            vx, vy, vz = p2x - p1x, p2y - p1y, p2z - p1z
            norm = math.sqrt(vx * vx + vy * vy + vz * vz)
            if norm < 1e-9:
                cx, cy, cz = d.geom_xpos[h].tolist()
                vx, vy, vz = p2x - cx, p2y - cy, p2z - cz
                norm = math.sqrt(vx * vx + vy * vy + vz * vz)
                if norm < 1e-9:
                    continue
            elif dist < 0.0:
                vx, vy, vz = -vx, -vy, -vz
            out.append(
                (dist, vx / norm, vy / norm, vz / norm, p1x - site[0], p1y - site[1], p1z - site[2], sensor._owner[o])
            )
    return tuple(out)


def _random(env: Any, rng: np.random.Generator) -> np.ndarray:
    a = rng.uniform(-0.6, 0.6, env.task_spec.action_layout.dim)
    for arm in env.task_spec.action_layout.arms:
        a[arm.offset + 2] -= 0.3  # downwards, into the objects and the table
    return a


# task -> (policy, seeds, steps): scripted references grasp and carry (held objects, box pairs).
CASES: dict[str, tuple[Any, tuple[int, ...], int]] = {
    "T1": (lambda env, rng: scripted.pick(env.obs_dict), (0, 1, 2), 70),
    "T2": (lambda env, rng: scripted.place(env.obs_dict), (3,), 110),
    "T3": (lambda env, rng: scripted.stack(env.obs_dict), (0, 4), 90),
    "T4": (_random, (0, 1), 50),
    "T5": (_random, (2,), 50),
    "T6": (_random, (0, 1, 5), 50),
}


@pytest.mark.parametrize("task", sorted(CASES))
def test_near_reports_what_the_pair_by_pair_reference_reports(task: str) -> None:
    policy, seeds, steps = CASES[task]
    env = make_task(task, horizon=steps + 5)
    try:
        sensor = env._proximity
        arms = len(sensor._arms)
        reported = held = 0
        for seed in seeds:
            rng = np.random.default_rng(seed)
            env.reset(seed=seed)
            for step in range(steps):
                for i in range(arms):
                    want = reference_near(sensor, i)
                    got = sensor.near(i)
                    assert got == want, (task, seed, step, i)
                    reported += len(got)
                    held += bool(sensor.held(i))
                _, _, terminated, truncated, _ = env.step(policy(env, rng))
                if terminated or truncated:
                    break
        assert reported > 0
        if task in ("T1", "T2", "T3"):
            assert held > 0  # the held-object path ran
    finally:
        env.close()


def test_sensing_covers_the_forearms_of_every_arm() -> None:
    for task, links in (("T6", (3, 4, 5, 6, 7)), ("T1", (5, 6, 7))):
        env = make_task(task, horizon=5)
        try:
            env.reset(seed=0)
            model = env._model  # the compiled MuJoCo model
            sensor = env._proximity
            for arm in range(len(env.task_spec.action_layout.arms)):
                names = (
                    mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g]) for g in sensor.sensed(arm)
                )
                bodies = set(names)
                assert {b for b in bodies if b.startswith(f"robot{arm}_link")} == {
                    f"robot{arm}_link{k}" for k in links
                }, bodies
        finally:
            env.close()
