"""The gate's statistics on hand-made outcome lists, checked against scipy and published values.

Invariants of :mod:`capevo.runtime.gate_stats`: pairing by seed only (1), seed-order
invariance (2), identical lists give p = 1 (3), interval bounds (4), finite evidence (5).
"""

from __future__ import annotations

import json
import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import optimize
from scipy import stats as sps

from capevo.errors import ErrorCode, Invalid
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.gate_stats import (
    check_alpha,
    mcnemar_exact_p,
    noninferiority_p,
    pair_outcomes,
    paired_difference_interval,
    paired_stats,
    side_stats,
    wilcoxon_greater_p,
    wilson_interval,
)


def oc(seed: int, success: bool, reward: float = 0.0, steps: int = 50) -> EpisodeOutcome:
    return EpisodeOutcome(
        seed=seed,
        success=success,
        reward=reward,
        steps=steps,
        duration_s=steps * 0.02,
        interventions=0,
        unsafe_steps=0,
        ecm_failures=0,
        capability_set={"pick.reach": 1},
    )


outcome_rows = st.lists(
    st.tuples(st.booleans(), st.floats(-5, 20, allow_nan=False), st.integers(1, 200)), min_size=1, max_size=25
)


def lists_from(rows_a: list, rows_c: list) -> tuple[list[EpisodeOutcome], list[EpisodeOutcome]]:
    n = min(len(rows_a), len(rows_c))
    active = [oc(100 + i, *rows_a[i]) for i in range(n)]
    cand = [oc(100 + i, *rows_c[i]) for i in range(n)]
    return active, cand


# --- single tests against scipy -----------------------------------------------------------


@pytest.mark.parametrize(("k", "n", "alpha"), [(0, 8, 0.05), (8, 8, 0.05), (3, 10, 0.05), (17, 40, 0.01), (1, 1, 0.1)])
def test_wilson_interval_is_scipys_at_level_one_minus_two_alpha(k: int, n: int, alpha: float) -> None:
    ci = sps.binomtest(k, n).proportion_ci(confidence_level=1 - 2 * alpha, method="wilson")
    got = wilson_interval(k, n, alpha=alpha)
    assert got.estimate == k / n
    assert got.low == pytest.approx(max(0.0, ci.low), abs=1e-12)
    assert got.high == pytest.approx(min(1.0, ci.high), abs=1e-12)
    assert got.level == pytest.approx(1 - 2 * alpha)


def test_wilson_interval_known_value() -> None:
    # 8/8 at one-sided 95%: n / (n + z^2) with z = 1.6449.
    z = sps.norm.isf(0.05)
    assert wilson_interval(8, 8, alpha=0.05).low == pytest.approx(8 / (8 + z * z), abs=1e-9)


@pytest.mark.parametrize(("b", "c"), [(8, 0), (5, 1), (3, 3), (0, 4), (12, 2)])
def test_mcnemar_is_the_exact_one_sided_sign_test_on_discordant_pairs(b: int, c: int) -> None:
    expected = sps.binomtest(b, b + c, 0.5, alternative="greater").pvalue
    assert mcnemar_exact_p(b, c) == pytest.approx(expected, rel=1e-12)


def test_mcnemar_known_values() -> None:
    assert mcnemar_exact_p(8, 0) == pytest.approx(0.5**8)
    assert mcnemar_exact_p(0, 0) == 1.0
    assert mcnemar_exact_p(4, 0) == pytest.approx(0.0625)  # 4 discordant pairs can never reach 0.05


def test_wilcoxon_is_scipys_one_sided_signed_rank_with_ties_dropped() -> None:
    diffs = [1.5, -0.2, 3.0, 0.0, 2.2, 0.7, -1.1, 4.0]
    expected = sps.wilcoxon([d for d in diffs if d != 0.0], alternative="greater").pvalue
    assert wilcoxon_greater_p(diffs) == pytest.approx(expected, rel=1e-12)
    # All eight positive: the exact null puts 1/2^8 on the largest rank sum.
    assert wilcoxon_greater_p([1, 2, 3, 4, 5, 6, 7, 8]) == pytest.approx(1 / 256)
    assert wilcoxon_greater_p([0.0, 1e-12, -1e-12]) == 1.0


