"""Per-call cost of running ECMs: sandboxed code, in-process code, neural policies.

Times, after warm-up:

* ``sandbox_ping``: an empty request/reply to a sandbox worker (pipe + JSON floor);
* ``sandbox_step``: one ``SandboxedSkill.step`` of a reach skill on a robosuite-sized
  observation (marshalled inputs only: 4 arrays, 13 floats);
* ``sandbox_step_invoker``: the same through ``EcmInvoker.step`` (marshalling, checks,
  outcome record);
* ``inprocess_step`` / ``inprocess_step_invoker``: the same skill as a trusted in-process
  ``CodeSkill``;
* ``neural_predict`` / ``neural_step_invoker``: a SAC policy (2x256 MLP, the SB3 default)
  on a 13-dim observation, ``predict(deterministic=True)`` on CPU;
* ``sandbox_start``: spawn + imports + lock-down + handshake of a new worker;
* ``sandbox_timeout_recovery``: a call that hangs past a 50 ms timeout (kill + respawn
  started), then the next successful call (which waits for the new worker).

Prints a markdown table and saves ``benchmarks/results/sandbox.json``.

Run::

    .venv/bin/python benchmarks/bench_sandbox.py [--n 2000]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import markdown_table, save_results, summarize_ms, time_calls

from capevo.errors import Timeout
from capevo.records import Interface, IOSpec, Origin
from capevo.runtime.ecm import EcmInvoker, load_code, load_neural
from capevo.runtime.sandbox import SandboxedSkill

REACH = """
import numpy as np

PARAMS = {"gain": 8.0, "hover": 0.10, "tol": 0.01}


def _target(obs, params):
    return obs["cube_pos"] + np.array([0.0, 0.0, params["hover"]])


def act(obs, params):
    delta = (_target(obs, params) - obs["robot0_eef_pos"]) * params["gain"]
    move = np.clip(delta, -1.0, 1.0)
    grip = -1.0 if obs["robot0_gripper_qpos"][0] > 0.0 else 1.0
    return [move[0], move[1], move[2], 0.0, 0.0, 0.0, grip]


def done(obs, params):
    return float(np.linalg.norm(_target(obs, params) - obs["robot0_eef_pos"])) < params["tol"]
"""

INTERFACE = Interface(
    inputs=(
        IOSpec(name="robot0_eef_pos", shape=(3,)),
        IOSpec(name="robot0_eef_quat", shape=(4,)),
        IOSpec(name="robot0_gripper_qpos", shape=(2,)),
        IOSpec(name="cube_pos", shape=(3,)),
        IOSpec(name="cube_to_eef", shape=(1,)),
    ),
    outputs=(IOSpec(name="action", shape=(7,), low=-1.0, high=1.0),),
)


def robosuite_like_obs(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A Lift-sized raw observation (extra keys the skill does not declare included)."""
    return {
        "robot0_eef_pos": rng.normal(size=3),
        "robot0_eef_quat": rng.normal(size=4),
        "robot0_gripper_qpos": rng.normal(size=2),
        "robot0_joint_pos_cos": rng.normal(size=7),
        "robot0_joint_pos_sin": rng.normal(size=7),
        "robot0_joint_vel": rng.normal(size=7),
        "robot0_gripper_qvel": rng.normal(size=2),
        "cube_pos": rng.normal(size=3),
        "cube_quat": rng.normal(size=4),
        "cube_to_eef": rng.normal(size=1),
        "robot0_proprio-state": rng.normal(size=32),
        "object-state": rng.normal(size=10),
    }


