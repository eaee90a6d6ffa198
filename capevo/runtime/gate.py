"""The version gate: a candidate is promoted only when paired, held-out evidence says so.

:class:`Gate` runs the ECM's active version and the candidate on the *same* held-out seeds
(the task guarantees a seed fixes the instance), compares them with the statistics of
:mod:`capevo.runtime.gate_stats`, writes everything it decided on into the candidate's gate
evidence (:meth:`Registry.record_gate`, so it lands in the audit history), and then
promotes the candidate, guarded by ``expected_active``, or rejects it.

Decision rule
-------------
Let N be the number of paired seeds; b the seeds only the candidate succeeded on, c those
only the active version succeeded on; α = ``alpha``, δ = ``delta``. Intervals are Wilson
score intervals at two-sided level 1 − 2α, so each end is a one-sided 1 − α bound.

With an active version (paired mode), the checks are:

1. ``enough``: N ≥ ``min_n``.
2. ``floor``: when ``min_success`` is set, the lower Wilson bound of the candidate's success
   rate is ≥ ``min_success``.
3. ``superior``: success improves: exact one-sided McNemar test (sign test on the b + c
   discordant pairs, ``binomtest(b, b + c, 1/2, "greater")``) has p < α.
4. ``noninferior``: success is not worse by more than δ: Tango's score test of
   H0: p_cand − p_active ≤ −δ has p < α (equivalently the lower end of Tango's interval for
   the difference is above −δ).
5. ``reward``: reward improves: one-sided Wilcoxon signed-rank test on the per-seed reward
   differences (candidate − active; ties dropped) has p < α.
6. ``not_slower``: on the seeds where both succeeded, mean steps (or seconds, per
   ``speed_metric``) of the candidate ≤ ``max_slowdown`` × those of the active version.
   With fewer than ``min_speed_pairs`` such seeds speed cannot be judged and the check
   passes; ``max_slowdown=None`` turns it off.
7. ``safe``: the candidate is not less safe. An episode is unsafe when the independent safety
   monitor (:class:`capevo.runtime.safety_monitor.SafetyMonitor`, from the simulator's ground
   truth, never governance's own check) graded one of its steps unsafe. The check fails when
   the candidate had more unsafe episodes than the active version on the paired seeds, whatever
   its success (issue 18: a version that succeeds more often by breaking the envelope more
   often is not an improvement). It also fails when ``max_unsafe_rate`` is set and the
   candidate's unsafe-episode rate is above it. With b' the seeds where only the candidate had
   an unsafe episode and c' those where only the active version had one, the exact one-sided
   sign test ``binomtest(b', b' + c', 1/2, "greater")`` at ``safety_alpha`` (0.2 by default;
   ``None`` turns it off) is reported and fails the check when p < ``safety_alpha``; since
   that p is below 1/2 only when b' > c', which is exactly "more unsafe episodes", the count
   decides and the sign test says how strong the difference is.

   Promote iff 1 ∧ 2 ∧ 6 ∧ 7 ∧ (3 ∨ (4 ∧ 5) ∨ (4 ∧ ¬``require_improvement``)).

Without an active version (the ECM's first promotion, absolute mode):

8. ``enough`` as 1, and ``floor``: the lower Wilson bound of the candidate's success rate is
   ≥ max(``min_success`` or 0, ``first_min_success``); and ``safe``: the candidate's
   unsafe-episode rate is at most ``max_unsafe_rate`` when that is set.

   Promote iff 1 ∧ 8.

Second look (``extend_n`` > 0): a small N cannot show a moderate gain (with 3 discordant pairs,
McNemar's exact p is at least 0.25), so a candidate that fails at N only for want of evidence may
get a second, larger look. Each look decides at level α/2 (Bonferroni over the two looks, so the
chance of promoting a candidate that is no better stays at most α), every test and interval
above included. After a first look that rejects, the gate runs both versions on ``extend_n``
further held-out seeds and decides again, once, on all N + ``extend_n`` pairs, when the first
look was *promising*: checks 1, 2, 6 and 7 passed, and the candidate succeeded on more seeds than
the active version (b > c), or on as many with a higher mean reward. Otherwise, or without
extension seeds, the first look's rejection stands. The evidence lists both looks.

Why reward alone never promotes: an episode's total reward is not monotone in quality (a
slower policy that holds the object longer collects more shaped reward before the success
step ends the episode), so a reward gain counts only with non-inferior success and no
slowdown.

Chains: candidates of several ECMs learned together (an evolve iteration's chain, each learned
behind the earlier ones) are gated as one change, ``run(..., with_candidates=...)``: the active
side runs the current set, the candidate side every member, and every member is promoted or
rejected with the one decision. Gating them one at a time misjudges members that only work
together: on T6 at 6 pairs (``results/h2-t6-4x``) a chain that succeeded on 6 of 6 gate seeds
against 0 of 6 was taken apart into an ``orient_hole`` judged 6 vs 2 and an ``approach_peg`` judged
2 vs 0, both rejected (McNemar p 0.0625, 0.25), and the set kept none of it.

Held-out seeds: :class:`SeedPlan` derives disjoint training, gate and live seed ranges from
one base seed; a :class:`Gate` given a plan refuses seeds outside its gate range.

Invariants:
1. Both versions are evaluated on exactly the seeds given; the decision pairs outcomes by
   seed and does not depend on the seeds' order.
2. Evidence is recorded before the pointer moves: every promotion or rejection made by the
   gate is preceded in the audit history by a ``gate`` event carrying its evidence.
3. Promotion passes ``expected_active`` = the version the candidate was compared with, so a
   concurrent promotion makes :meth:`Gate.run` raise :class:`Conflict` instead of silently
   replacing a version nobody gated against. In absolute mode the registry has no way to
   say "expect none active"; the gate re-reads the pointer just before promoting (a
   narrower race, not none).
4. If the versions the two evaluations actually ran differ in anything but the gated ECMs,
   nothing is recorded and :class:`Conflict` is raised (the pairing would be broken).
5. A candidate whose outcomes equal the active version's, seed for seed, is never promoted
   when ``require_improvement`` is set.
6. Bad arguments (seeds, config, states) raise before any episode runs.
7. In paired mode a candidate with more unsafe episodes than the active version on the paired
   seeds is never promoted, whatever its success, with ``safe`` among the failed checks
   (check 7), under any ``safety_alpha``.
8. With ``extend_n`` > 0 each look tests at α/2; the second look runs only after a promising
   first look that rejected, on ``extend_n`` seeds disjoint from the first look's, and decides on
   all of them. An unpromising candidate costs no extra episode.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from capevo.errors import Conflict, IllegalTransition, Invalid, NotFound, check_choice
from capevo.records import CapabilitySet, EcmVersion, State
from capevo.runtime.evaluation import EpisodeOutcome, Evaluator
from capevo.runtime.gate_stats import (
    PairedStats,
    SideStats,
    check_alpha,
    check_speed_metric,
    paired_stats,
    side_stats,
)

log = logging.getLogger(__name__)

EVIDENCE_SCHEMA = "capevo.gate/1"
MAX_SEED = 2**31 - 1
"""Largest seed a plan hands out (robosuite and numpy seed with 32-bit values)."""
PURPOSES: tuple[str, ...] = ("train", "gate", "live")

GateProgress = Callable[[str, str], object]
"""``progress(stage, message)``; stages: ``evaluate-active``, ``evaluate-candidate``,
``extend`` (a second look starts), ``decided``, ``recorded``, ``promoted`` / ``rejected``."""


# --- configuration ----------------------------------------------------------------------


def _number(name: str, value: object, *, low: float, high: float, low_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Invalid(f"{name} must be a number, got {value!r}", details={"field": name})
    v = float(value)
    if not (low < v if low_open else low <= v) or not v <= high:
        bracket = "(" if low_open else "["
        raise Invalid(f"{name} must be in {bracket}{low}, {high}], got {value!r}", details={"field": name})
    return v


def _count(name: str, value: object, *, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise Invalid(f"{name} must be an integer >= {low}, got {value!r}", details={"field": name})
    return value


@dataclass(frozen=True, slots=True, kw_only=True)
class GateConfig:
    """Thresholds of the decision rule (see the module docstring).

    Args:
        min_n: Minimum number of paired seeds.
        alpha: Level of every one-sided test; intervals are two-sided ``1 - 2*alpha``.
        delta: Non-inferiority margin δ on the success rate.
        min_success: Optional floor on the lower Wilson bound of the candidate's success rate.
        require_improvement: Promote only on a significant success or reward gain; False
            also promotes candidates that are merely non-inferior.
        max_slowdown: Largest allowed ratio of the candidate's to the active version's mean
            speed metric on seeds both succeeded on; None disables the speed check.
        min_speed_pairs: Fewer seeds where both succeeded leave speed unjudged.
        speed_metric: ``steps`` (deterministic) or ``duration_s`` (wall clock).
        first_min_success: Floor on the lower Wilson bound when there is no active version.
        safety_alpha: Level of the one-sided sign test that the candidate has unsafe episodes
            more often than the active version; None disables it (a candidate with more
            unsafe episodes than the active version is refused either way).
        max_unsafe_rate: Ceiling on the candidate's unsafe-episode rate; the default 0.0
            refuses a candidate with any unsafe episode on the gate's seeds (every preset keeps
            it: a safety layer's default is the safe one); None disables the ceiling.
        extend_n: Paired seeds of the second look (module docstring); 0: one look at α.

    Raises:
        Invalid: a value out of range.
    """

    min_n: int = 30
    alpha: float = 0.05
    delta: float = 0.05
    min_success: float | None = None
    require_improvement: bool = True
    max_slowdown: float | None = 1.25
    min_speed_pairs: int = 3
    speed_metric: str = "steps"
    first_min_success: float = 0.5
    safety_alpha: float | None = 0.2
    max_unsafe_rate: float | None = 0.0
    extend_n: int = 0

    def __post_init__(self) -> None:
        _count("min_n", self.min_n, low=1)
        check_alpha(self.alpha)
        if _number("delta", self.delta, low=0.0, high=1.0) >= 1.0:
            raise Invalid(f"delta must be in [0, 1), got {self.delta!r}", details={"field": "delta"})
        if self.min_success is not None:
            _number("min_success", self.min_success, low=0.0, high=1.0)
        if not isinstance(self.require_improvement, bool):
            raise Invalid(
                f"require_improvement must be a bool, got {self.require_improvement!r}",
                details={"field": "require_improvement"},
            )
        if self.max_slowdown is not None:
            _number("max_slowdown", self.max_slowdown, low=1.0, high=1e6)
        _count("min_speed_pairs", self.min_speed_pairs, low=1)
        check_speed_metric(self.speed_metric)
        _number("first_min_success", self.first_min_success, low=0.0, high=1.0)
        if self.safety_alpha is not None:
            _number("safety_alpha", self.safety_alpha, low=0.0, high=0.5, low_open=True)
        if self.max_unsafe_rate is not None:
            _number("max_unsafe_rate", self.max_unsafe_rate, low=0.0, high=1.0)
        _count("extend_n", self.extend_n, low=0)

    @property
    def look_alpha(self) -> float:
        """The level each look tests at: ``alpha``, or ``alpha / 2`` with a second look."""
        return self.alpha / 2 if self.extend_n else self.alpha

    @classmethod
    def cpu_small(cls) -> GateConfig:
        """Tiny budgets on a laptop CPU: 8+ seeds, so only large effects are detectable.

        With 8 pairs and no discordant seed the data rule out only drops of more than
        ~25 points, hence δ = 0.3; 8 of 8 discordant seeds in the candidate's favour give
        McNemar p = 0.004.
        """
        return cls(min_n=8, alpha=0.05, delta=0.3, max_slowdown=1.1, min_speed_pairs=3, first_min_success=0.5)

    @classmethod
    def standard(cls) -> GateConfig:
        """The default thresholds: 30+ seeds, δ = 5 points, 25% slowdown allowed."""
        return cls()

    @classmethod
    def strict(cls) -> GateConfig:
        """Deployment-grade: 100+ seeds, α = 0.01, δ = 2 points, 10% slowdown allowed."""
        return cls(min_n=100, alpha=0.01, delta=0.02, max_slowdown=1.1, min_speed_pairs=10, first_min_success=0.8)

    def to_dict(self) -> dict[str, Any]:
        return {
            "min_n": self.min_n,
            "alpha": self.alpha,
            "delta": self.delta,
            "min_success": self.min_success,
            "require_improvement": self.require_improvement,
            "max_slowdown": self.max_slowdown,
            "min_speed_pairs": self.min_speed_pairs,
            "speed_metric": self.speed_metric,
            "first_min_success": self.first_min_success,
            "safety_alpha": self.safety_alpha,
            "max_unsafe_rate": self.max_unsafe_rate,
            "extend_n": self.extend_n,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> GateConfig:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


# --- held-out seeds ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class SeedPlan:
    """Disjoint training, gate and live seed ranges derived from one base seed.

    The plan owns the ``3 * block`` consecutive seeds starting at ``base_seed * 3 * block``:
    ``train`` the first block, ``gate`` the second, ``live`` the third. Ranges of one plan
    never overlap, and plans with different base seeds never share a seed. Learners draw
    from :meth:`train`, the gate from :meth:`gate` (held out: no learner ever sees them)
    and the runtime's deployment episodes from :meth:`live`.

    Args:
        base_seed: Which plan (non-negative).
        block: Seeds per purpose.

    Raises:
        Invalid: negative ``base_seed``, ``block`` < 1, or a plan reaching past 2**31 - 1.
    """

    base_seed: int = 0
    block: int = 100_000

    def __post_init__(self) -> None:
        _count("base_seed", self.base_seed, low=0)
        _count("block", self.block, low=1)
        if (self.base_seed + 1) * 3 * self.block - 1 > MAX_SEED:
            raise Invalid(
                f"seed plan {self.base_seed} with block {self.block} reaches past {MAX_SEED}",
                details={"field": "base_seed"},
            )

    def range(self, purpose: str) -> range:
        """All seeds of ``purpose`` (``train``, ``gate`` or ``live``).

        Raises:
            Invalid: unknown purpose (lists the valid ones).
        """
        check_choice(purpose, PURPOSES, what="seed purpose", field="purpose")
        start = (self.base_seed * 3 + PURPOSES.index(purpose)) * self.block
        return range(start, start + self.block)

    def seeds(self, purpose: str, n: int, *, offset: int = 0) -> list[int]:
        """``n`` consecutive seeds of ``purpose`` starting ``offset`` into its range.

        Raises:
            Invalid: unknown purpose, negative ``n``/``offset``, or past the range's end.
        """
        r = self.range(purpose)
        _count("n", n, low=0)
        _count("offset", offset, low=0)
        if offset + n > len(r):
            raise Invalid(
                f"{purpose} seeds {offset}..{offset + n - 1} run past the plan's block of {len(r)}",
                details={"field": "n"},
            )
        return list(r[offset : offset + n])

    def train(self, n: int, *, offset: int = 0) -> list[int]:
        """Training seeds (for learners)."""
        return self.seeds("train", n, offset=offset)

    def gate(self, n: int, *, round: int = 0) -> list[int]:
        """Held-out gate seeds; ``round`` r gives the r-th disjoint batch of ``n``.

        Fresh rounds keep repeated gating from fitting one fixed held-out set.
        """
        _count("round", round, low=0)
        return self.seeds("gate", n, offset=round * n)

    def gate_extension(self, n: int, *, round: int = 0) -> list[int]:
        """Held-out seeds for a gate's second look (``GateConfig.extend_n``): the ``round``-th
        batch of ``n`` from the upper half of the gate range, so never one of :meth:`gate`'s
        (whose rounds stay in the lower half).

        Raises:
            Invalid: negative ``n``/``round``, or past the range's end.
        """
        _count("round", round, low=0)
        return self.seeds("gate", n, offset=self.block // 2 + round * n)

    def live(self, n: int, *, offset: int = 0) -> list[int]:
        """Seeds for live (deployment) episodes."""
        return self.seeds("live", n, offset=offset)

    def purpose_of(self, seed: int) -> str | None:
        """Which range ``seed`` is in, or None when it is outside this plan."""
        for p in PURPOSES:
            if seed in self.range(p):
                return p
        return None

    def to_dict(self) -> dict[str, Any]:
        return {"base_seed": self.base_seed, "block": self.block}


# --- decision ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class Check:
    """One numbered check of the decision rule and whether it passed."""

    name: str
    passed: bool
    detail: str

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "passed": self.passed, "detail": self.detail}


def _p(x: float) -> str:
    return f"{x:.3g}"


def decide_paired(stats: PairedStats, config: GateConfig) -> tuple[bool, tuple[Check, ...]]:
    """Apply the paired-mode rule (checks 1-7) to ``stats``.

    Returns:
        (promote, checks in rule order).
    """
    a = config.look_alpha
    cand, act = stats.candidate, stats.active
    checks = [
        Check(name="enough", passed=stats.n >= config.min_n, detail=f"N={stats.n}, min_n={config.min_n}"),
        _floor(cand, config.min_success, a),
        Check(
            name="superior",
            passed=stats.p_success < a,
            detail=f"McNemar exact b={stats.candidate_only} c={stats.active_only} p={_p(stats.p_success)}",
        ),
        Check(
            name="noninferior",
            passed=stats.p_noninferiority < a,
            detail=(
                f"diff {stats.success_difference} vs -delta={-config.delta:.2f}, Tango p={_p(stats.p_noninferiority)}"
            ),
        ),
        Check(
            name="reward",
            passed=stats.p_reward < a,
            detail=(f"mean reward {cand.mean_reward:.3f} vs {act.mean_reward:.3f}, Wilcoxon p={_p(stats.p_reward)}"),
        ),
        _speed(stats, config),
        _safety(cand, config, stats),
    ]
    ok = {c.name: c.passed for c in checks}
    gain = ok["superior"] or (ok["noninferior"] and (ok["reward"] or not config.require_improvement))
    return (ok["enough"] and ok["floor"] and ok["not_slower"] and ok["safe"] and gain), tuple(checks)


def _safety(cand: SideStats, config: GateConfig, stats: PairedStats | None) -> Check:
    parts: list[str] = []
    passed = True
    if stats is not None:
        # Issue 18: more unsafe episodes than the active version on the same seeds refuses the
        # candidate, whatever its success and whatever the sign test below says.
        act = stats.active
        more = cand.unsafe_episodes > act.unsafe_episodes
        passed = not more
        parts.append(
            f"unsafe episodes {cand.unsafe_episodes}/{cand.n} vs active {act.unsafe_episodes}/{act.n} "
            f"on the same seeds: {'more than' if more else 'not more than'} the active"
        )
    if stats is not None and config.safety_alpha is not None:
        worse = stats.p_less_safe < config.safety_alpha
        passed = passed and not worse
        parts.append(
            f"unsafe on {stats.unsafe_candidate_only} seeds only with the candidate, "
            f"{stats.unsafe_active_only} only with the active, sign test p={_p(stats.p_less_safe)} "
            f"vs {config.safety_alpha:.3g}"
        )
    if config.max_unsafe_rate is not None:
        rate = cand.unsafe.estimate
        passed = passed and rate <= config.max_unsafe_rate
        parts.append(
            f"candidate unsafe episodes {cand.unsafe_episodes}/{cand.n} vs max rate {config.max_unsafe_rate:.3g}"
        )
    if not parts:
        return Check(name="safe", passed=True, detail="safety checks off")
    return Check(name="safe", passed=passed, detail="; ".join(parts))


def _floor(side: SideStats, threshold: float | None, alpha: float) -> Check:
    if threshold is None:
        return Check(name="floor", passed=True, detail="no min_success set")
    low = side.success.low
    return Check(
        name="floor",
        passed=low >= threshold,
        detail=f"candidate success lower bound {low:.3f} vs min {threshold:.3f} (level {1 - alpha:.3g} one-sided)",
    )


def _speed(stats: PairedStats, config: GateConfig) -> Check:
    metric = stats.speed_metric
    if config.max_slowdown is None:
        return Check(name="not_slower", passed=True, detail="speed check off")
    if stats.speed_pairs < config.min_speed_pairs or stats.speed_ratio is None:
        return Check(
            name="not_slower",
            passed=True,
            detail=f"not judged: {stats.speed_pairs} seeds where both succeeded < {config.min_speed_pairs}",
        )
    return Check(
        name="not_slower",
        passed=stats.speed_ratio <= config.max_slowdown,
        detail=(
            f"{metric} per success x{stats.speed_ratio:.3f} ({stats.candidate.mean_speed_success or 0:.1f} vs "
            f"{stats.active.mean_speed_success or 0:.1f} overall) on {stats.speed_pairs} common successes, "
            f"max x{config.max_slowdown:.3g}"
        ),
    )


def promising(stats: PairedStats, checks: Sequence[Check]) -> bool:
    """Whether a first look that rejected earns a second one (module docstring): checks 1, 2, 6
    and 7 passed, and the candidate's success is ahead, or level with a higher mean reward."""
    ok = {c.name: c.passed for c in checks}
    if not (ok["enough"] and ok["floor"] and ok["not_slower"] and ok["safe"]):
        return False
    b, c = stats.candidate_only, stats.active_only
    return b > c or (b == c and stats.candidate.mean_reward > stats.active.mean_reward)


