"""spot.results.stats against hand-computed values and an independent stratified bootstrap."""

import warnings

import numpy as np
import pytest
from scipy import stats as scipy_stats

from spot.results import stats


def test_probability_of_improvement_by_hand():
    # task 1: x = 1, 2, 3 vs y = 2, 2: pairs (1,2)x2 -> 0, (2,2)x2 -> 1/2 each, (3,2)x2 -> 1 each
    #   = 3 / 6 = 0.5;  task 2: 5 vs 1 -> 1.  Mean over tasks: 0.75.
    got = stats.probability_of_improvement(np.array([1.0, 2, 3]), np.array([5.0]), np.array([2.0, 2]), np.array([1.0]))
    assert got == 0.75


def test_iqm_pools_runs_and_trims_a_quarter_each_side():
    # pooled 1..8: drop 1, 2 and 7, 8 -> mean(3, 4, 5, 6) = 4.5
    assert stats.iqm(np.array([1.0, 8, 3, 6]), np.array([2.0, 7, 4, 5])) == 4.5


def test_mean_difference_weighs_tasks_equally():
    # task 1: 2 - 1 = 1; task 2: mean(10, 20, 30) - 0 = 20 -> (1 + 20) / 2
    got = stats.mean_difference(np.array([2.0, 2]), np.array([10.0, 20, 30]), np.array([1.0]), np.array([0.0]))
    assert got == 10.5


def _independent_stratified_bootstrap(strata, fn, n=20000, seed=123):
    """Resample each stratum with replacement on its own; percentile interval of fn."""
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(n):
        values.append(fn([rng.choice(s, size=len(s), replace=True) for s in strata]))
    return np.percentile(values, [2.5, 97.5])


def test_bootstrap_ci_matches_an_independent_stratified_bootstrap():
    rng = np.random.default_rng(0)
    strata = [rng.normal(10, 3, size=5), rng.normal(50, 10, size=3), rng.normal(0, 1, size=4)]
    low, high = stats.bootstrap_ci(strata, stats.mean_of_means, n_resamples=20000)
    want = _independent_stratified_bootstrap(strata, lambda ss: np.mean([s.mean() for s in ss]))
    width = want[1] - want[0]
    assert abs(low - want[0]) < 0.05 * width and abs(high - want[1]) < 0.05 * width
    # the stratified interval is narrower than pooling all runs and resampling them together
    point = stats.mean_of_means(*strata)
    assert low < point < high


def test_difference_ci_matches_an_independent_computation():
    x = [np.array([5.0, 6, 7]), np.array([1.0, 3, 2])]
    y = [np.array([4.0, 4.5, 5]), np.array([1.0, 1.5, 2])]  # means 4.5, 1.5
    est = stats.estimate([*x, *y], stats.mean_difference)
    assert est.value == np.mean([6 - 4.5, 2 - 1.5])
    want = _independent_stratified_bootstrap(
        [*x, *y], lambda ss: np.mean([ss[0].mean() - ss[2].mean(), ss[1].mean() - ss[3].mean()])
    )
    width = want[1] - want[0]
    assert abs(est.low - want[0]) < 0.06 * width and abs(est.high - want[1]) < 0.06 * width
    assert est.n == 12


def test_cell_reports_mean_std_and_ci_and_drops_non_finite():
    c = stats.cell([1.0, 2.0, 3.0, float("nan")])
    assert c["n"] == 3 and c["mean"] == 2.0 and c["std"] == 1.0
    assert 1.0 <= c["ci_low"] < 2.0 < c["ci_high"] <= 3.0


def test_one_seed_gives_no_interval_and_verdict_says_so():
    est = stats.estimate([[3.0], [1.0]], stats.mean_difference)
    assert np.isnan(est.low) and stats.verdict(est) == stats.TOO_FEW