def sac_zip(obs_dim: int, act_dim: int) -> bytes:
    import gymnasium as gym
    from stable_baselines3 import SAC

    class Box(gym.Env):  # a stand-in env only to give SAC its spaces
        observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, shape=(act_dim,), dtype=np.float32)

    model = SAC("MlpPolicy", Box(), learning_starts=10**6, buffer_size=16, device="cpu", seed=0)
    buf = io.BytesIO()
    model.save(buf)
    return buf.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=2000)
    args = parser.parse_args()
    n = args.n
    rng = np.random.default_rng(0)
    obs = robosuite_like_obs(rng)
    inputs = {s.name: np.asarray(obs[s.name], dtype=np.float32) for s in INTERFACE.inputs}
    results: dict[str, dict[str, float]] = {}

    starts = []
    for _ in range(5):
        t0 = time.perf_counter()
        s = SandboxedSkill(REACH)
        starts.append(time.perf_counter() - t0)
        s.close()
    results["sandbox_start"] = summarize_ms(starts)

    sandboxed = load_code(REACH, name="reach", origin=Origin.LLM, interface=INTERFACE)
    skill = sandboxed.runner
    assert isinstance(skill, SandboxedSkill)
    layers = dict(skill.layers)
    results["sandbox_ping"] = summarize_ms(time_calls(lambda i: skill.ping(), n, warmup=100))
    results["sandbox_step"] = summarize_ms(time_calls(lambda i: skill.step(inputs, timeout_s=1.0), n, warmup=100))
    inv = EcmInvoker(sandboxed, timeout_s=1.0, step_budget=None)
    results["sandbox_step_invoker"] = summarize_ms(time_calls(lambda i: inv.step(obs), n, warmup=100))
    sandboxed.close()

    local = load_code(REACH, name="reach", origin=Origin.MANUAL, interface=INTERFACE)
    runner = local.runner
    assert runner is not None
    results["inprocess_step"] = summarize_ms(time_calls(lambda i: runner.step(inputs, timeout_s=1.0), n, warmup=100))
    inv = EcmInvoker(local, timeout_s=1.0, step_budget=None)
    results["inprocess_step_invoker"] = summarize_ms(time_calls(lambda i: inv.step(obs), n, warmup=100))

    obs_dim = sum(int(np.prod(s.shape)) for s in INTERFACE.inputs)
    neural = load_neural(sac_zip(obs_dim, 7), name="reach-sac", interface=INTERFACE)
    policy = neural.runner
    vec = np.concatenate([inputs[s.name].ravel() for s in INTERFACE.inputs])
    results["neural_predict"] = summarize_ms(time_calls(lambda i: policy.predict(vec), n, warmup=100))  # type: ignore[union-attr]
    inv = EcmInvoker(neural, timeout_s=1.0, step_budget=None)
    results["neural_step_invoker"] = summarize_ms(time_calls(lambda i: inv.step(obs), n, warmup=100))

    hang = REACH + "\n\ndef _spin():\n    while True:\n        pass\n\n\nHANG = [False]\n"
    hang = hang.replace(
        "def act(obs, params):\n", "def act(obs, params):\n    if obs['cube_to_eef'][0] > 1e6:\n        _spin()\n", 1
    )
    with SandboxedSkill(hang) as s:
        stuck = dict(inputs, cube_to_eef=np.array([1e7], dtype=np.float32))
        recover = []
        for _ in range(5):
            t0 = time.perf_counter()
            with contextlib.suppress(Timeout):
                s.step(stuck, timeout_s=0.05)
            s.step(inputs, timeout_s=5.0)
            recover.append(time.perf_counter() - t0)
            s.restarts = 0  # measuring, not testing the restart cap
        results["sandbox_timeout_recovery"] = summarize_ms(recover)

    rows = [[k, v["n"], v["p50_ms"], v["p99_ms"], v["mean_ms"]] for k, v in results.items()]
    print(markdown_table(["measure", "n", "p50 ms", "p99 ms", "mean ms"], rows))
    print(f"\nsandbox layers: {layers}")
    path = save_results("sandbox", {"n": n, "layers": layers, "results": results})
    print(f"saved {path}")


if __name__ == "__main__":
    main()
