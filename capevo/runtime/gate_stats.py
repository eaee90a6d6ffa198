"""The statistics of the version gate: paired episode outcomes in, tests and intervals out.

Every number the gate decides on comes from here, computed with :mod:`scipy.stats`:

* success rates with Wilson score intervals (``binomtest(k, n).proportion_ci(method="wilson")``);
* the paired success comparison with the exact one-sided McNemar test, i.e. a sign test on the
  discordant pairs (``binomtest(b, b + c, 0.5, alternative="greater")``);
* non-inferiority of the success rate within a margin with Tango's asymptotic score test
  for paired proportions (Tango 1998; ``scipy.stats.norm`` tail, restricted MLE in closed
  form) and the score interval that inverts it (``scipy.optimize.brentq``);
* the paired reward comparison with the one-sided Wilcoxon signed-rank test
  (``wilcoxon(d, alternative="greater")``). Why not the paired t-test: an episode's total
  reward is bounded, bimodal (a success ends the episode early with a bonus step, a failure
  accumulates shaped reward to the horizon) and the gate runs few episodes (8-50), so the
  t-test's normality is not credible; the signed-rank test needs no normality, is exact for
  small samples without ties, and loses at most ~5% efficiency when the data are normal.
* speed as the ratio of mean steps (or seconds) over the seeds where *both* versions
  succeeded, so harder instances cannot make either side look slow;
* safety as the same exact sign test on the seeds where exactly one version had an unsafe
  episode (some executed step broke Φ), asking whether the candidate is unsafe more often.

Confidence convention: every interval is two-sided at level ``1 - 2*alpha``, so each end is
a one-sided ``1 - alpha`` bound, matching the one-sided tests at ``alpha``.

Invariants:
1. :func:`pair_outcomes` pairs by seed and refuses lists whose seeds differ, repeat, or
   whose lengths differ: a paired statistic never mixes instances.
2. Every statistic is invariant to the order of the seeds.
3. Identical outcome lists give McNemar p = 1 and Wilcoxon p = 1 (no discordant pair, no
   non-zero reward difference).
4. Every interval satisfies ``0 <= low <= estimate <= high <= 1`` for rates and
   ``-1 <= low <= estimate <= high <= 1`` for the difference.
5. All numbers in :meth:`GateStats.to_dict` are finite or None (the registry refuses NaN/inf).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import optimize
from scipy import stats as sps

from capevo.errors import Invalid, check_choice
from capevo.runtime.evaluation import EpisodeOutcome

REWARD_TOLERANCE = 1e-9
"""Reward differences this small count as ties (zero), not as evidence either way."""
SPEED_METRICS: tuple[str, ...] = ("steps", "duration_s")


@dataclass(frozen=True, slots=True, kw_only=True)
class Interval:
    """A point estimate with its two-sided ``level`` interval."""

    estimate: float
    low: float
    high: float
    level: float

    def to_dict(self) -> dict[str, float]:
        return {"estimate": self.estimate, "low": self.low, "high": self.high, "level": self.level}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Interval:
        return cls(estimate=float(d["estimate"]), low=float(d["low"]), high=float(d["high"]), level=float(d["level"]))

    def __str__(self) -> str:
        return f"{self.estimate:.2f} [{self.low:.2f}, {self.high:.2f}]"


@dataclass(frozen=True, slots=True, kw_only=True)
class Pair:
    """The two outcomes of one seed."""

    seed: int
    active: EpisodeOutcome
    candidate: EpisodeOutcome


def check_alpha(alpha: float) -> float:
    """``alpha`` if it is a number in (0, 0.5).

    Raises:
        Invalid: otherwise (at 0.5 or above the ``1 - 2*alpha`` intervals are empty).
    """
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0.0 < float(alpha) < 0.5:
        raise Invalid(f"alpha must be a number in (0, 0.5), got {alpha!r}", details={"field": "alpha"})
    return float(alpha)


def _by_seed(outcomes: Sequence[EpisodeOutcome], which: str) -> dict[int, EpisodeOutcome]:
    out: dict[int, EpisodeOutcome] = {}
    for o in outcomes:
        if not isinstance(o, EpisodeOutcome):
            raise Invalid(f"{which} outcomes must be EpisodeOutcome, got {type(o).__name__}", details={"field": which})
        if o.seed in out:
            raise Invalid(f"{which} outcomes repeat seed {o.seed}", details={"field": which, "seed": o.seed})
        out[o.seed] = o
    return out


def pair_outcomes(active: Sequence[EpisodeOutcome], candidate: Sequence[EpisodeOutcome]) -> list[Pair]:
    """Pair two outcome lists by seed, sorted by seed.

    Raises:
        Invalid: a list repeats a seed, or the two lists do not cover the same seeds.
    """
    a = _by_seed(active, "active")
    c = _by_seed(candidate, "candidate")
    if set(a) != set(c):
        only_a = sorted(set(a) - set(c))[:5]
        only_c = sorted(set(c) - set(a))[:5]
        raise Invalid(
            f"paired outcomes need the same seeds: only active has {only_a}, only candidate has {only_c}",
            details={"field": "seeds", "only_active": only_a, "only_candidate": only_c},
        )
    return [Pair(seed=s, active=a[s], candidate=c[s]) for s in sorted(a)]


def wilson_interval(successes: int, n: int, *, alpha: float) -> Interval:
    """Success rate ``successes / n`` with its Wilson score interval at level ``1 - 2*alpha``.

    Raises:
        Invalid: ``n < 1`` or ``successes`` outside ``[0, n]``.
    """
    if n < 1 or not 0 <= successes <= n:
        raise Invalid(f"need 0 <= successes <= n and n >= 1, got {successes}/{n}", details={"field": "n"})
    level = 1.0 - 2.0 * check_alpha(alpha)
    ci = sps.binomtest(int(successes), int(n)).proportion_ci(confidence_level=level, method="wilson")
    p = successes / n
    # scipy's Wilson ends can miss the estimate by a rounding error at 0 and 1.
    return Interval(estimate=p, low=min(max(float(ci.low), 0.0), p), high=max(min(float(ci.high), 1.0), p), level=level)


def mcnemar_exact_p(candidate_only: int, active_only: int) -> float:
    """One-sided exact McNemar p-value that the candidate succeeds more often than the active.

    (Any paired binary event works: the gate also feeds it unsafe episodes.)

    Conditional on the ``b + c`` discordant pairs, ``b`` (candidate-only successes) is
    Binomial(b + c, 1/2) under the null of equal rates; p = P(X >= b). No discordant pair
    gives p = 1.
    """
    m = candidate_only + active_only
    if m == 0:
        return 1.0
    return float(sps.binomtest(candidate_only, m, 0.5, alternative="greater").pvalue)


def _tango_statistic(candidate_only: int, active_only: int, n: int, delta: float) -> float:
    """Tango's score statistic for H0: p_candidate - p_active = ``delta`` (large: difference above)."""
    b, c = candidate_only, active_only
    if abs(delta) < 1e-12:
        # Squares of such deltas underflow and would make the variance vanish.
        delta = 0.0
    # Restricted MLE of P(active only) under H0, Tango (1998) closed form.
    qa = 2.0 * n
    qb = -b - c + (2.0 * n - b + c) * delta
    qc = -c * delta * (1.0 - delta)
    p21 = (math.sqrt(max(0.0, qb * qb - 4.0 * qa * qc)) - qb) / (2.0 * qa)
    numerator = b - c - n * delta
    variance = n * (2.0 * p21 + delta * (1.0 - delta))
    if variance <= 0.0:
        # Only reached with no discordant pair at delta = 0: no evidence either way.
        return 0.0 if numerator == 0 else math.copysign(math.inf, numerator)
    return numerator / math.sqrt(variance)