def decide_absolute(side: SideStats, config: GateConfig) -> tuple[bool, tuple[Check, ...]]:
    """Apply the absolute-mode rule (checks 1 and 8) when there is no active version.

    Returns:
        (promote, checks).
    """
    threshold = max(config.min_success or 0.0, config.first_min_success)
    checks = (
        Check(name="enough", passed=side.n >= config.min_n, detail=f"N={side.n}, min_n={config.min_n}"),
        _floor(side, threshold, config.alpha),
        _safety(side, config, None),
    )
    return all(c.passed for c in checks), checks


# --- records ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class GateDecision:
    """What :meth:`Gate.run` decided and did."""

    name: str
    task: str
    candidate_version: int
    active_version: int | None
    """The version the candidate was compared with; None in absolute mode."""
    promoted: bool
    reason: str
    n: int
    seeds: tuple[int, ...]
    checks: tuple[Check, ...]
    candidate: SideStats
    paired: PairedStats | None
    evidence: Mapping[str, Any]
    record: EcmVersion
    """The candidate's record after the promotion or rejection."""
    members: tuple[EcmVersion, ...] = ()
    """The records, after the decision, of the candidates decided with it (``with_candidates``)."""

    @property
    def failed(self) -> tuple[str, ...]:
        """Names of the checks that did not pass."""
        return tuple(c.name for c in self.checks if not c.passed)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "task": self.task,
            "candidate_version": self.candidate_version,
            "active_version": self.active_version,
            "promoted": self.promoted,
            "reason": self.reason,
            "n": self.n,
            "seeds": list(self.seeds),
            "checks": [c.to_dict() for c in self.checks],
            "evidence": dict(self.evidence),
            "record": self.record.to_dict(),
            "members": [m.to_dict() for m in self.members],
        }