def test_tango_interval_matches_the_published_bentur_example() -> None:
    # Fagerland, Lydersen & Laake (2014), airway hyper-responsiveness (Bentur et al. 2009):
    # n12 = 1, n21 = 7, N = 21, Tango asymptotic score 95% CI -0.5172 to -0.0260.
    got = paired_difference_interval(1, 7, 21, alpha=0.025)
    assert got.estimate == pytest.approx(-6 / 21)
    assert got.low == pytest.approx(-0.5172, abs=2e-4)
    assert got.high == pytest.approx(-0.0260, abs=2e-4)


def _score_statistic_by_numeric_mle(b: int, c: int, n: int, delta: float) -> float:
    """Tango's statistic with the restricted MLE found numerically (independent of the closed form)."""

    def nll(p21: float) -> float:
        p12 = p21 + delta
        rest = 1.0 - p12 - p21
        return -(b * math.log(p12) + c * math.log(p21) + (n - b - c) * math.log(rest))

    lo = max(0.0, -delta) + 1e-12
    hi = (1.0 - delta) / 2.0 - 1e-12
    p21 = optimize.minimize_scalar(nll, bounds=(lo, hi), method="bounded", options={"xatol": 1e-12}).x
    return (b - c - n * delta) / math.sqrt(n * (2 * p21 + delta * (1 - delta)))


@pytest.mark.parametrize(("b", "c", "n"), [(1, 7, 21), (6, 16, 161), (0, 1, 10), (3, 0, 10), (2, 2, 9)])
def test_tango_bounds_are_where_the_score_statistic_hits_z(b: int, c: int, n: int) -> None:
    alpha = 0.05
    z = sps.norm.isf(alpha)
    got = paired_difference_interval(b, c, n, alpha=alpha)
    if got.low > -1:
        assert _score_statistic_by_numeric_mle(b, c, n, got.low) == pytest.approx(z, abs=1e-3)
    if got.high < 1:
        assert _score_statistic_by_numeric_mle(b, c, n, got.high) == pytest.approx(-z, abs=1e-3)


def test_no_discordant_pair_does_not_collapse_the_interval() -> None:
    # Unlike Wald/Newcombe, 0 discordant pairs of 8 still leave about +-0.25 (z^2 / (n + z^2)).
    z2 = sps.norm.isf(0.05) ** 2
    for both in (0, 4, 8):
        got = paired_difference_interval(0, 0, 8, alpha=0.05)
        assert got.low == pytest.approx(-z2 / (8 + z2), abs=1e-6), both
        assert got.high == pytest.approx(z2 / (8 + z2), abs=1e-6)


def test_noninferiority_p_is_the_normal_tail_of_tangos_statistic() -> None:
    for b, c, n, margin in [(0, 1, 10, 0.3), (1, 7, 21, 0.1), (0, 0, 8, 0.3), (4, 0, 8, 0.05)]:
        expected = sps.norm.sf(_score_statistic_by_numeric_mle(b, c, n, -margin))
        assert noninferiority_p(b, c, n, margin=margin) == pytest.approx(expected, abs=1e-4)


@given(
    st.integers(1, 60).flatmap(
        lambda n: st.tuples(st.just(n), st.integers(0, n)).flatmap(
            lambda t: st.tuples(st.just(t[0]), st.just(t[1]), st.integers(0, t[0] - t[1]))
        )
    ),
    st.floats(0.0, 0.9),
    st.sampled_from([0.01, 0.05, 0.1]),
)
@settings(max_examples=150, deadline=None)
def test_noninferiority_agrees_with_the_interval(nbc: tuple[int, int, int], margin: float, alpha: float) -> None:
    n, b, c = nbc
    p = noninferiority_p(b, c, n, margin=margin)
    ci = paired_difference_interval(b, c, n, alpha=alpha)
    assert -1.0 <= ci.low <= ci.estimate <= ci.high <= 1.0
    # Away from the boundary (root-finding tolerance), the test and the interval agree.
    if abs(ci.low + margin) > 1e-6:
        assert (p < alpha) == (ci.low > -margin)


# --- pairing ------------------------------------------------------------------------------


def test_pairing_refuses_different_seeds() -> None:
    with pytest.raises(Invalid) as e:
        pair_outcomes([oc(1, True), oc(2, True)], [oc(1, True), oc(3, True)])
    assert e.value.code is ErrorCode.INVALID
    assert "same seeds" in e.value.message and "[2]" in e.value.message and "[3]" in e.value.message


