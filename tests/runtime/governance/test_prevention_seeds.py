"""Issue 18's three colliding seeds: the default envelope prevents what the paper's only reacts to.

``data/`` holds the pick set that ``scripts/demo`` evolved under the paper's Φ before the default
changed (``pick.reach`` v2 by CEM, ``pick.grasp`` and ``pick.lift`` at v0), as published. On live
seeds 200006, 200017 and 200032 its hand hits the rim of bin1 (and the can) at 40-90 N under the
paper's Φ, whose force rule acts only once a reading is over 20 N; under the default Φ it slows
towards every nearby geom first and no step is unsafe. Graded by the independent safety monitor.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from replay import unsafe_reasons

from capevo.agent import DecompositionPolicy, IdentityMemory
from capevo.learner.skills import seed_specs
from capevo.registry.local import LocalRegistry
from capevo.runtime.evaluator import LocalEvaluator

DATA = Path(__file__).parent / "data"
SEEDS = [200006, 200017, 200032]
SET = {"pick.reach": "pick_reach_v2.src", "pick.grasp": "pick_grasp_v0.src", "pick.lift": "pick_lift_v0.src"}


@pytest.mark.slow
def test_the_default_envelope_prevents_the_rim_collisions_the_papers_lets_through(tmp_path: Path) -> None:
    specs = {name: spec for name, _, spec in seed_specs("pick")}  # descriptors and interfaces as published
    with LocalRegistry(tmp_path / "registry", actor="tests") as reg:
        for name, file in SET.items():
            reg.promote(name, reg.publish(name, (DATA / file).read_bytes(), specs[name]).version)
        policy = DecompositionPolicy(identity=IdentityMemory.default())
        unsafe = {}
        for phi in ("paper", "task"):
            with LocalEvaluator(reg, policy=policy, trace_dir=None, phi=phi) as evaluator:
                unsafe[phi] = [o.unsafe_steps for o in evaluator.evaluate("T1", {}, SEEDS)]
    assert all(n > 0 for n in unsafe["paper"]), unsafe
    assert unsafe["task"] == [0, 0, 0], unsafe


FOREARM = DATA / "am_t1_forearm_actions.json"


@pytest.mark.slow
def test_the_default_envelope_brakes_the_forearm_a_learned_policy_drove_into_the_bin() -> None:
    """A learned whole-task policy (the AM baseline of results/cpu-small) twisting its hand drove
    the forearm (link 5) into the bin at about 315 N while the hand itself moved clear of
    everything: hand-only braking let it through. Its proposed actions, replayed open loop, are
    unsafe without governance and safe under the default Φ, which brakes links 5-7 by how the
    action moves them (``link_motion``)."""
    import json

    record = json.loads(FOREARM.read_text())
    ungoverned = unsafe_reasons(record["actions"], record["seed"], governance=False)
    assert any("link5" in r for r in ungoverned), ungoverned
    assert unsafe_reasons(record["actions"], record["seed"]) == []


@pytest.mark.slow
def test_a_finger_brushing_another_object_does_not_make_it_part_of_the_hand() -> None:
    """T5, evolved set, held-out seed 250022: carrying the can past the placed milk carton, one
    finger brushed the milk. Counting every touching object as held put the milk on the hand's
    side, dropped the can-to-milk pair, released the brake, and the held can struck the milk at
    32.4 N. Held now means grasped (both fingers, robosuite's own test), so the milk stays among
    the others.

    The scene is built in MuJoCo directly (the carton placed on one finger's pad, then between
    both pads of a closed gripper) rather than by replaying the episode's 751 actions open loop:
    that replay reached the scene on the AMD machine that recorded it and left it by step 230 on
    an Intel one, so it could not hold on any machine."""
    import mujoco
    import numpy as np

    from capevo.runtime.tasks import make_task

    env = make_task("T5")
    try:
        env.reset(seed=0)
        prox = env._proximity
        model, data = prox.model, prox.data
        milk = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "Milk_main")
        free = model.jnt_qposadr[model.body_jntadr[milk]]
        fingers = prox._finger_of[0]
        names = {g: mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or "" for g in fingers}
        pads = {side: g for g, side in fingers.items() if "pad" in names[g]}
        assert set(pads) == {0, 1}

        def place(centre: np.ndarray) -> set[int]:
            """Put the carton upright at ``centre``; the finger sides it then touches."""
            data.qpos[free : free + 3] = centre
            data.qpos[free + 3 : free + 7] = (1.0, 0.0, 0.0, 0.0)
            mujoco.mj_forward(model, data)
            geoms = {g for g in range(model.ngeom) if model.geom_bodyid[g] == milk}
            return {
                fingers[a if b in geoms else b]
                for a, b in data.contact.geom[: data.ncon].tolist()
                if (a in geoms and b in fingers) or (b in geoms and a in fingers)
            }

        one, other = data.geom_xpos[pads[0]].copy(), data.geom_xpos[pads[1]].copy()
        outward = (one - other) / np.linalg.norm(one - other)
        assert place(one + 0.02 * outward) == {0}  # pressed on one pad from outside
        assert prox.held(0) == ()
        for name, opening in (("gripper0_right_finger_joint1", 0.015), ("gripper0_right_finger_joint2", -0.015)):
            data.qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)]] = opening
        mujoco.mj_forward(model, data)
        middle = (data.geom_xpos[pads[0]] + data.geom_xpos[pads[1]]) / 2
        assert place(middle) == {0, 1}  # between both pads of the closed gripper
        assert prox.held(0) == (milk,)
    finally:
        env.close()