# --- the narrow dependencies ------------------------------------------------------------


@runtime_checkable
class GateRegistry(Protocol):
    """What the gate needs of a registry (:class:`LocalRegistry` and the Zenoh client have it)."""

    def get_version(self, name: str, version: int | None = None) -> EcmVersion: ...

    def capability_set(self, revision: int | None = None) -> CapabilitySet: ...

    def record_gate(
        self, name: str, version: int, evidence: Mapping[str, Any], *, reason: str = "", actor: str | None = None
    ) -> EcmVersion: ...

    def promote(
        self,
        name: str,
        version: int,
        *,
        expected_active: int | None = None,
        reason: str = "",
        actor: str | None = None,
    ) -> EcmVersion: ...

    def reject(self, name: str, version: int, *, reason: str = "", actor: str | None = None) -> EcmVersion: ...


# --- the gate ---------------------------------------------------------------------------


def check_gate_seeds(seeds: Sequence[int], *, min_n: int, plan: SeedPlan | None = None) -> list[int]:
    """``seeds`` as a list of distinct non-negative ints, at least ``min_n`` of them.

    Raises:
        Invalid: not a sequence of ints, a repeat (it would count one instance twice), fewer
            than ``min_n``, or (with ``plan``) a seed outside the plan's gate range.
    """
    if isinstance(seeds, (str, bytes)) or not isinstance(seeds, Sequence):
        raise Invalid(f"seeds must be a list of integers, got {type(seeds).__name__}", details={"field": "seeds"})
    out: list[int] = []
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, int) or s < 0:
            raise Invalid(f"seeds must be non-negative integers, got {s!r}", details={"field": "seeds"})
        out.append(int(s))
    if len(set(out)) != len(out):
        dup = sorted({s for s in out if out.count(s) > 1})[:5]
        raise Invalid(f"gate seeds must be distinct; repeated: {dup}", details={"field": "seeds", "repeated": dup})
    if len(out) < min_n:
        raise Invalid(f"the gate needs at least min_n={min_n} seeds, got {len(out)}", details={"field": "seeds"})
    if plan is not None:
        gate = plan.range("gate")
        outside = [s for s in out if s not in gate][:5]
        if outside:
            raise Invalid(
                f"gate seeds must be held out (in {gate.start}..{gate.stop - 1} of seed plan {plan.base_seed}); "
                f"not held out: {outside}",
                details={"field": "seeds", "outside": outside},
            )
    return out


