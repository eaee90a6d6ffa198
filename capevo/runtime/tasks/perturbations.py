"""Stochastic perturbations applied on top of each task's nominal scene distribution, and the
seeded random streams that draw them.

One episode seed fixes the whole instance: the robosuite scene (object placement, joint
initialisation noise) and every perturbation draw. Each kind of draw has its own stream, so
the draws of one kind never depend on another kind's settings nor on the actions taken:
two policy versions run on the same seed see the same scene, the same observation noise at
step t and the same dropped steps.

Invariants:
1. ``EpisodeRngs(seed)`` for equal seeds produce equal draw sequences, stream by stream.
2. The drop decision at step t is ``u_t < actuation_failure_p`` with ``u_t`` from the drop
   stream; one ``u_t`` is drawn every step whatever the probability, so raising the probability
   only adds dropped steps.
3. ``Perturbations`` refuses negative magnitudes and probabilities outside [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from capevo.errors import Invalid


@dataclass(frozen=True, slots=True, kw_only=True)
class Perturbations:
    """Which perturbations are on and how strong; the defaults are the benchmark setting.

    Args:
        object_position_jitter: Half-width in metres of a uniform offset added to the initial
            x and y of every movable object after robosuite has placed it (for peg_in_hole,
            to each end effector's initial x and y, through the arm's joints).
        obs_position_noise_std: Standard deviation in metres of i.i.d. Gaussian noise added every
            step to each Cartesian position observation (``TaskSpec.position_keys``).
        actuation_failure_p: Probability that a step's commanded action is dropped and replaced
            by zeros (hold pose, keep gripper); recorded in ``info["actuation_dropped"]``.

    Raises:
        Invalid: a value is negative, not finite, or a probability is above 1.
    """

    object_position_jitter: float = 0.05
    obs_position_noise_std: float = 0.01
    actuation_failure_p: float = 0.05

    def __post_init__(self) -> None:
        for name in ("object_position_jitter", "obs_position_noise_std", "actuation_failure_p"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise Invalid(f"{name} must be a finite number >= 0, got {value!r}", details={"field": name})
        if self.actuation_failure_p > 1:
            raise Invalid(
                f"actuation_failure_p is a probability, got {self.actuation_failure_p!r}",
                details={"field": "actuation_failure_p"},
            )

    @classmethod
    def none(cls) -> Perturbations:
        """All perturbations off: the clean task."""
        return cls(object_position_jitter=0.0, obs_position_noise_std=0.0, actuation_failure_p=0.0)

    @property
    def any(self) -> bool:
        return bool(self.object_position_jitter or self.obs_position_noise_std or self.actuation_failure_p)


class EpisodeRngs:
    """The independent random streams of one episode, all derived from one seed.

    Args:
        seed: Episode seed; None draws fresh OS entropy.

    Attributes:
        scene: Seeds robosuite's own generator (placement, joint init noise).
        jitter: Initial object position jitter.
        obs_noise: Observation noise.
        drop: Actuation failures.
    """

    __slots__ = ("drop", "jitter", "obs_noise", "scene")

    def __init__(self, seed: int | None) -> None:
        scene, jitter, obs_noise, drop = np.random.SeedSequence(seed).spawn(4)
        self.scene = np.random.default_rng(scene)
        self.jitter = np.random.default_rng(jitter)
        self.obs_noise = np.random.default_rng(obs_noise)
        self.drop = np.random.default_rng(drop)
