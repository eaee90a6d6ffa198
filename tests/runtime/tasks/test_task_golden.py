"""Golden digests: the task wrappers' episodes, bit for bit, as they were before the
per-step cost work (one forced observable pass in dependency order, robosuite's in-step
sampling skipped, cached goals, cheaper clipping and flattening).

The digests were computed from the code at the commit before that work; any change to an
observation, noise draw, reward, flag, info, signal or robot state changes them. They pin the
machine's floating point (numpy's CPU dispatch, the MuJoCo and numpy builds), so they are kept
per :func:`golden_support.machine_fingerprint`: on a new machine add its entry, computed at a
known-good commit with ``golden_support.task_episode_digest`` (seeds 0 and 7, 30 steps).
"""

from __future__ import annotations

import pytest
from golden_support import RECORDED_BEFORE_FINGERPRINTS, expect_golden, task_episode_digest

from capevo.runtime.tasks import TaskEnv, make_task

pytestmark = pytest.mark.slow

STEPS = 30
GOLDEN: dict[str, dict[str, tuple[str, str]]] = {
    RECORDED_BEFORE_FINGERPRINTS: {
        "T1": (
            "f96a1229a1fd4f87bf776a0f1df091b5b51f7c8c2d4286b1b702d13d02367fc4",
            "66c46bc29609cb0b06355696d0cc4574e3d80d7c1ccb50163ae15c07a0b43d2e",
        ),
        "T2": (
            "089a38797b9ed2aab2c984b78be626d9ddf914e4b08a59b03901a6eebf4cf93e",
            "55f33be38f12346cc5688367b8c8110de3a7d00b25f029c6573bef86466148d9",
        ),
        "T3": (
            "13700fdaeba667b620668f1ec83cfee47d0e7101377b2ce0dcac6f9ca155b4af",
            "95df9ba8c7009a5c341e79da5ca1ae4bee9e0c7ac8f327a4c955ccb3df45f1ba",
        ),
        "T4": (
            "1c0cf50dc603078800941ed452c6a247d35cfd78225ae2af34411c597f7e0fa7",
            "0973f2201714190dc8405b5d4a8abdca526ef48cfc4f5872c06ecf385af51c56",
        ),
        "T5": (
            "fb5615a2078bb7a8081250a99f9a03b45525eadc8a24c9bf8d98d8e7788bf00b",
            "3cd785db12ef215cd5c7fa90428ec2ea584c2bf112eb93ab60fad8687291f1fe",
        ),
        "T6": (
            "9e949e29612b871ef47545b61978ee6806248b3cfb0783ea440396a7e7c08c51",
            "1431e2cf2e8640f3bd37efede9e1626fdb17f67235b555a53e9bd614016e4bff",
        ),
    },
    # AMD EPYC (Zen 4, AVX-512), numpy 1.26.4, mujoco 3.7.0, OpenBLAS on its Cooperlake kernels
    # (what it picks there); computed at commit b3034bd.
    "52adc3507f2a5cb8": {
        "T1": (
            "7dc9b756b2e2a0672098cb1e03ace8e4d406bc9e9c08e9e7b49d80a1c4c2babe",
            "beb1810e04a809620b36508ebb6122fef105e358f335c3acdf96b58d4f025956",
        ),
        "T2": (
            "8c9e9e54fde88f096336c86e8bd49d7c98777bbc5c2a068847d29897149d481c",
            "fad8858f8e91130b2225e4816441fc5b492a008de927ae7f480e141338260fa2",
        ),
        "T3": (
            "be48ae897f2d5daf7ab1d2df5d6361aefd08b9b43b26cf23ead20781b1f6a9ed",
            "fa61efedb0bacde78a7adf1525674b22d7d9dbd6e5cfbb977b91d6952bc27884",
        ),
        "T4": (
            "8176afcd571163ae16eeb54d26b57b4bd5353f12ab55e5c7c967f54d95abb092",
            "279422fd76c12ae9081bcb32888a0801e20c9b08d82b14890176afe6e68d7112",
        ),
        "T5": (
            "4568fbcd995225e590c3f66e43c837452481986c6a232552956aae8db10b1acb",
            "82248ea7b64eebe97b62632e1b669ff0ea3e97e89d8feca8fef700d2e68ee88f",
        ),
        "T6": (
            "839e016d8834d6fd86b3181b6f7c073dc8adf553b3f6c91c3f26794aa1f8e98d",
            "f249b31b4bcf5d7035bc76c8ed155e378903d573d936a9f919501f3aae3c7652",
        ),
    },
}
# The same CPU features with OpenBLAS forced to its SkylakeX kernels (OPENBLAS_CORETYPE) give the
# same digests; on its Haswell (AVX2) kernels, those of the machine the suite was written on
# (both checked on a Zen 5 at 8a72d89).
GOLDEN["a9fae7d83db2f47b"] = GOLDEN["52adc3507f2a5cb8"]
# An Intel Xeon (family 6, model 167; AVX-512, AMX), numpy 1.26.4, mujoco 3.7.0, OpenBLAS on its
# SkylakeX kernels: the Zen 4's digests, computed there at b3034bd and at 15091ce alike.
GOLDEN["16315d6f2cea6070"] = GOLDEN["52adc3507f2a5cb8"]
GOLDEN["b53a26c6fc0c472f"] = GOLDEN[RECORDED_BEFORE_FINGERPRINTS]
TASKS = sorted(GOLDEN[RECORDED_BEFORE_FINGERPRINTS])


@pytest.mark.parametrize("task", TASKS)
def test_seeded_random_episodes_match_the_golden_digests(quiet: None, task: str) -> None:
    # Base invariant 1 across code changes: same seed, same actions -> the same episode.
    env: TaskEnv = make_task(task, horizon=STEPS)
    try:
        # seed 7 runs on the reused environment, as workers reuse theirs
        got = tuple(task_episode_digest(env, seed, STEPS) for seed in (0, 7))
    finally:
        env.close()
    expect_golden(
        got,
        {machine: digests[task] for machine, digests in GOLDEN.items()},
        generate="golden_support.task_episode_digest",
    )