def paired_difference_interval(candidate_only: int, active_only: int, n: int, *, alpha: float) -> Interval:
    """Candidate minus active success rate with Tango's score interval for paired data.

    The interval inverts Tango's (1998) asymptotic score test (the one
    :func:`noninferiority_p` uses), so its lower end is above ``-delta`` exactly when that
    test shows non-inferiority at ``alpha``. Unlike Wald or Newcombe intervals it does not
    collapse to a point when no pair is discordant: 0 discordant pairs out of 8 still give
    about [-0.25, 0.25] at alpha = 0.05.

    Args:
        candidate_only: Seeds only the candidate succeeded on (b).
        active_only: Seeds only the active version succeeded on (c).
        n: Paired seeds in all.
        alpha: Each end is a one-sided ``1 - alpha`` bound.

    Raises:
        Invalid: negative counts or ``b + c > n`` or ``n < 1``.
    """
    b, c = candidate_only, active_only
    if n < 1 or min(b, c) < 0 or b + c > n:
        raise Invalid(f"bad paired counts b={b} c={c} n={n}", details={"field": "table"})
    z = float(sps.norm.isf(check_alpha(alpha)))
    est = (b - c) / n
    eps = 1e-9

    def bound(sign: float, lo: float, hi: float, edge: float) -> float:
        f = lambda d: _tango_statistic(b, c, n, d) - sign * z  # noqa: E731
        if f(lo) * f(hi) > 0:
            return edge
        return float(optimize.brentq(f, lo, hi, xtol=1e-10))

    low = -1.0 if est <= -1.0 else bound(1.0, -1.0 + eps, est, -1.0)
    high = 1.0 if est >= 1.0 else bound(-1.0, est, 1.0 - eps, 1.0)
    return Interval(estimate=est, low=min(max(-1.0, low), est), high=max(min(1.0, high), est), level=1.0 - 2.0 * alpha)