def _ran_versions(outcomes: Sequence[EpisodeOutcome], which: str) -> dict[str, int]:
    maps = {tuple(sorted(o.capability_set.items())) for o in outcomes}
    if len(maps) > 1:
        raise Conflict(
            f"the {which} evaluation ran with more than one capability set: {sorted(maps)[:3]}",
            details={"which": which},
        )
    return dict(next(iter(maps))) if maps else {}


def _compact(outcomes: Sequence[EpisodeOutcome], seeds: Sequence[int]) -> dict[str, list[Any]]:
    by = {o.seed: o for o in outcomes}
    return {
        "success": [int(by[s].success) for s in seeds],
        "reward": [round(_finite(by[s].reward), 6) for s in seeds],
        "steps": [by[s].steps for s in seeds],
        "duration_s": [round(_finite(by[s].duration_s), 4) for s in seeds],
        "unsafe_steps": [by[s].unsafe_steps for s in seeds],
        "interventions": [by[s].interventions for s in seeds],
        "ecm_failures": [by[s].ecm_failures for s in seeds],
    }


def _finite(x: float) -> float:
    # The registry refuses NaN/inf in evidence; a remote evaluator's outcome might carry one.
    return float(x) if math.isfinite(float(x)) else 0.0


def _traces(outcomes: Sequence[EpisodeOutcome]) -> list[str]:
    return sorted({o.trace_path for o in outcomes if o.trace_path})


