"""Digests that pin a task episode bit for bit: same seed, same actions -> same digest.

Computed from everything an episode exposes (flat and per-key observations, noisy and clean,
rewards, flags, infos, signals, robot state), hashed from exact float representations, so a
refactor of the task wrappers that changes any value by one ulp changes the digest.

A digest also depends on the machine: numpy picks its SIMD kernels by CPU feature at run time
(AVX2 and AVX-512 round some results differently), and the libraries' builds differ by version.
Golden tables are therefore keyed by :func:`machine_fingerprint`; :func:`expect_golden` compares
against this machine's entry and skips, saying how to add one, on a machine that has none.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest
from numpy.core._multiarray_umath import __cpu_features__
from threadpoolctl import threadpool_info

RECORDED_BEFORE_FINGERPRINTS = "recorded before fingerprints"
"""Key of the digests of the machine the suite was first written on, whose fingerprint is unknown."""


def blas_kernels() -> str:
    """The kernel set numpy's BLAS picked: OpenBLAS chooses on its own, by CPU or by the
    ``OPENBLAS_CORETYPE`` variable, so two machines with the same numpy features can differ here
    (a Zen 4 got its AVX-512 Cooperlake kernels; a Zen 5 whose environment sets
    ``OPENBLAS_CORETYPE=Haswell`` gets AVX2 ones) and round matrix products differently."""
    # numpy's wheel bundles its OpenBLAS in numpy.libs; scipy's and torch's BLAS live elsewhere.
    numpy_libs = str(Path(np.__file__).resolve().parent.parent / "numpy.libs")
    for lib in threadpool_info():
        if lib.get("user_api") == "blas" and str(lib.get("filepath", "")).startswith(numpy_libs):
            return f"{lib.get('internal_api')} {lib.get('version')} {lib.get('architecture')}"
    return "unknown"


def machine_fingerprint() -> str:
    """What a digest depends on besides the code: numpy's and MuJoCo's versions, the CPU
    features numpy dispatches on, and the kernels its BLAS picked."""
    features = ",".join(sorted(name for name, enabled in __cpu_features__.items() if enabled))
    text = f"numpy {np.__version__}; mujoco {mujoco.__version__}; cpu {features}; blas {blas_kernels()}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def expect_golden(got: Any, by_machine: Mapping[str, Any], *, generate: str) -> None:
    """Assert ``got`` is this machine's golden value; skip on a machine with no entry.

    The digests recorded before fingerprints existed count for any machine without an entry
    that reproduces them. ``generate`` says how to compute an entry at a known-good commit.
    """
    fingerprint = machine_fingerprint()
    want = by_machine.get(fingerprint)
    if want is not None:
        assert got == want
    elif got != by_machine.get(RECORDED_BEFORE_FINGERPRINTS):
        pytest.skip(
            f"no golden digests for machine {fingerprint} (numpy {np.__version__}, mujoco {mujoco.__version__}); "
            f"add an entry computed at a known-good commit with {generate}"
        )


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


def _as_tuple(value: Any) -> Any:
    return tuple(value.tolist()) if isinstance(value, np.ndarray) else value


def trace_digest(records: Any, run: Any) -> str:
    """Digest of an episode's trace records and outcome, without wall-clock durations and
    without what depends on Φ (interventions, unsafe counts): with a counting governor
    that is everything the episode loop decided."""
    d = Digest()
    for r in records:
        name = type(r).__name__
        if name == "Intervention":
            continue
        # A vector is digested as the tuple of its values, array or tuple alike, so these digests
        # also pin the values of traces recorded before the loop passed the env's arrays.
        fields = {
            f.name: _as_tuple(getattr(r, f.name))
            for f in dataclasses.fields(r)
            if f.name not in ("duration_s", "interventions", "unsafe_steps")
        }
        d.add((name, fields))
    o = run.outcome
    d.add((o.success, o.reward, o.steps, o.ecm_failures, run.end_reason, run.activations))
    return d.hexdigest()