def noninferiority_p(candidate_only: int, active_only: int, n: int, *, margin: float) -> float:
    """One-sided p-value against H0: p_candidate - p_active <= -``margin`` (Tango's score test).

    Small p means the candidate's success rate is, with confidence, no more than ``margin``
    below the active version's.

    Raises:
        Invalid: bad counts, or ``margin`` outside [0, 1).
    """
    b, c = candidate_only, active_only
    if n < 1 or min(b, c) < 0 or b + c > n:
        raise Invalid(f"bad paired counts b={b} c={c} n={n}", details={"field": "table"})
    if not 0.0 <= margin < 1.0:
        raise Invalid(f"margin must be in [0, 1), got {margin!r}", details={"field": "delta"})
    return float(sps.norm.sf(_tango_statistic(b, c, n, -float(margin))))


def wilcoxon_greater_p(differences: Sequence[float], *, tolerance: float = REWARD_TOLERANCE) -> float:
    """One-sided Wilcoxon signed-rank p-value that the paired differences are centred above 0.

    Differences within ``tolerance`` of zero are ties and are dropped (Wilcoxon's
    convention); none left gives p = 1.
    """
    d = np.asarray([x for x in differences if abs(x) > tolerance], dtype=np.float64)
    if d.size == 0:
        return 1.0
    return float(sps.wilcoxon(d, alternative="greater", zero_method="wilcox", method="auto").pvalue)


@dataclass(frozen=True, slots=True, kw_only=True)
class SideStats:
    """One version's outcomes on the gate seeds."""

    n: int
    successes: int
    success: Interval
    mean_reward: float
    mean_speed_success: float | None
    """Mean speed metric over this side's successful episodes; None without successes."""
    interventions: int
    unsafe_steps: int
    unsafe_episodes: int
    """Episodes with at least one unsafe step."""
    unsafe: Interval
    """Unsafe-episode rate with its Wilson interval."""
    ecm_failures: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "successes": self.successes,
            "success_rate": self.success.estimate,
            "success_interval": self.success.to_dict(),
            "mean_reward": self.mean_reward,
            "mean_speed_success": self.mean_speed_success,
            "interventions": self.interventions,
            "unsafe_steps": self.unsafe_steps,
            "unsafe_episodes": self.unsafe_episodes,
            "unsafe_interval": self.unsafe.to_dict(),
            "ecm_failures": self.ecm_failures,
        }


def side_stats(outcomes: Sequence[EpisodeOutcome], *, alpha: float, speed_metric: str = "steps") -> SideStats:
    """Success interval, mean reward and mean speed of one version's outcomes.

    Raises:
        Invalid: no outcomes, or an unknown ``speed_metric``.
    """
    metric = check_speed_metric(speed_metric)
    if not outcomes:
        raise Invalid("no outcomes to summarise", details={"field": "outcomes"})
    ordered = sorted(outcomes, key=lambda o: o.seed)
    k = sum(1 for o in ordered if o.success)
    unsafe = sum(1 for o in ordered if o.unsafe_steps > 0)
    speeds = [float(getattr(o, metric)) for o in ordered if o.success]
    return SideStats(
        n=len(ordered),
        successes=k,
        success=wilson_interval(k, len(ordered), alpha=alpha),
        mean_reward=_finite_mean([o.reward for o in ordered]),
        mean_speed_success=_finite_mean(speeds) if speeds else None,
        interventions=sum(o.interventions for o in ordered),
        unsafe_steps=sum(o.unsafe_steps for o in ordered),
        unsafe_episodes=unsafe,
        unsafe=wilson_interval(unsafe, len(ordered), alpha=alpha),
        ecm_failures=sum(o.ecm_failures for o in ordered),
    )


def check_speed_metric(metric: str) -> str:
    """``metric`` if it is one of :data:`SPEED_METRICS`.

    Raises:
        Invalid: naming the valid metrics.
    """
    return check_choice(metric, SPEED_METRICS, what="speed metric", field="speed_metric")