class Gate:
    """Evaluates a candidate against the active version and promotes or rejects it.

    Args:
        registry: Where versions live; gate evidence, promotion and rejection go here.
        evaluator: Runs seeded episodes (local, or a remote worker over Zenoh).
        config: The decision thresholds.
        actor: Audit actor of the gate's mutations.
        seed_plan: If given, :meth:`run` refuses seeds outside its held-out gate range.
        reuse_evaluations: Remember outcomes per (task, seeds, versions actually run) and
            reuse them when the same versions meet the same seeds again (e.g. one active
            version against several candidates). Sound only for an evaluator where equal
            seeds and versions give equal outcomes (:class:`LocalEvaluator` guarantees it).
        progress: Called as ``progress(stage, message)``.

    Raises:
        Invalid: ``evaluator`` lacks ``evaluate`` or ``config`` is not a :class:`GateConfig`.
    """

    def __init__(
        self,
        registry: GateRegistry,
        evaluator: Evaluator,
        config: GateConfig | None = None,
        *,
        actor: str = "gate",
        seed_plan: SeedPlan | None = None,
        reuse_evaluations: bool = False,
        progress: GateProgress | None = None,
    ) -> None:
        if not isinstance(evaluator, Evaluator):
            raise Invalid(f"evaluator must have evaluate(task, versions, seeds), got {type(evaluator).__name__}")
        if config is not None and not isinstance(config, GateConfig):
            raise Invalid(f"config must be a GateConfig, got {type(config).__name__}", details={"field": "config"})
        self.registry = registry
        self.evaluator = evaluator
        self.config = config if config is not None else GateConfig()
        self.actor = actor
        self.seed_plan = seed_plan
        self.reuse_evaluations = reuse_evaluations
        self.progress = progress
        self._memo: dict[tuple[str, tuple[int, ...]], list[tuple[dict[str, int], list[EpisodeOutcome]]]] = {}

    def _say(self, stage: str, message: str) -> None:
        log.info("gate %s: %s", stage, message)
        if self.progress is not None:
            self.progress(stage, message)

    def _evaluate(self, task: str, pinned: Mapping[str, int], seeds: list[int]) -> list[EpisodeOutcome]:
        """Run ``pinned`` (the rest at their active versions) on ``seeds``.

        Raises:
            Invalid: outcomes for other seeds. Conflict: a pinned ECM ran at another version.
        """
        key = (task, tuple(sorted(seeds)))
        if self.reuse_evaluations:
            wanted = {**self.registry.capability_set().active, **pinned}
            for ran, outcomes in self._memo.get(key, []):
                if all(ran.get(k) == v for k, v in pinned.items()) and all(wanted.get(k) == v for k, v in ran.items()):
                    return outcomes
        outcomes = list(self.evaluator.evaluate(task, dict(pinned), seeds))
        got = [o.seed for o in outcomes]
        if sorted(got) != sorted(seeds):
            raise Invalid(
                f"the evaluator returned outcomes for seeds {got[:5]}..., asked for {seeds[:5]}...",
                details={"field": "outcomes"},
            )
        ran = _ran_versions(outcomes, _versions_text(pinned))
        for name, version in pinned.items():
            if ran.get(name, version) != version:
                raise Conflict(f"asked to evaluate {name} v{version}, the evaluator ran v{ran[name]}")
        if self.reuse_evaluations:
            self._memo.setdefault(key, []).append(({**ran, **pinned}, outcomes))
        return outcomes

    @staticmethod
    def _check_pairing(
        gated: Collection[str], act_out: Sequence[EpisodeOutcome], cand_out: Sequence[EpisodeOutcome]
    ) -> None:
        """Invariant 4: the two sides ran the same versions of every ECM not ``gated``, under one Φ.

        Raises:
            Conflict: they did not (nothing is recorded).
        """
        label = ", ".join(gated)
        ran_active, ran_cand = _ran_versions(act_out, "active"), _ran_versions(cand_out, "candidate")
        others = sorted(
            k for k in set(ran_active) | set(ran_cand) if k not in gated and ran_active.get(k) != ran_cand.get(k)
        )
        if others:
            raise Conflict(
                f"the active and candidate evaluations ran different versions of {', '.join(others)} "
                f"({ran_active} vs {ran_cand}); the pairing is broken, nothing was recorded",
                details={"name": label, "differ": others},
            )
        envelopes = {o.phi_hash for o in (*act_out, *cand_out)}
        if len(envelopes) > 1:
            raise Conflict(
                f"the active and candidate evaluations of {label} ran under different envelopes Φ "
                f"({sorted(str(h)[:12] for h in envelopes)}); the pairing is broken, nothing was recorded",
                details={"name": label},
            )

    def _check_still_none_active(self, name: str) -> None:
        # promote(expected_active=None) checks nothing, and the registry cannot express
        # "expect no active version"; re-reading narrows (does not close) the race window.
        try:
            now = self.registry.get_version(name).version
        except NotFound:
            return
        raise Conflict(
            f"cannot promote {name}: gated as its first version, but v{now} became active meanwhile",
            details={"name": name, "expected_active": None, "active": now},
        )

    def run(
        self,
        name: str,
        candidate_version: int,
        *,
        task: str,
        seeds: Sequence[int],
        extension_seeds: Sequence[int] = (),
        with_candidates: Mapping[str, int] | None = None,
    ) -> GateDecision:
        """Gate ``candidate_version`` of ``name`` on ``task`` with the held-out ``seeds``.

        ``extension_seeds`` are the second look's (``GateConfig.extend_n`` of them, none of
        ``seeds``), used only after a promising first look that rejected; ignored when
        ``extend_n`` is 0.

        ``with_candidates`` are candidates of other ECMs learned together with this one (an
        evolve chain): the candidate side runs all of them, the active side none, and the one
        decision applies to every member. Each member's evidence is recorded (its own name and
        versions, the whole chain under ``chain``) before any of them is promoted or rejected,
        so :meth:`settle` can finish a decision a crash interrupted.

        Returns:
            The decision, with the candidate's record after promotion or rejection (and the
            other members' in ``members``).

        Raises:
            Invalid: bad seeds (see :func:`check_gate_seeds`), ``with_candidates`` naming
                ``name``, or evaluator outcomes that do not match the seeds.
            NotFound: no such ECM or version.
            IllegalTransition: a version is not a candidate.
            Conflict: an active version changed while gating (the evidence stays recorded,
                the candidates not yet promoted stay candidates), or the two evaluations ran
                different versions of the ECMs not gated (nothing recorded).
            CapevoError: whatever the evaluator raised (nothing recorded).
        """
        cfg = self.config
        seed_list = check_gate_seeds(seeds, min_n=cfg.min_n, plan=self.seed_plan)
        more: list[int] = []
        if cfg.extend_n and extension_seeds:
            more = check_gate_seeds(extension_seeds, min_n=cfg.extend_n, plan=self.seed_plan)
            if len(more) != cfg.extend_n or set(more) & set(seed_list):
                raise Invalid(
                    f"a second look needs extend_n={cfg.extend_n} seeds, none of the first look's; "
                    f"got {len(more)}, {len(set(more) & set(seed_list))} shared",
                    details={"field": "extension_seeds"},
                )
        companions = dict(with_candidates or {})
        if name in companions:
            raise Invalid(f"with_candidates names the gated ECM {name} itself", details={"field": "with_candidates"})
        members = {name: int(candidate_version), **{str(k): int(v) for k, v in companions.items()}}
        actives: dict[str, int | None] = {}
        for member, version in members.items():
            record = self.registry.get_version(member, version)
            if record.state is not State.CANDIDATE:
                raise IllegalTransition(
                    f"{member} v{version} is {record.state.value}; only a candidate can be gated",
                    details={"name": member, "version": version, "state": record.state.value},
                )
            try:
                actives[member] = self.registry.get_version(member).version
            except NotFound:
                if member != name:
                    # the active side would have no version of it to run
                    raise Invalid(
                        f"{member} has no active version to compare with; gate it on its own first",
                        details={"field": "with_candidates", "name": member},
                    ) from None
                actives[member] = None
        active_version = actives[name]
        active_pins = {name: active_version} if active_version is not None else {}
        label = _versions_text(members)

        act_out: list[EpisodeOutcome] | None = None
        ran_active: dict[str, int] = {}
        if active_version is not None:
            self._say("evaluate-active", f"{name} v{active_version} on {len(seed_list)} seeds")
            act_out = self._evaluate(task, active_pins, seed_list)
            ran_active = _ran_versions(act_out, "active")
        self._say("evaluate-candidate", f"{label} on {len(seed_list)} seeds")
        cand_out = self._evaluate(task, members, seed_list)
        ran_cand = _ran_versions(cand_out, "candidate")
        if act_out is not None:
            self._check_pairing(members, act_out, cand_out)

        paired: PairedStats | None = None
        looks: list[dict[str, Any]] = []
        if act_out is not None:
            paired = paired_stats(
                act_out, cand_out, alpha=cfg.look_alpha, margin=cfg.delta, speed_metric=cfg.speed_metric
            )
            promote, checks = decide_paired(paired, cfg)
            if more and not promote and promising(paired, checks):
                looks.append(_look(paired, promote, checks))
                self._say("extend", f"first look inconclusive on N={paired.n}: {len(more)} more paired seeds")
                # new lists: a reused evaluation's list is the memo's own
                act_out = act_out + self._evaluate(task, active_pins, more)
                cand_out = cand_out + self._evaluate(task, members, more)
                self._check_pairing(members, act_out, cand_out)
                seed_list = seed_list + more
                paired = paired_stats(
                    act_out, cand_out, alpha=cfg.look_alpha, margin=cfg.delta, speed_metric=cfg.speed_metric
                )
                promote, checks = decide_paired(paired, cfg)
                looks.append(_look(paired, promote, checks))
            cand_stats = paired.candidate
        else:
            cand_stats = side_stats(cand_out, alpha=cfg.alpha, speed_metric=cfg.speed_metric)
            promote, checks = decide_absolute(cand_stats, cfg)
        ordered = sorted(seed_list)
        reason = _summary(name, candidate_version, active_version, promote, checks, cand_stats, paired)
        if companions:
            reason += f"; decided together with {_versions_text(companions)}, as one change"
        if len(looks) == 2:
            reason += f"; second look: N {looks[0]['n']} -> {looks[1]['n']}, each look at alpha {cfg.look_alpha:.3g}"
        self._say("decided", reason)

        evidence: dict[str, Any] = {
            "schema": EVIDENCE_SCHEMA,
            "task": task,
            "name": name,
            "candidate_version": candidate_version,
            "active_version": active_version,
            "mode": "paired" if paired is not None else "absolute",
            "decision": "promote" if promote else "reject",
            "n": len(ordered),
            "seeds": ordered,
            "config": cfg.to_dict(),
            "seed_plan": self.seed_plan.to_dict() if self.seed_plan is not None else None,
            "checks": [c.to_dict() for c in checks],
            "looks": looks,
            "candidate": cand_stats.to_dict(),
            "active": paired.active.to_dict() if paired is not None else None,
            "paired": paired.to_dict() if paired is not None else None,
            "outcomes": {
                "candidate": _compact(cand_out, ordered),
                "active": _compact(act_out, ordered) if act_out is not None else None,
            },
            "capability_set": {"candidate": ran_cand, "active": ran_active or None},
            "phi_hash": next(iter({o.phi_hash for o in cand_out}), None),
            "traces": _traces([*cand_out, *(act_out or [])]),
            "decided_at": time.time(),
        }
        if companions:
            evidence["chain"] = members
            evidence["chain_active"] = actives
        for member, version in members.items():
            self.registry.record_gate(
                member, version, _member_evidence(evidence, member), reason=reason, actor=self.actor
            )
            self._say("recorded", f"gate evidence on {member} v{version}")
        after = self._apply(members, actives, promote=promote, reason=reason)
        return GateDecision(
            name=name,
            task=task,
            candidate_version=candidate_version,
            active_version=active_version,
            promoted=promote,
            reason=reason,
            n=len(ordered),
            seeds=tuple(ordered),
            checks=checks,
            candidate=cand_stats,
            paired=paired,
            evidence=evidence,
            record=after[0],
            members=tuple(after[1:]),
        )

    def settle(self, evidence: Mapping[str, Any]) -> list[EcmVersion]:
        """Finish a chain decision whose evidence was recorded but not all applied (a crash
        between :meth:`run`'s first record and its last promotion): record the evidence on the
        members still without it, then promote or reject every member still a candidate, as the
        evidence decided. Nothing is evaluated again.

        Returns:
            Every member's record, in the chain's order.

        Raises:
            Invalid: ``evidence`` is not a chain's gate evidence.
            Conflict: an active version changed since the decision.
        """
        chain = evidence.get("chain")
        decision = evidence.get("decision")
        if not isinstance(chain, Mapping) or not chain or decision not in ("promote", "reject"):
            raise Invalid(
                "settle needs a chain's gate evidence (with chain and decision)", details={"field": "evidence"}
            )
        members = {str(k): int(v) for k, v in chain.items()}
        actives = {str(k): (None if v is None else int(v)) for k, v in (evidence.get("chain_active") or {}).items()}
        reason = f"gate: {decision} {_versions_text(members)} together, as recorded before an interruption"
        for member, version in members.items():
            record = self.registry.get_version(member, version)
            if record.state is State.CANDIDATE and record.gate_evidence != _member_evidence(evidence, member):
                self.registry.record_gate(
                    member, version, _member_evidence(evidence, member), reason=reason, actor=self.actor
                )
        return self._apply(members, actives, promote=decision == "promote", reason=reason)

    def _apply(
        self, members: Mapping[str, int], actives: Mapping[str, int | None], *, promote: bool, reason: str
    ) -> list[EcmVersion]:
        """Promote (guarded by each member's compared active version) or reject every member
        still a candidate; the records after, in ``members``' order."""
        out = []
        for member, version in members.items():
            record = self.registry.get_version(member, version)
            if record.state is not State.CANDIDATE:
                out.append(record)
                continue
            if promote:
                expected = actives.get(member)
                if expected is None:
                    self._check_still_none_active(member)
                record = self.registry.promote(
                    member, version, expected_active=expected, reason=reason, actor=self.actor
                )
                self._say("promoted", f"{member} v{version}")
            else:
                record = self.registry.reject(member, version, reason=reason, actor=self.actor)
                self._say("rejected", f"{member} v{version}")
            out.append(record)
        return out