def test_verdicts():
    assert stats.verdict(stats.Estimate(2.0, 0.5, 3.0, 6)) == stats.SUPPORTED
    assert stats.verdict(stats.Estimate(-2.0, -3.0, -0.5, 6)) == stats.NOT_SUPPORTED
    assert stats.verdict(stats.Estimate(0.2, -1.0, 1.5, 6)) == stats.INCONCLUSIVE
    assert stats.verdict(stats.Estimate(0.7, 0.55, 0.9, 6), null=0.5) == stats.SUPPORTED


def test_rank_correlation_by_hand_and_its_small_sample_limits():
    # ranks of y by x: 2 1 3 4 -> rank differences 1 1 0 0: rho = 1 - 6 * 2 / (4 * 15) = 0.8
    est = stats.rank_correlation([1.0, 2.0, 3.0, 4.0], [5.0, 1.0, 6.0, 9.0])
    assert est.value == pytest.approx(0.8, abs=1e-12) and est.n == 4 and est.low <= 0.8 <= est.high
    few = stats.rank_correlation([1.0, 2.0, 3.0], [1.0, 3.0, 2.0])
    assert few.value == pytest.approx(0.5) and np.isnan(few.low) and stats.verdict(few) == stats.TOO_FEW
    with pytest.raises(ValueError, match="3 x values but 2 y values"):
        stats.rank_correlation([1.0, 2.0, 3.0], [1.0, 2.0])
    # constant x (every arm adds the same term): no correlation, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        flat = stats.rank_correlation([0.5] * 6, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    assert np.isnan(flat.value) and np.isnan(flat.low) and flat.n == 6


def test_intervals_do_not_depend_on_the_order_the_runs_are_listed_in():
    # a re-exported results file may list the same runs in another order; with three seeds an arm an
    # order-dependent bootstrap moved a bound of the committed report by up to 3.4 points
    x, y = np.array([58.0, 3.2, 90.1, 21.7]), np.array([21.0, 19.5, 44.0])
    forward = stats.estimate([x, y], stats.mean_difference)
    backward = stats.estimate([x[::-1], y[[2, 0, 1]]], stats.mean_difference)
    assert (forward.low, forward.high) == (backward.low, backward.high)
    # 12 pairs: with 6 the paired bootstrap's CI is (0, 1) in any order and could not show a difference
    u = np.array([0.0, 0.3, -0.27, -0.89, -0.45, -0.99, 0.06, 1.34, -0.49, -0.62, 0.49, 0.36])
    v = np.array([0.11, -0.78, -0.16, 0.25, -1.57, -0.95, -1.87, -0.62, -2.09, -0.55, -1.02, 0.45])
    perm = np.array([10, 2, 7, 8, 3, 9, 0, 1, 6, 4, 5, 11])  # unsorted, the bounds move: -0.547 vs -0.541
    a, b = stats.rank_correlation(u, v), stats.rank_correlation(u[perm], v[perm])
    assert (a.value, a.low, a.high) == (b.value, b.low, b.high)


def test_vectorised_spearman_matches_scipy_with_ties_and_constant_rows():
    rng = np.random.default_rng(3)
    u = rng.integers(0, 4, size=(50, 7)).astype(float)  # many ties
    v = rng.normal(size=(50, 7))
    v[0] = 1.0  # a constant row has no correlation
    got = stats.spearman(u, v)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = np.array([scipy_stats.spearmanr(a, b).statistic for a, b in zip(u, v, strict=True)])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12, equal_nan=True)
    assert np.isnan(got[0])
    # by hand: ranks (1, 2, 3) against (1, 3, 2): d = (0, -1, 1), rho = 1 - 6 * 2 / (3 * 8) = 0.5
    assert stats.spearman(np.array([1.0, 2, 3]), np.array([10.0, 30, 20])) == pytest.approx(0.5)