def _finite_mean(xs: Sequence[float]) -> float:
    finite = [float(x) for x in xs if math.isfinite(float(x))]
    # math.fsum: the mean must not depend on the order the seeds came in.
    return math.fsum(finite) / len(finite) if finite else 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class PairedStats:
    """Everything the gate compares between the active and the candidate version."""

    n: int
    seeds: tuple[int, ...]
    active: SideStats
    candidate: SideStats
    both: int
    candidate_only: int
    active_only: int
    neither: int
    success_difference: Interval
    p_success: float
    """One-sided exact McNemar: candidate succeeds more often."""
    p_noninferiority: float
    """One-sided Tango score test: candidate's success rate is above active's minus ``margin``."""
    margin: float
    p_reward: float
    """One-sided Wilcoxon signed-rank on candidate minus active reward."""
    reward_difference_median: float
    speed_metric: str
    speed_pairs: int
    """Seeds where both versions succeeded (the speed comparison's sample)."""
    speed_ratio: float | None
    """Candidate over active mean speed metric on those seeds; None without such seeds."""
    unsafe_candidate_only: int
    """Seeds where only the candidate had an unsafe episode."""
    unsafe_active_only: int
    """Seeds where only the active version had an unsafe episode."""
    p_less_safe: float
    """One-sided exact sign test: the candidate is unsafe more often than the active version."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "active": self.active.to_dict(),
            "candidate": self.candidate.to_dict(),
            "table": {
                "both": self.both,
                "candidate_only": self.candidate_only,
                "active_only": self.active_only,
                "neither": self.neither,
            },
            "success_difference": self.success_difference.to_dict(),
            "p_success": self.p_success,
            "p_noninferiority": self.p_noninferiority,
            "margin": self.margin,
            "p_reward": self.p_reward,
            "reward_difference_median": self.reward_difference_median,
            "speed": {"metric": self.speed_metric, "pairs": self.speed_pairs, "ratio": self.speed_ratio},
            "safety": {
                "candidate_only_unsafe": self.unsafe_candidate_only,
                "active_only_unsafe": self.unsafe_active_only,
                "p_less_safe": self.p_less_safe,
            },
        }


def paired_stats(
    active: Sequence[EpisodeOutcome],
    candidate: Sequence[EpisodeOutcome],
    *,
    alpha: float,
    margin: float = 0.0,
    speed_metric: str = "steps",
    reward_tolerance: float = REWARD_TOLERANCE,
) -> PairedStats:
    """All paired statistics of two versions run on the same seeds.

    Args:
        active, candidate: One outcome per seed each, same seeds (any order).
        alpha: Level of the one-sided tests; intervals are two-sided ``1 - 2*alpha``.
        margin: Non-inferiority margin on the success rate.
        speed_metric: ``steps`` or ``duration_s``.
        reward_tolerance: Reward differences at most this large are ties.

    Raises:
        Invalid: the lists cannot be paired (see :func:`pair_outcomes`), are empty, or a bad
            ``alpha`` / ``speed_metric``.
    """
    check_alpha(alpha)
    metric = check_speed_metric(speed_metric)
    pairs = pair_outcomes(active, candidate)
    if not pairs:
        raise Invalid("no paired outcomes", details={"field": "outcomes"})
    a = sum(1 for p in pairs if p.active.success and p.candidate.success)
    b = sum(1 for p in pairs if p.candidate.success and not p.active.success)
    c = sum(1 for p in pairs if p.active.success and not p.candidate.success)
    d = len(pairs) - a - b - c
    unsafe_b = sum(1 for p in pairs if p.candidate.unsafe_steps > 0 and p.active.unsafe_steps == 0)
    unsafe_c = sum(1 for p in pairs if p.active.unsafe_steps > 0 and p.candidate.unsafe_steps == 0)
    diffs = [_finite(p.candidate.reward) - _finite(p.active.reward) for p in pairs]
    both = [p for p in pairs if p.active.success and p.candidate.success]
    ratio: float | None = None
    if both:
        act_speed = _finite_mean([float(getattr(p.active, metric)) for p in both])
        cand_speed = _finite_mean([float(getattr(p.candidate, metric)) for p in both])
        ratio = cand_speed / act_speed if act_speed > 0 else None
    return PairedStats(
        n=len(pairs),
        seeds=tuple(p.seed for p in pairs),
        active=side_stats([p.active for p in pairs], alpha=alpha, speed_metric=metric),
        candidate=side_stats([p.candidate for p in pairs], alpha=alpha, speed_metric=metric),
        both=a,
        candidate_only=b,
        active_only=c,
        neither=d,
        success_difference=paired_difference_interval(b, c, len(pairs), alpha=alpha),
        p_success=mcnemar_exact_p(b, c),
        p_noninferiority=noninferiority_p(b, c, len(pairs), margin=margin),
        margin=margin,
        p_reward=wilcoxon_greater_p(diffs, tolerance=reward_tolerance),
        reward_difference_median=float(np.median(diffs)),
        speed_metric=metric,
        speed_pairs=len(both),
        speed_ratio=ratio,
        unsafe_candidate_only=unsafe_b,
        unsafe_active_only=unsafe_c,
        # The same exact sign test as McNemar's, with "unsafe" in the role of "success".
        p_less_safe=mcnemar_exact_p(unsafe_b, unsafe_c),
    )


def _finite(x: float) -> float:
    return float(x) if math.isfinite(float(x)) else 0.0