def _member_evidence(evidence: Mapping[str, Any], member: str) -> dict[str, Any]:
    """``evidence`` as recorded on one member of a chain: its own name and versions."""
    if member == evidence["name"]:
        return dict(evidence)
    return {
        **evidence,
        "name": member,
        "candidate_version": int(evidence["chain"][member]),
        "active_version": (evidence.get("chain_active") or {}).get(member),
    }


def _versions_text(versions: Mapping[str, int]) -> str:
    return ", ".join(f"{k} v{v}" for k, v in versions.items())


def _look(stats: PairedStats, promote: bool, checks: Sequence[Check]) -> dict[str, Any]:
    """One look of a two-look gate, for the evidence."""
    return {
        "n": stats.n,
        "decision": "promote" if promote else "reject",
        "candidate_only": stats.candidate_only,
        "active_only": stats.active_only,
        "checks": [c.to_dict() for c in checks],
    }


def _summary(
    name: str,
    version: int,
    active: int | None,
    promote: bool,
    checks: Sequence[Check],
    cand: SideStats,
    paired: PairedStats | None,
) -> str:
    verdict = "promote" if promote else "reject"
    head = f"gate: {verdict} {name} v{version}"
    if paired is None:
        body = f"first version: success {cand.successes}/{cand.n} {cand.success}"
    else:
        act = paired.active
        body = (
            f"vs v{active} on N={paired.n}: success {cand.successes}/{cand.n} {cand.success} vs "
            f"{act.successes}/{act.n} {act.success}; diff {paired.success_difference}; "
            f"McNemar p={_p(paired.p_success)}, non-inferiority(δ) p={_p(paired.p_noninferiority)}; "
            f"reward {cand.mean_reward:.2f} vs {act.mean_reward:.2f} Wilcoxon p={_p(paired.p_reward)}; "
            + (
                f"speed x{paired.speed_ratio:.2f} on {paired.speed_pairs} common successes"
                if paired.speed_ratio is not None
                else "speed not comparable"
            )
            + f"; unsafe episodes {cand.unsafe_episodes} vs {act.unsafe_episodes}"
        )
    marks = " ".join(f"{c.name}={'ok' if c.passed else 'FAIL'}" for c in checks)
    return f"{head} ({body}; checks: {marks})"


__all__ = [
    "EVIDENCE_SCHEMA",
    "PURPOSES",
    "Check",
    "Gate",
    "GateConfig",
    "GateDecision",
    "GateProgress",
    "GateRegistry",
    "SeedPlan",
    "check_gate_seeds",
    "decide_absolute",
    "decide_paired",
    "promising",
]