def test_estimate_names_the_verdicts_other_bootstrap_seeds_give():
    # three seeds an arm: the lower bound of the difference sits at 0, and its side of 0 depends on
    # which resamples are drawn; the estimate says so instead of presenting one draw as the verdict
    x, y = np.array([1.7, 0.5, -1.3]), np.array([-1.5, -0.6, -1.8])
    est = stats.estimate([x, y], stats.mean_difference)
    assert est.value == pytest.approx(1.6)
    redrawn = {
        stats.verdict(stats.Estimate(est.value, *stats.bootstrap_ci([x, y], stats.mean_difference, seed=k), 6))
        for k in range(1, stats.SEED_CHECKS + 1)
    }
    assert len(redrawn | {stats.verdict(est)}) == 2
    assert est.other_verdicts == tuple(sorted(redrawn - {stats.verdict(est)}))
    # a clear effect is the same under every seed
    clear = stats.estimate([np.array([50.0, 52, 55]), np.array([1.0, 2, 3])], stats.mean_difference)
    assert clear.other_verdicts == () and stats.verdict(clear) == stats.SUPPORTED


def test_permutation_p_by_hand_and_against_scipy():
    # one task, 3 vs 3, fully separated: of the C(6, 3) = 20 splits one lies as far up, one as far down
    assert stats.permutation_p([[61.0, 64, 66], [50.0, 52, 57]]) == pytest.approx(2 / 20)
    # 5 vs 3 with every x above every y: one split of C(8, 3) = 56 as high; two-sided doubles it
    assert stats.permutation_p([[38.6, 23.8, 74.3, 77.7, 10.9], [9.7, 9.4, 0.9]]) == pytest.approx(2 / 56)
    # two tasks, each 3 vs 3 and separated: 20 x 20 relabellings, one as high -> 2/400
    assert stats.permutation_p([[61.0, 64, 66], [65.0, 69, 64], [50.0, 52, 57], [58.0, 61, 60]]) == pytest.approx(
        2 / 400
    )
    assert stats.permutation_p([[1.0, 2, 3], [1.0, 2, 3]]) == 1.0
    assert np.isnan(stats.permutation_p([[1.0, np.nan, 3], [1.0, 2, 3]]))  # not a p of 0
    assert np.isnan(stats.sign_flip_p([[1.0, np.nan, 3]]))
    # one task: SciPy's own permutation test (exact at 13 runs, C(13, 7) = 1716 splits)
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=7) + 1, rng.normal(size=6)
    ref = scipy_stats.permutation_test(
        (x, y), lambda a, b, axis: a.mean(axis) - b.mean(axis), vectorized=True, n_resamples=10**6
    ).pvalue
    assert stats.permutation_p([x, y]) == pytest.approx(ref)


def test_permutation_p_keeps_tasks_apart():
    # task 1's runs sit far above task 2's; relabelling across tasks (SciPy's test on the pooled runs)
    # makes the arms' difference look small against a null that mixes the tasks. Within tasks x beats
    # y by 1 everywhere.
    x1, y1, x2, y2 = [101.0, 102, 103], [100.0, 101, 102], [1.0, 2, 3], [0.0, 1, 2]
    within = stats.permutation_p([x1, x2, y1, y2])
    # 3 vs 3 per task, shifted by 1 with overlap: count by enumeration of the 400 within-task splits
    import itertools

    def split_means(v, k):
        return [
            np.mean([v[i] for i in c]) - np.mean([v[i] for i in range(len(v)) if i not in c])
            for c in itertools.combinations(range(len(v)), k)
        ]

    null = [(a + b) / 2 for a in split_means(x1 + y1, 3) for b in split_means(x2 + y2, 3)]
    expected = 2 * min(np.mean(np.array(null) >= 1 - 1e-9), np.mean(np.array(null) <= 1 + 1e-9))
    assert within == pytest.approx(min(1.0, expected))
    pooled = scipy_stats.permutation_test(
        (np.array(x1 + x2), np.array(y1 + y2)), lambda a, b, axis: a.mean(axis) - b.mean(axis), vectorized=True
    ).pvalue
    assert within < 0.5 < pooled  # 0.175 within tasks, 0.64 across them


