"""Task-agnostic offline play data for the skill-learning baselines (SPiRL, SkiMo; issue 20).

SPiRL (Pertsch et al., CoRL 2020, §3 and §5.1) and SkiMo (Shi et al., CoRL 2022, §3.1) learn
their skills from a large offline data set of play that was not collected for the downstream
task. Issue 20 asks for such data "collected in the same envs from scripted and random play",
with how documented. This module collects it, in the cell's own
:class:`~capevo.baselines.governed_env.GovernedTaskEnv` (same task, Φ, governance and
perturbations as every other step of the comparison), and stores it as one ``.npz``.

How the data is made (all of it is hand-written play; nothing here is learned). Episode ``j``
runs task seed ``OFFLINE_SEED_BASE + 1000 * seed + j`` and is one of these kinds, in turn:

* ``scripted``: the task's hand-written reference controller
  (:data:`capevo.runtime.tasks.scripted.REFERENCES`: T1 ``pick``, T2 ``place``, T3 ``stack``)
  with Gaussian noise of σ ``noise`` added to every action (then clipped to [-1, 1]). T4-T6 have
  no reference, so their data is random play only;
* ``smooth``: structured random play: a target action drawn uniformly from [-1, 1]^d every
  ``SMOOTH_HOLD`` steps, followed through a first-order filter (``a ← 0.8 a + 0.2 target``), so
  the arm makes sustained, varied motions (reaches, sweeps, gripper open and close) rather than
  jitter;
* ``uniform``: an independent uniform action in [-1, 1]^d every step.

With a reference the kinds cycle ``scripted, scripted, smooth, uniform`` (half the episodes
scripted), without one ``smooth, uniform``. Each step stores the observation the policy saw
(noise included), the action the robot executed (after governance, ``info["action"]``), the
task reward, the next observation and whether the episode ended. The scripted references make
the data *not* strictly task-agnostic for T1-T3 (they are the task's own hand-written
controllers, the same knowledge ours' code ECMs start from); the report's knowledge column says
"offline play data" and this docstring names the references.

The steps spent collecting are the env steps of :class:`OfflineData` (``env_steps``); the
methods report them as their starting knowledge, separately from the per-iteration budget.

Resumable: the file is written to a temporary name and renamed, so a file that exists is
complete; :func:`offline_data` loads it when its settings match and collects otherwise.

Invariants:
1. ``len(d.obs) == d.env_steps`` and ``d.env_steps`` is the env steps collecting took (the
   sum of its episodes' lengths); rows of one episode are contiguous and in step order.
2. Observations are float32 of the task's observation length, actions float32 in [-1, 1] of
   its action dimension.
3. Equal settings give equal data; :func:`offline_data` never recollects a complete file whose
   settings match, and refuses (:class:`Conflict`) one whose settings differ.
4. Offline seeds lie between the training seeds and the held-out evaluation seeds: no held-out
   episode is ever in the data.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capevo.baselines.base import HELD_OUT_SEED_BASE, MAX_CELL_SEED
from capevo.baselines.governed_env import GovernedTaskEnv
from capevo.errors import Conflict, Corrupt, Invalid
from capevo.runtime.envelope import PhiChoice
from capevo.runtime.tasks import task_spec
from capevo.runtime.tasks.scripted import REFERENCES

OFFLINE_SEED_BASE = 1_600_000_000
"""Task seeds of offline episodes: ``OFFLINE_SEED_BASE + 1000 * seed + j``; above every
training seed and AM's demonstration seeds (from 1.5e9 + 1000 * seed, under 1000 each), below
the held-out ones (2e9)."""
MAX_EPISODES = 1000
SMOOTH_HOLD = 10
"""Steps a ``smooth`` episode follows one random target action (the skill length H)."""
SMOOTH_GAIN = 0.2
KINDS_SCRIPTED = ("scripted", "scripted", "smooth", "uniform")
KINDS_RANDOM = ("smooth", "uniform")
FORMAT = 1
if OFFLINE_SEED_BASE + 1000 * MAX_CELL_SEED + MAX_EPISODES >= HELD_OUT_SEED_BASE:  # invariant 4, at import
    raise RuntimeError("offline seeds would reach the held-out evaluation seeds")


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class OfflineData:
    """Offline play of one task (see the module docstring); one row per env step."""

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    done: np.ndarray
    """The episode ended after this step (success or horizon)."""
    episode: np.ndarray
    """Per row, the episode's index ``j`` (int64)."""
    kinds: tuple[str, ...]
    """Per episode, how it was played: ``scripted``, ``smooth`` or ``uniform``."""
    successes: int
    settings: Mapping[str, Any]
    reused: bool = False
    """Loaded from an earlier, complete file rather than collected now."""

    @property
    def env_steps(self) -> int:
        """Env steps collecting took."""
        return len(self.obs)

    @property
    def episodes(self) -> int:
        return len(self.kinds)

    def describe(self) -> str:
        """One line for a record's notes and the report's knowledge column."""
        counts = {k: self.kinds.count(k) for k in dict.fromkeys(self.kinds)}
        kinds = ", ".join(f"{n} {k}" for k, n in counts.items())
        reused = " (reused: collected earlier with the same settings)" if self.reused else ""
        return (
            f"offline play data: {self.env_steps} env steps in {self.episodes} episodes ({kinds}; "
            f"{self.successes} successful){reused}"
        )


