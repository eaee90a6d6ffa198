"""Digests that pin a task episode bit for bit: same seed, same actions -> same digest.

Computed from everything an episode exposes (flat and per-key observations, noisy and clean,
rewards, flags, infos, signals, robot state), hashed from exact float representations, so a
refactor of the task wrappers that changes any value by one ulp changes the digest.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any

import numpy as np


class Digest:
    """An incremental SHA-256 over exact renderings of episode values."""

    def __init__(self) -> None:
        self._h = hashlib.sha256()

    def add(self, value: Any) -> None:
        """Hash ``value`` (arrays by dtype, shape and bytes; floats by ``repr``; containers in order)."""
        h = self._h
        if isinstance(value, np.ndarray):
            h.update(f"nd{value.dtype.str}{value.shape}".encode())
            h.update(np.ascontiguousarray(value).tobytes())
        elif isinstance(value, dict):
            h.update(b"{")
            for k in sorted(value):
                h.update(repr(k).encode())
                self.add(value[k])
            h.update(b"}")
        elif isinstance(value, (tuple, list)):
            h.update(b"(")
            for v in value:
                self.add(v)
            h.update(b")")
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            h.update(type(value).__name__.encode())
            self.add({f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
        else:
            h.update(f"{type(value).__name__}:{value!r};".encode())

    def hexdigest(self) -> str:
        return self._h.hexdigest()


def task_episode_digest(env: Any, seed: int, steps: int) -> str:
    """Reset ``env`` with ``seed``, take ``steps`` seeded random actions in +-0.7 and digest all of it."""
    d = Digest()
    rng = np.random.default_rng(1000 + seed)

    def snapshot() -> None:
        d.add(env.obs_dict)
        d.add(env.clean_obs_dict)
        d.add(env.signals())
        # The physical state only: governance may add derived fields to the arms' records.
        d.add([(a.eef_pos, a.eef_force, a.eef_rot) for a in env.robot_state().arms])

    obs, info = env.reset(seed=seed)
    d.add(obs)
    d.add(info)
    snapshot()
    for _ in range(steps):
        a = rng.uniform(-0.7, 0.7, env.action_space.shape)
        obs, reward, terminated, truncated, info = env.step(a)
        d.add((obs, reward, terminated, truncated, info))
        snapshot()
        if terminated or truncated:
            break
    return d.hexdigest()


def trace_digest(records: Any, run: Any) -> str:
    """Digest of an episode's trace records and outcome, without wall-clock durations and
    without what depends on Φ (interventions, unsafe counts): with a counting governor
    that is everything the episode loop decided."""
    d = Digest()
    for r in records:
        name = type(r).__name__
        if name == "Intervention":
            continue
        fields = {
            f.name: getattr(r, f.name)
            for f in dataclasses.fields(r)
            if f.name not in ("duration_s", "interventions", "unsafe_steps")
        }
        d.add((name, fields))
    o = run.outcome
    d.add((o.success, o.reward, o.steps, o.ecm_failures, run.end_reason, run.activations))
    return d.hexdigest()