def test_the_percentile_bootstrap_alone_calls_too_many_differences_and_the_permutation_test_does_not():
    # exchangeable arms (both drawn from one normal pool): the percentile CI over 3 vs 3 runs excludes
    # 0 far more often than 5 % (docs/tables.md measures ~19 %); with the permutation test beside it
    # no verdict is called at 3 vs 3 (p >= 0.1) and at 5 vs 5 the rate stays near its 5 %
    pool = np.random.default_rng(1).normal(size=10000)
    ci_alone = stats.verdict_rate(pool, 3, 3, permutation=False, trials=300, n_resamples=500)
    assert ci_alone > 0.10
    assert stats.verdict_rate(pool, 3, 3, permutation=True, trials=100, n_resamples=500) == 0.0
    both = stats.verdict_rate(pool, 5, 5, permutation=True, trials=300, n_resamples=500, seed=1)
    assert both <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / 300)
    # and it still finds a real difference: x shifted by 3 standard deviations, 5 vs 5
    rng = np.random.default_rng(2)
    found = sum(stats.permutation_p([rng.normal(size=5) + 3, rng.normal(size=5)]) < 0.05 for _ in range(50))
    assert found >= 45


def _t_power(d, n_x, n_y, alpha=0.05):
    """Two-sided two-sample t-test power from the noncentral t, written out here (not statsmodels)."""
    df = n_x + n_y - 2
    nc = d / np.sqrt(1 / n_x + 1 / n_y)
    crit = scipy_stats.t.ppf(1 - alpha / 2, df)
    return scipy_stats.nct.sf(crit, df, nc) + scipy_stats.nct.cdf(-crit, df, nc)


def _unit_sd_arms(effect):
    # x = effect ± a, y = ± a with a = 1/√2: each arm's sample variance (ddof 1) is 2a² = 1
    a = np.sqrt(0.5)
    return [np.array([effect - a, effect + a]), np.array([-a, a])]


@pytest.mark.parametrize("d, n", [(0.2, 394), (0.5, 64), (0.8, 26)])
def test_power_plan_runs_match_the_textbook_sample_sizes(d, n):
    # per group for power .80, two-tailed alpha .05, exact t-test: G*Power's 394 / 64 / 26 (total
    # 788 / 128 / 52); Cohen's (1988) Table 2.4.1, from a normal approximation, gives 393 / 64 / 26
    plan = stats.power_plan(_unit_sd_arms(d))
    assert plan.sd == pytest.approx(1.0)
    assert plan.runs == n
    assert _t_power(d, n, n) >= 0.8 > _t_power(d, n - 1, n - 1)


def test_power_plan_smallest_effect_has_the_power_by_the_noncentral_t():
    x = np.array([1.0, 2, 3, 4, 5]) + 10
    y = np.array([2.0, 4, 6, 8, 10])
    # pooled sd: both arms centred, sums of squares 10 and 40 over 4 + 4 dof -> sqrt(50 / 8)
    plan = stats.power_plan([x, y])
    assert plan.sd == pytest.approx(np.sqrt(50 / 8))
    assert _t_power(plan.mde / plan.sd, 5, 5) == pytest.approx(0.8, abs=1e-3)
    assert 1.9 < plan.mde / plan.sd < 2.1  # ~2.02 sd at 5 vs 5
    # the observed effect (+7) is 2.8 sd: 4 runs per arm have that power, and 4 is the test's floor
    assert _t_power(7 / plan.sd, 4, 4) > 0.8 and plan.runs == 4