def offline_settings(
    task: str,
    *,
    episodes: int,
    seed: int,
    noise: float,
    phi: PhiChoice,
    governance: bool,
    perturbations: bool,
    horizon: int | None,
) -> dict[str, Any]:
    """The settings that determine the data (stored with it; a reuse must match them).

    Raises:
        Invalid: an unknown task, or a value out of range.
    """
    spec = task_spec(task)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or not 1 <= episodes <= MAX_EPISODES:
        raise Invalid(
            f"offline episodes must be an integer from 1 to {MAX_EPISODES}, got {episodes!r}",
            details={"field": "options.offline_episodes"},
        )
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_CELL_SEED:
        raise Invalid(f"seed must be an integer from 0 to {MAX_CELL_SEED}, got {seed!r}", details={"field": "seed"})
    if isinstance(noise, bool) or not isinstance(noise, (int, float)) or not 0.0 <= float(noise) <= 2.0:
        raise Invalid(
            f"offline noise must be a number from 0 to 2, got {noise!r}", details={"field": "options.offline_noise"}
        )
    if not isinstance(phi, str):
        raise Invalid("offline data needs Φ named by a string (task, paper or a path)", details={"field": "phi"})
    return {
        "format": FORMAT,
        "task": spec.name,
        "episodes": episodes,
        "seed": seed,
        "noise": float(noise),
        "phi": phi,
        "governance": bool(governance),
        "perturbations": bool(perturbations),
        "horizon": horizon if horizon is not None else spec.default_horizon,
    }