def test_pairing_refuses_repeated_seeds() -> None:
    with pytest.raises(Invalid, match="candidate outcomes repeat seed 1"):
        pair_outcomes([oc(1, True), oc(2, True)], [oc(1, True), oc(1, False)])


def test_paired_stats_on_a_hand_made_table() -> None:
    # seeds 0-3 both succeed (candidate faster), 4-7 only the candidate, 8 only the active, 9 neither.
    active = [oc(s, s < 4 or s == 8, 1.0, 60) for s in range(10)]
    cand = [oc(s, s < 8, 2.0, 45) for s in range(10)]
    got = paired_stats(active, cand, alpha=0.05, margin=0.1)
    assert (got.both, got.candidate_only, got.active_only, got.neither) == (4, 4, 1, 1)
    assert got.p_success == pytest.approx(sps.binomtest(4, 5, 0.5, alternative="greater").pvalue)
    assert got.p_reward == pytest.approx(sps.wilcoxon([1.0] * 10, alternative="greater").pvalue)
    assert got.speed_pairs == 4 and got.speed_ratio == pytest.approx(45 / 60)
    assert got.candidate.successes == 8 and got.active.successes == 5
    assert got.success_difference.estimate == pytest.approx(0.3)
    assert got.seeds == tuple(range(10))


def test_speed_uses_only_seeds_where_both_succeeded() -> None:
    active = [oc(0, True, steps=40), oc(1, True, steps=40), oc(2, False, steps=80)]
    cand = [oc(0, True, steps=60), oc(1, False, steps=80), oc(2, True, steps=10)]
    got = paired_stats(active, cand, alpha=0.05, speed_metric="steps")
    assert got.speed_pairs == 1 and got.speed_ratio == pytest.approx(1.5)
    by_time = paired_stats(active, cand, alpha=0.05, speed_metric="duration_s")
    assert by_time.speed_ratio == pytest.approx(1.5)


def test_bad_alpha_and_metric_are_invalid() -> None:
    for bad in (0, 0.5, -0.1, True, "0.05"):
        with pytest.raises(Invalid, match="alpha must be a number in"):
            check_alpha(bad)  # type: ignore[arg-type]
    with pytest.raises(Invalid, match="unknown speed metric 'wall'; valid: steps, duration_s"):
        side_stats([oc(0, True)], alpha=0.05, speed_metric="wall")


# --- properties ---------------------------------------------------------------------------


@given(outcome_rows, outcome_rows, st.randoms(use_true_random=False))
@settings(max_examples=80, deadline=None)
def test_statistics_do_not_depend_on_seed_order(rows_a: list, rows_c: list, rnd: random.Random) -> None:
    active, cand = lists_from(rows_a, rows_c)
    ref = paired_stats(active, cand, alpha=0.05, margin=0.1)
    rnd.shuffle(active)
    rnd.shuffle(cand)
    assert paired_stats(active, cand, alpha=0.05, margin=0.1) == ref


@given(outcome_rows)
@settings(max_examples=80, deadline=None)
def test_identical_outcomes_give_no_evidence_of_improvement(rows: list) -> None:
    active, _ = lists_from(rows, rows)
    got = paired_stats(active, list(active), alpha=0.05, margin=0.1)
    assert got.p_success == 1.0 and got.p_reward == 1.0
    assert got.candidate_only == got.active_only == 0
    assert got.success_difference.estimate == 0.0
    assert got.speed_ratio in (None, 1.0)


@given(outcome_rows, outcome_rows)
@settings(max_examples=80, deadline=None)
def test_intervals_are_ordered_and_evidence_is_finite_json(rows_a: list, rows_c: list) -> None:
    active, cand = lists_from(rows_a, rows_c)
    got = paired_stats(active, cand, alpha=0.05, margin=0.2)
    for side in (got.active, got.candidate):
        assert 0.0 <= side.success.low <= side.success.estimate <= side.success.high <= 1.0
    d = got.success_difference
    assert -1.0 <= d.low <= d.estimate <= d.high <= 1.0
    assert 0.0 <= got.p_success <= 1.0 and 0.0 <= got.p_reward <= 1.0 and 0.0 <= got.p_noninferiority <= 1.0
    json.dumps(got.to_dict(), allow_nan=False)