def test_power_plan_respects_what_the_permutation_test_can_reach():
    assert stats.min_permutation_p([(3, 3)]) == pytest.approx(2 / 20)
    assert stats.min_permutation_p([(3, 3), (3, 3)]) == pytest.approx(2 / 400)
    assert stats.permutation_floor(1) == 4 and stats.permutation_floor(2) == 3 and stats.permutation_floor(3) == 2
    three = [np.array([10.0, 11, 12]), np.array([0.0, 1, 2])]
    plan = stats.power_plan(three)
    assert plan.mde == np.inf  # no split of 3 vs 3 reaches p < 0.05
    assert plan.runs == 4  # a 10-sd effect needs only the floor
    # on two datasets 3 vs 3 each can pass, and the runs are per dataset: Cohen's 64 per arm at d = 0.5
    # spread over two datasets is 32 each
    two = stats.power_plan([*_unit_sd_arms(0.5)[:1], *_unit_sd_arms(0.5)[:1], *_unit_sd_arms(0.5)[1:] * 2])
    assert two.runs == 32
    # no effect, and no spread or too few runs
    assert stats.power_plan([np.array([1.0, 2]), np.array([1.0, 2])]).runs == np.inf
    assert np.isnan(stats.power_plan([np.array([1.0]), np.array([1.0, 2])]).sd)
    assert np.isnan(stats.power_plan([np.array([1.0, 1]), np.array([1.0, 1])]).runs)


def test_the_verdict_rule_has_about_the_planned_power_at_the_planned_runs():
    # a normal pool with a shift of 1.5 sd: the plan asks for 9 runs per arm; the full rule (bootstrap
    # CI and permutation test) then calls the difference close to 80 % of the time
    pool = np.random.default_rng(4).normal(size=10000)
    plan = stats.power_plan(_unit_sd_arms(1.5))
    n = int(plan.runs)  # the fewest runs per arm whose t-test power reaches 80 %
    assert _t_power(1.5, n, n) >= 0.8 > _t_power(1.5, n - 1, n - 1)
    power = stats.verdict_rate(pool, n, n, shift=1.5, permutation=True, trials=200)
    assert 0.65 <= power <= 0.95
    assert stats.verdict_rate(pool, 4, 4, shift=1.5, permutation=True, trials=200) < power


def test_t_test_power_against_simulated_t_tests_and_where_scipys_nct_gives_nan():
    rng = np.random.default_rng(5)
    x, y = rng.normal(size=(20000, 5)) + 1.5, rng.normal(size=(20000, 5))
    simulated = np.mean(scipy_stats.ttest_ind(x, y, axis=1).pvalue < 0.05)
    assert stats.t_test_power(1.5, 5, 5) == pytest.approx(simulated, abs=0.015)  # ~0.54
    assert stats.t_test_power(12.0, 6, 6) == pytest.approx(1.0)  # nct is nan here: the normal fallback
    assert stats.t_test_power(0.0, 5, 5) == pytest.approx(0.05)


def test_power_plan_uses_effective_sizes_where_the_datasets_sizes_differ():
    # 10 and 2 runs per arm on two tasks: the mean of the tasks' differences has variance
    # sd² (1/10 + 1/10 + 1/2 + 1/2) / 4, so it is as precise as 4 / 0.6 = 6.7 runs per arm, not 12.
    # Simulated here: the stratified t statistic at the plan's mde, on t(24 − 4) = t(20)
    rng = np.random.default_rng(6)
    sizes = (10, 2)
    strata = [rng.normal(size=n) for n in sizes] + [rng.normal(size=n) for n in sizes]
    plan = stats.power_plan(strata)
    trials = 20000
    diffs, ss = np.zeros(trials), np.zeros(trials)
    for n in sizes:
        x, y = rng.normal(size=(trials, n)) + plan.mde / plan.sd, rng.normal(size=(trials, n))
        diffs += (x.mean(1) - y.mean(1)) / 2
        ss += ((x - x.mean(1, keepdims=True)) ** 2).sum(1) + ((y - y.mean(1, keepdims=True)) ** 2).sum(1)
    se = np.sqrt(ss / 20) * np.sqrt(sum(1 / n + 1 / n for n in sizes)) / 2
    found = np.mean(np.abs(diffs / se) > scipy_stats.t.ppf(0.975, 20))
    assert found == pytest.approx(0.8, abs=0.015)
    # and never fewer runs than a verdict needs: 3 tasks can pass the permutation test at 2 vs 2
    big = [np.array([100.0, 101])] * 3 + [np.array([0.0, 1])] * 3
    assert stats.power_plan(big).runs == 2 and stats.power_plan(big, min_runs=3).runs == 3