def collect(settings: Mapping[str, Any]) -> OfflineData:
    """Play ``settings["episodes"]`` episodes in the governed env (see the module docstring).

    Args:
        settings: From :func:`offline_settings`.

    Returns:
        The data, in memory.
    """
    task = settings["task"]
    reference = REFERENCES.get(task)
    cycle = KINDS_SCRIPTED if reference is not None else KINDS_RANDOM
    rng = np.random.default_rng([settings["seed"], FORMAT])
    env = GovernedTaskEnv(
        task,
        phi=settings["phi"],
        governance=settings["governance"],
        perturbations=settings["perturbations"],
        horizon=settings["horizon"],
    )
    rows: dict[str, list[Any]] = {k: [] for k in ("obs", "action", "reward", "next_obs", "done", "episode")}
    kinds: list[str] = []
    successes = 0
    with contextlib.closing(env):
        dim = env.action_space.shape[0]
        for j in range(settings["episodes"]):
            kind = cycle[j % len(cycle)]
            kinds.append(kind)
            obs, _ = env.reset(seed=OFFLINE_SEED_BASE + 1000 * settings["seed"] + j)
            smooth = np.zeros(dim)
            target = np.zeros(dim)
            done = False
            step = 0
            info: dict[str, Any] = {}
            while not done:
                if kind == "scripted" and reference is not None:
                    proposal = reference(env.obs_dict) + rng.normal(0.0, settings["noise"], dim)
                elif kind == "smooth":
                    if step % SMOOTH_HOLD == 0:
                        target = rng.uniform(-1.0, 1.0, dim)
                    smooth = (1.0 - SMOOTH_GAIN) * smooth + SMOOTH_GAIN * target
                    proposal = smooth
                else:
                    proposal = rng.uniform(-1.0, 1.0, dim)
                next_obs, reward, terminated, truncated, info = env.step(np.clip(proposal, -1.0, 1.0))
                done = terminated or truncated
                rows["obs"].append(obs)
                rows["action"].append(info["action"])
                rows["reward"].append(reward if np.isfinite(reward) else 0.0)
                rows["next_obs"].append(next_obs)
                rows["done"].append(done)
                rows["episode"].append(j)
                obs = next_obs
                step += 1
            successes += bool(info.get("is_success"))
    return OfflineData(
        obs=np.asarray(rows["obs"], dtype=np.float32),
        action=np.clip(np.asarray(rows["action"], dtype=np.float32), -1.0, 1.0),
        reward=np.asarray(rows["reward"], dtype=np.float32),
        next_obs=np.asarray(rows["next_obs"], dtype=np.float32),
        done=np.asarray(rows["done"], dtype=bool),
        episode=np.asarray(rows["episode"], dtype=np.int64),
        kinds=tuple(kinds),
        successes=successes,
        settings=dict(settings),
    )


def save(data: OfflineData, path: Path) -> None:
    """Write ``data`` to ``path`` atomically (a temporary file renamed): a file that exists is complete."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    meta = {"settings": dict(data.settings), "kinds": list(data.kinds), "successes": data.successes}
    with open(tmp, "wb") as f:
        np.savez(
            f,
            obs=data.obs,
            action=data.action,
            reward=data.reward,
            next_obs=data.next_obs,
            done=data.done,
            episode=data.episode,
            meta=np.asarray(json.dumps(meta, sort_keys=True)),
        )
    os.replace(tmp, path)


def load(path: Path) -> OfflineData:
    """Read a file :func:`save` wrote.

    Raises:
        Corrupt: the file is not such a file, or its arrays disagree.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("obs", "action", "reward", "next_obs", "done", "episode")}
            meta = json.loads(str(z["meta"]))
    except (OSError, KeyError, ValueError) as exc:
        raise Corrupt(f"{path}: not a complete offline data file ({exc})", details={"path": str(path)}) from None
    n = len(arrays["obs"])
    if any(len(a) != n for a in arrays.values()) or len(meta.get("kinds", ())) != meta["settings"]["episodes"]:
        raise Corrupt(f"{path}: offline data arrays disagree", details={"path": str(path)})
    return OfflineData(
        **arrays, kinds=tuple(meta["kinds"]), successes=int(meta["successes"]), settings=meta["settings"], reused=True
    )


def offline_data(path: str | os.PathLike[str], settings: Mapping[str, Any]) -> OfflineData:
    """The offline data of ``settings`` at ``path``: loaded if a complete matching file is there, else collected.

    Args:
        path: The ``.npz`` file (in the cell's work directory).
        settings: From :func:`offline_settings`.

    Returns:
        The data; ``reused`` says whether it was loaded.

    Raises:
        Conflict: ``path`` holds data of other settings (naming the first that differs).
        Corrupt: ``path`` exists but is not a complete offline data file.
    """
    p = Path(path)
    if p.exists():
        data = load(p)
        stored = dict(data.settings)
        for key in sorted(set(stored) | set(settings)):
            if stored.get(key) != settings.get(key):
                raise Conflict(
                    f"{p}: offline data was collected with {key}={stored.get(key)!r}, not {settings.get(key)!r}",
                    details={"path": str(p), "field": key},
                )
        return data
    data = collect(settings)
    save(data, p)
    return data
