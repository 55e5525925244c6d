"""Reports: published references as data, intervals, verdicts and runs-to-settle, the files they write."""

from __future__ import annotations

import csv
import io
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import cli

from orchestrator import report, statistics
from orchestrator.references import THESIS, Reference, find, load_references
from orchestrator.sweep import SweepError, load_sweep
from orchestrator.tracking import FAILED, FINISHED, Tracker, default_tracking_uri


def test_worked_example_18_of_20_against_096_is_consistent():
    comparison = statistics.compare_rate(18, 20, 0.96)
    assert comparison.verdict == "consistent" and comparison.test == "exact binomial"
    assert comparison.p_value == pytest.approx(0.19, abs=0.005)  # two-sided exact binomial
    # Telling 0.90 from 0.96 at 5% with 80% power takes on the order of a hundred episodes.
    assert 80 <= comparison.runs_needed <= 250


@pytest.mark.parametrize("successes, trials, published, needed", [(0, 1, 0.9, 2), (1, 1, 0.1, 2), (4, 5, 0.9, 98)])
def test_runs_needed_for_few_episodes_and_large_effects(successes, trials, published, needed):
    """0 of 1 against 0.9 is not significant yet; two episodes would be (Cohen's h 2.5, two-sided at 5% with 80%
    power: ((1.96 + 0.84) / 2.5)^2 = 1.26), not a crash."""
    comparison = statistics.compare_rate(successes, trials, published)
    assert comparison.verdict == "consistent" and comparison.runs_needed == needed


def test_a_clearly_lower_rate_is_below_and_needs_no_more_runs():
    comparison = statistics.compare_rate(5, 40, 0.81)
    assert comparison.verdict == "below" and comparison.p_value < 1e-6 and comparison.runs_needed is None
    assert statistics.compare_rate(40, 40, 0.5).verdict == "above"


def test_a_true_published_rate_is_called_below_or_above_in_at_most_5_percent_of_comparisons():
    """The verdict's side comes from the data, so the test is two-sided: a one-sided test in the direction the
    data happen to point would call about 9% of these exact-null draws below or above."""
    draws = np.random.default_rng(0).binomial(100, 0.5, size=2000)
    verdicts = [statistics.compare_rate(int(k), 100, 0.5).verdict for k in draws]
    assert np.mean([v != "consistent" for v in verdicts]) < 0.065
    assert statistics.compare_rate(73, 100, 0.81).verdict == "consistent"  # one-sided p 0.032, two-sided 0.055


def test_runs_to_settle_against_a_few_published_runs_reach_80_percent_power_or_are_not_named():
    """Against 50 published runs more own runs settle a 100-point gap (and simulated Welch tests at that count
    detect it in about 80% of cases); against 5 published runs with a spread as large as the gap, no number of
    own runs does, and the report says so instead of naming one."""
    from scipy import stats

    spread = 167.0
    own = 5336 + spread * np.array([-1.0, -0.5, 0.0, 0.5, 1.0]) / np.std([-1.0, -0.5, 0.0, 0.5, 1.0], ddof=1)
    comparison = statistics.compare_mean(own, 5236, spread, "std", 50)
    assert comparison.verdict == "consistent" and comparison.attainable
    needed = comparison.runs_needed
    rng = np.random.default_rng(1)
    detected = [
        stats.ttest_ind(rng.normal(5336, spread, needed), rng.normal(5236, spread, 50), equal_var=False).pvalue < 0.05
        for _ in range(1000)
    ]
    assert 0.75 <= np.mean(detected) <= 0.87
    few = statistics.compare_mean(np.array([9.5, 10.0, 10.5, 11.0, 11.5]), 10.0, 1.0, "std", 5)
    assert few.verdict == "consistent" and few.runs_needed is None and not few.attainable
    reference = Reference(task="halfcheetah_running", metric="episode_return", value=10.0, spread=1.0,
                          spread_kind="std", runs=5, source="test")  # fmt: skip
    group = report.Group("halfcheetah_running", "mpc", {}, None, {}, [], 10.5, 0.0, statistics.Interval(10.5, 0, 0),
                         None, None, reference, few)  # fmt: skip
    assert "no number of runs settles it against 5 published runs" in report._comparison_text(group)
    summary = report.Summary([group], "episode_return", "mean_return", "max", 0)
    (row,) = csv.DictReader(io.StringIO(report.to_csv(summary)))
    assert row["runs_to_settle"] == "unattainable"


def test_a_reference_of_one_run_or_constant_runs_are_tested_only_where_a_test_is_defined():
    """One published run has no spread to test against: its mean is taken as exact (a one-sample test), not a nan
    p-value turned into a verdict; constant own runs against a mean without a spread are not tested."""
    single = statistics.compare_mean(np.array([9.0, 10.0, 11.0, 12.0]), 8.0, 1.0, "std", 1)
    assert single.test == "one-sample t-test, published spread unused (one run)" and math.isfinite(single.p_value)
    constant = statistics.compare_mean(np.array([5.0, 5.0, 5.0]), 3.0, 1.0, "std", None)
    assert constant.test == "too few runs to test" and constant.verdict == "untested"
    assert statistics.compare_mean(np.array([5.0]), 3.0, 1.0, "std", 10).verdict == "untested"
    assert statistics._verdict(math.nan, below=True) == "untested"  # whatever test returns an undefined p-value
    assert statistics.compare_mean(np.array([5.0, 5.0, 5.0]), 3.0, 1.0, "std", 10).test == "Welch t-test"
    zero = statistics.compare_mean(np.array([9.0, 10.0, 11.0]), 8.0, 0.0, "std", 5)  # a spread of 0 over 5 runs
    assert zero.test == "one-sample t-test, published spread unused (a spread of 0)"


def test_a_published_rate_over_known_runs_is_tested_as_a_second_sample():
    """Table 3's rates come from 50 or 100 runs: 9 of 10 against 50 of 50 is Fisher's p = 0.17, not the
    binomial test's p = 0 against an exact 1.0; the rate stays exact where no run count is published."""
    fisher = statistics.compare_rate(9, 10, 1.0, 50)
    assert fisher.verdict == "consistent" and fisher.test == "Fisher exact"
    assert fisher.p_value == pytest.approx(0.167, abs=0.002)
    assert statistics.compare_rate(5, 40, 0.81).verdict == "below"  # the rate taken as exact
    assert statistics.compare_rate(5, 40, 0.81, 100).verdict == "below"


@pytest.mark.parametrize("published", [0.0, 1.0])
def test_a_published_rate_of_zero_or_one_without_runs_is_not_tested(published):
    """Taken as exact, a published 100% makes one failure in 50 impossible (p = 0, "below"); that rate was itself
    counted over runs the reference does not give."""
    comparison = statistics.compare_rate(1 if published == 0.0 else 49, 50, published)
    assert comparison.verdict == "untested" and "without its run count" in comparison.test


def test_episodes_to_settle_against_published_runs_reach_80_percent_power_or_are_not_named():
    """Against 100 published runs the episodes named detect the gap in about 80% of simulated Fisher tests; a gap
    the published runs alone cannot resolve names none."""
    from scipy import stats

    comparison = statistics.compare_rate(6, 10, 0.81, 100)
    assert comparison.verdict == "consistent" and comparison.attainable
    needed = comparison.runs_needed
    assert needed > statistics.compare_rate(6, 10, 0.81).runs_needed  # the published runs' own error counts
    rng = np.random.default_rng(0)
    ours, theirs = rng.binomial(needed, 0.6, size=600), rng.binomial(100, 0.81, size=600)
    detected = [stats.fisher_exact([[a, needed - a], [b, 100 - b]]).pvalue < 0.05 for a, b in zip(ours, theirs)]
    assert 0.72 <= np.mean(detected) <= 0.88
    # Fetch's 73 of 100 against 81 of 100: h^2 = 0.037 is below z^2 / 100 = 0.078, so no count of own episodes does.
    hopeless = statistics.compare_rate(73, 100, 0.81, 100)
    assert hopeless.verdict == "consistent" and hopeless.runs_needed is None and not hopeless.attainable


def test_the_interval_of_a_few_runs_mean_covers_the_true_mean_95_percent_of_the_time():
    """Three normal runs: Student's t covers the true mean in about 95% of draws, where a bootstrap of three runs
    covers about 71%."""
    rng = np.random.default_rng(0)
    covered = []
    for _ in range(400):
        interval = statistics.mean_interval(rng.normal(5236.0, 167.0, size=3))
        covered.append(interval.low <= 5236.0 <= interval.high)
    assert 0.92 <= np.mean(covered) <= 0.98
    two = statistics.mean_interval(np.array([1.0, 3.0]))
    assert two.low == pytest.approx(2.0 - 12.706, abs=1e-3)  # t(0.975, 1) * sem 1


def test_success_figures_logged_with_their_episodes_are_rates_of_independent_episodes_only():
    """Ground-truth MPC's episodes are independent draws: 0.6, 0.4 and 0.2 over 5 episodes each are 6 of 15, not
    three trials' rates rounded to 1 of 3. An mbrl (or APEX, neural APSP) trial's episodes share one trained model:
    the seed is the unit, so its rates stay a mean over seeds however many episodes each counts."""
    from orchestrator.tracking import TrialRun

    def run(method, key, seed, rate, episodes=None):
        params = {"method": method, "task": "bridge_maze", "seed": str(seed)}
        metrics = {key: rate} | ({f"{key}_episodes": episodes} if episodes else {})
        return TrialRun(f"r{seed}", f"k{seed}", FINISHED, "name", params, {}, metrics)

    rates = [(0, 0.6), (1, 0.4), (2, 0.2)]
    counted = report.summarize([run("mpc", "success_rate", s, r, 5) for s, r in rates], "success", references=[])
    (group,) = counted.groups
    assert group.successes == (6, 15) and group.mean == pytest.approx(0.4)
    learned = [run("mbrl", "final_success_rate", s, r, 5) for s, r in rates]
    (per_seed,) = report.summarize(learned, "success", references=[]).groups
    assert per_seed.successes is None and per_seed.mean == pytest.approx(0.4)
    assert per_seed.interval.high - per_seed.interval.low > 0.5  # a t interval over 3 seeds, not 15 episodes'


def test_apex_rates_are_tested_against_table_9_by_seed_not_by_pooled_episode():
    """Three seeds at 0.60, 0.65, 0.70 over 125 episodes each against Table 9's 0.77: pooled as 375 independent
    episodes they would be "below" at p = 1.5e-7; by seed the one-sample test gives p = 0.053."""
    from orchestrator.tracking import TrialRun

    params = {"method": "apex", "task": "fetch_pick_place_sparse"}
    runs = [TrialRun(f"r{s}", f"k{s}", FINISHED, "n", params | {"seed": str(s)}, {},
                     {"final_policy_success": rate, "final_policy_success_episodes": 125})
            for s, rate in enumerate([0.60, 0.65, 0.70])]  # fmt: skip
    reference = Reference(task="fetch_pick_place_sparse", metric="policy_success", value=0.77, source="t", method="apex")
    (group,) = report.summarize(runs, "policy_success", references=[reference]).groups
    assert group.successes is None and group.comparison.test == "one-sample t-test"
    assert group.comparison.verdict == "consistent" and group.comparison.p_value == pytest.approx(0.053, abs=0.002)


@pytest.mark.parametrize("seeds, published", [([0.5, 0.6], 0.99), ([0.0, 1.0], 4.7426), ([0.0, 1.0], 6.0)])
def test_runs_to_settle_a_one_sample_test_far_from_the_published_mean_reach_80_percent_power(seeds, published):
    """Two runs 4.9-7.8 of their standard deviations from a mean taken as exact, not significant (one degree of
    freedom): the power with those two runs is 0.42-0.68 and with three above 0.95, so three runs settle it. Two
    would be too few, and scipy's noncentral t gives nan there, which must not end the report."""
    from scipy import stats

    comparison = statistics.compare_mean(np.array(seeds), published, None, None, None)
    assert comparison.verdict == "consistent" and comparison.runs_needed == 3 and comparison.attainable
    effect = abs(np.mean(seeds) - published) / np.std(seeds, ddof=1)
    for runs, enough in ((2, False), (3, True)):  # simulated one-sample t-tests at that many runs
        draws = np.random.default_rng(runs).normal(effect, 1.0, size=(100_000, runs))
        t = draws.mean(axis=1) / (draws.std(axis=1, ddof=1) / math.sqrt(runs))
        power = np.mean(np.abs(t) > stats.t.ppf(0.975, runs - 1))
        assert (power >= statistics.POWER) == enough


def test_runs_to_settle_a_one_sample_test_of_a_small_effect():
    """Four runs 0.23 of their standard deviation from the published mean: 148 runs (statsmodels' TTestPower
    solves the same question to 147.3)."""
    comparison = statistics.compare_mean(np.array([9.0, 10.0, 11.0, 12.0]), 10.2, None, None, None)
    assert comparison.verdict == "consistent" and comparison.runs_needed == 148


def test_a_mean_of_per_seed_rates_has_an_interval_within_0_and_1():
    """Student's t over two seeds' rates 1.0 and 0.9 reaches 1.59, and over 0.0, 0.04, 0.0 below 0; a rate's
    interval is cut to [0, 1]. A return's interval is not."""
    from orchestrator.tracking import TrialRun

    def summary(metric, key, values):
        runs = [TrialRun(f"r{s}", f"k{s}", FINISHED, "n", {"method": "apex", "task": "door_sparse", "seed": str(s)},
                         {}, {key: v}) for s, v in enumerate(values)]  # fmt: skip
        return report.summarize(runs, metric, references=[])

    def group(metric, key, values):
        (only,) = summary(metric, key, values).groups
        return only.interval

    high = group("policy_success", "final_policy_success", [1.0, 0.9])
    assert high.high == 1.0 and high.low == pytest.approx(0.315, abs=0.001)
    low = group("policy_success", "final_policy_success", [0.0, 0.04, 0.0])
    assert low.low == 0.0 and low.high == pytest.approx(0.071, abs=0.001)
    returns = group("policy_return", "final_policy_return", [1.0, 0.9])
    assert returns.high == pytest.approx(1.585, abs=0.001)
    assert "cut to [0, 1]" in report.interval_caption(summary("policy_success", "final_policy_success", [1.0, 0.9]))
    assert "cut to" not in report.interval_caption(summary("policy_return", "final_policy_return", [1.0, 0.9]))


def test_seeds_without_a_value_leave_the_configuration_untested_and_unranked():
    """Rollouts to the threshold of 10 Ours+HER seeds, 7 of which never got there: the 3 that did (9,000-9,400) are
    not "below" section 6.6.2's 11k, and their configuration does not outrank one whose every seed crossed."""
    from orchestrator.tracking import TrialRun

    def run(reward, seed, value):
        params = {"method": "napsp", "task": "fetch_pick_place", "reward": reward, "seed": str(seed)}
        return TrialRun(f"{reward}{seed}", f"k{reward}{seed}", FINISHED, "n", params, {"reward": reward},
                        {"episodes_to_threshold": value})  # fmt: skip

    ours = [run("ours_her", s, v) for s, v in enumerate([9000, 9200, 9400] + [math.nan] * 7)]
    ddl = [run("ddl_her", s, 15000 + 100 * s) for s in range(10)]
    summary = report.summarize(ours + ddl, "episodes_to_threshold", "min", load_references(THESIS))
    groups = {g.trials[0].params["reward"]: g for g in summary.groups}
    assert groups["ours_her"].missing == 7 and groups["ours_her"].n == 10
    assert groups["ours_her"].comparison.verdict == "untested" and "7 of 10" in groups["ours_her"].comparison.test
    assert summary.groups[summary.best] is groups["ddl_her"]  # its mean is higher, but every seed has one
    assert "(of 3; 7 without a value)" in report.format_table(summary)


def test_an_untested_comparison_is_not_written_as_consistent():
    """Two APEX seeds that never succeed against Table 9's 0.99, with no episode count: no test is defined, and
    the CSV says untested, not consistent."""
    from orchestrator.tracking import TrialRun

    params = {"method": "apex", "task": "door_sparse", "seed": "0"}
    runs = [TrialRun(f"r{s}", f"k{s}", FINISHED, "n", params | {"seed": str(s)}, {}, {"final_policy_success": 0.0})
            for s in (0, 1)]  # fmt: skip
    reference = Reference(task="door_sparse", metric="policy_success", value=0.99, source="test", method="apex")
    summary = report.summarize(runs, "policy_success", references=[reference])
    (row,) = csv.DictReader(io.StringIO(report.to_csv(summary)))
    assert row["verdict"] == "untested"


def test_a_reduced_apex_run_stands_beside_table_9_untested_with_what_it_changed():
    """The Door acceptance sweep runs n = 2 rollouts per iteration where Table 10 has 10: Table 9's 0.99 is shown
    beside it, not tested, and the report names the difference; the full HalfCheetah setting is tested."""
    from orchestrator.tracking import TrialRun

    references = load_references(THESIS)
    root = Path(__file__).resolve().parents[1] / "sweeps" / "acceptance"

    def summary_of(sweep: str, metric: str, values: list[float]):
        trial = load_sweep(root / sweep).trials[0]
        params = {key: str(value) for key, value in trial.config.flat().items()}
        params |= {"method": "apex", "task": trial.config.task}
        runs = [TrialRun(f"r{s}", f"k{s}", FINISHED, "n", params | {"seed": str(s)}, {}, {f"final_{metric}": v})
                for s, v in enumerate(values)]  # fmt: skip
        return report.summarize(runs, metric, references=references)

    door = summary_of("apex_door_sparse.yaml", "policy_success", [0.0, 0.0])
    (group,) = door.groups
    assert group.reference is not None and group.reference.value == 0.99
    assert group.comparison.verdict == "untested"
    assert "rollouts=2 (published 10)" in group.comparison.test and "window" not in group.comparison.test
    assert "rollouts=2 (published 10)" in report.format_table(door)
    (row,) = csv.DictReader(io.StringIO(report.to_csv(door)))
    assert row["verdict"] == "untested" and row["published"] == "0.99"

    halfcheetah = summary_of("apex_halfcheetah.yaml", "evaluation_return", [3000.0, 3500.0, 3200.0])
    tested = halfcheetah.groups[0].comparison
    assert tested.verdict == "below" and tested.test == "one-sample t-test, published spread unused (no run count)"


def test_pairs_that_all_differ_by_the_same_amount_get_the_sign_test():
    """The t statistic of constant differences is undefined; five of five pairs higher is p = 2 / 32."""
    shifted = statistics.compare_paired(np.array([3.0, 5.0, 2.0, 7.0, 4.0]), np.array([2.0, 4.0, 1.0, 6.0, 3.0]))
    assert shifted.test == "sign test" and shifted.p_value == pytest.approx(0.0625)
    same = statistics.compare_paired(np.array([3.0, 5.0]), np.array([3.0, 5.0]))
    assert same.test == "sign test" and same.p_value == 1.0


def test_wilson_interval_and_iqm():
    interval = statistics.rate_interval(18, 20)
    assert interval.estimate == 0.9 and 0.68 < interval.low < 0.72 and 0.97 < interval.high < 0.99
    values = np.array([1.0, 2.0, 3.0, 4.0, 100.0, 5.0, 6.0, 7.0])
    assert statistics.iqm(values) == pytest.approx(4.5)  # the middle half: 3, 4, 5, 6
    assert statistics.iqm_interval(values[:4]) is None  # fewer than five runs
    estimate = statistics.iqm_interval(values)
    assert estimate.low <= estimate.estimate <= estimate.high


def test_welch_against_a_published_mean_and_spread():
    rng = np.random.default_rng(0)
    close = rng.normal(5236, 167, size=8)
    far = rng.normal(4300, 167, size=8)
    assert statistics.compare_mean(close, 5236, 167, "std", 50).verdict == "consistent"
    below = statistics.compare_mean(far, 5236, 167, "std", 50)
    assert below.verdict == "below" and below.test == "Welch t-test" and below.p_value < 1e-4
    # A standard error is turned back into the per-run spread before testing.
    as_sem = statistics.compare_mean(close, 5236, 167 / math.sqrt(50), "sem", 50)
    assert as_sem.p_value == pytest.approx(statistics.compare_mean(close, 5236, 167, "std", 50).p_value)


def test_the_thesis_tables_are_data_with_sources():
    references = load_references(THESIS)
    full_episodes = {"planner.algorithm": "icem", "planner.budget": "100", "max_steps": "None"}
    table_3 = find(references, "halfcheetah_running", "mpc", full_episodes, "episode_return")
    assert (table_3.value, table_3.spread, table_3.runs) == (5236, 167, 50) and "Table 3" in table_3.source
    cut_short = {"planner.algorithm": "icem", "planner.budget": "100", "max_steps": "200"}
    assert find(references, "halfcheetah_running", "mpc", cut_short, "episode_return") is None  # not full episodes
    assert all(r.source for r in references)


def test_chapter_6s_sample_efficiency_stands_beside_its_paper_sweep():
    """Section 6.6.2's rollouts to the threshold on Fetch Pick&Place: Ours+HER (both readings) beside 11k, DDL+HER
    beside the derived 20k; the other rewards and the task with the wall have no published figure."""
    references = load_references(THESIS)
    sweep = Path(__file__).resolve().parents[1] / "sweeps" / "paper" / "napsp_fetch_pick_place.yaml"
    loaded = load_sweep(sweep)
    compared = {}
    for trial in loaded.trials:
        if trial.config.seed != 0:
            continue
        params = {key: str(value) for key, value in trial.config.flat().items()}
        reference = find(references, trial.config.task, "napsp", params, loaded.sweep.metric.name)
        compared[(trial.config.task, trial.variant)] = None if reference is None else reference.value
    assert {key: value for key, value in compared.items() if value is not None} == {
        ("fetch_pick_place", "ours_her"): 11000,
        ("fetch_pick_place", "ours_her_literal"): 11000,
        ("fetch_pick_place", "ddl_her"): 20000,
    }
    assert len(compared) == 10  # every variant on both tasks was looked up

    # The figure is for the goal augmented by the end effector (App. E.2): without it, shown beside, untested.
    from orchestrator.tracking import TrialRun

    plain = {"method": "napsp", "task": "fetch_pick_place", "reward": "ours_her", "task_options.augment_goal": "False"}
    runs = [TrialRun(f"r{s}", f"k{s}", FINISHED, "n", plain | {"seed": str(s)}, {}, {"episodes_to_threshold": v})
            for s, v in enumerate([9000.0, 9500.0, 9900.0])]  # fmt: skip
    (group,) = report.summarize(runs, "episodes_to_threshold", "min", references).groups
    assert group.reference.value == 11000 and group.comparison.verdict == "untested"
    assert "task_options.augment_goal=False" in group.comparison.test


@pytest.mark.parametrize("changed", [{"planner.horizon": "10"}, {"planner.sigma_init": "0.3"}, {"planner.elites": "5"}])
def test_table_3_is_not_tested_against_a_run_with_other_fixed_settings(changed):
    """Table 3 is the h = 30, sigma_init = 0.5, K = 10 configuration (Table 5): a horizon sweep's rows stand beside
    it, untested, naming what they changed, rather than reading as failures to reproduce it."""
    from orchestrator.tracking import TrialRun

    params = {"method": "mpc", "task": "halfcheetah_running", "planner.algorithm": "icem", "planner.budget": "100",
              "max_steps": "None", "planner.horizon": "30", "planner.sigma_init": "0.5", "planner.elites": "10"}
    runs = [TrialRun(f"r{s}", f"k{s}", FINISHED, "n", params | changed | {"seed": str(s)}, {}, {"mean_return": v})
            for s, v in enumerate([4000.0, 4100.0, 4200.0])]  # fmt: skip
    (group,) = report.summarize(runs, "episode_return", references=load_references(THESIS)).groups
    key, value = next(iter(changed.items()))
    assert group.reference.value == 5236 and group.comparison.verdict == "untested"
    assert f"{key}={value}" in group.comparison.test
    full = [r._replace(params=params | {"seed": r.params["seed"]}) for r in runs]
    (tested,) = report.summarize(full, "episode_return", references=load_references(THESIS)).groups
    assert tested.comparison.verdict == "below"


def test_table_9_stands_beside_the_full_apex_only():
    """APEX with every component on is compared with Table 9; iCEM BC, the ablations and other budgets are not."""
    references = load_references(THESIS)
    sweep = Path(__file__).resolve().parents[1] / "sweeps" / "acceptance" / "apex_halfcheetah.yaml"
    trials = load_sweep(sweep).trials
    compared = {}
    for trial in trials:
        params = {key: str(value) for key, value in trial.config.flat().items()}
        reference = find(references, "halfcheetah_running", "apex", params, "policy_return")
        compared[trial.variant] = None if reference is None else (reference.value, reference.source)
    assert compared["apex"] == compared["apex-reinit"] == (4847, "Table 9 (App. C.1)")
    assert compared["icem-bc"] is None and compared["icem-bc-reinit"] is None
    full = {key: str(value) for key, value in trials[0].config.flat().items()}
    budget_100 = full | {"planner.budget": "100"}
    assert find(references, "halfcheetah_running", "apex", budget_100, "policy_return").value == 5596
    assert find(references, "halfcheetah_running", "apex", full | {"warm_start": "False"}, "policy_return") is None
    assert find(references, "halfcheetah_running", "apex", full, "expert_return").value == 5556
    # The sweep's headline, the final policy over evaluation episodes, stands for Table 9's policy too.
    assert load_sweep(sweep).sweep.metric.name == "evaluation_return"
    assert find(references, "halfcheetah_running", "apex", full, "evaluation_return").value == 4847
    # Table 10's settings beyond the switches: another c is shown beside Table 9 untested; an expert with an
    # iCEM improvement off (an ablation) is not compared at all.
    from orchestrator.tracking import TrialRun

    def group_of(params: dict[str, str]):
        run = TrialRun("r", "k", FINISHED, "n", params | {"method": "apex", "task": "halfcheetah_running"}, {},
                       {"final_evaluation_return": 4000.0})  # fmt: skip
        return report.summarize([run], "evaluation_return", references=references).groups[0]

    assert group_of(full).reference.value == 4847 and group_of(full).comparison.verdict == "untested"  # one run
    other_c = group_of(full | {"c": "0.1"})
    assert other_c.reference.value == 4847 and other_c.comparison.test == "not tested: ran c=0.1 (published 0.025)"
    assert group_of(full | {"planner.keep_elites": "False"}).reference is None


def fabricate(
    tmp_path, values: dict[str, list[float]], metric_key="mean_return", sweep_text="name: mixed\n"
) -> Tracker:
    """A store holding a finished point_reach sweep: per algorithm, one run per value."""
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("mixed", "mixed", "hash", sweep_text, {}, "dev")
    for algorithm, runs in values.items():
        for seed, value in enumerate(runs):
            params = {"method": "mpc", "task": "point_reach", "seed": seed, "planner.algorithm": algorithm,
                      "planner.budget": 50, "max_steps": None, "episodes": 1}  # fmt: skip
            tags = {"method": "mpc", "task": "point_reach", "algorithm": algorithm, "budget": "50",
                    "icemlab.override.algorithm": f'"{algorithm}"'}  # fmt: skip
            run_id = tracker.start_trial(parent, f"{algorithm}{seed}", f"{algorithm}/{seed}", params, tags)
            tracker.end_trial(run_id, FINISHED, {metric_key: value})
    tracker.end_sweep(parent, FINISHED, {})
    return tracker


REFERENCE = """entries:
  - {task: point_reach, method: mpc, match: {planner.algorithm: icem, planner.budget: 50}, metric: episode_return,
     value: -4.0, spread: 0.5, spread_kind: std, runs: 20, source: "Table X"}
  - {task: point_reach, method: mpc, match: {planner.algorithm: cem_mpc, planner.budget: 50}, metric: episode_return,
     value: 10.0, spread: 0.5, spread_kind: std, runs: 20, source: "Table Y"}
"""


def test_report_marks_a_matching_configuration_consistent_and_a_distant_one_below(tmp_path):
    fabricate(tmp_path, {"icem": [-4.2, -3.9, -4.1, -3.8, -4.3, -4.0], "cem_mpc": [-5.2, -5.5, -5.1, -5.4, -5.6, -5.3]})
    (tmp_path / "paper.yaml").write_text(REFERENCE)
    sweep = tmp_path / "mixed.yaml"
    sweep.write_text("name: mixed\ntask: point_reach\nreference: paper.yaml\n")
    result = cli("report", str(sweep), "--output", str(tmp_path / "out"), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    lines = {line.split()[1]: line for line in result.stdout.splitlines() if line.startswith("point_reach")}
    assert "consistent (Welch t-test" in lines["icem"]
    assert "below (Welch t-test, p=" in lines["cem_mpc"]
    rows = {row["planner.algorithm" if "planner.algorithm" in row else "algorithm"]: row
            for row in csv.DictReader(io.StringIO((tmp_path / "out" / "summary.csv").read_text()))}  # fmt: skip
    assert rows["icem"]["verdict"] == "consistent" and rows["cem_mpc"]["verdict"] == "below"
    assert float(rows["cem_mpc"]["p_value"]) < 1e-6 and rows["cem_mpc"]["published_source"] == "Table Y"
    assert float(rows["icem"]["episode_return_ci_low"]) < float(rows["icem"]["episode_return_mean"])
    assert rows["icem"]["episode_return_iqm"] != ""  # six runs: the IQM is given
    assert rows["icem"]["runs_to_settle"] != "" and rows["cem_mpc"]["runs_to_settle"] == ""
    # Two tests at 5% each: the table says how many would read below or above by chance.
    assert "2 tests against published figures, each at 5% and not corrected" in result.stdout
    assert "about 0.1 of them" in result.stdout


def test_one_test_against_the_thesis_gets_no_note_on_the_number_of_tests():
    runs = [report_run("icem", value) for value in (1.0, 2.0, 1.5)]
    reference = Reference(task="point_reach", metric="episode_return", value=1.4, source="t", spread=0.5,
                          spread_kind="std", runs=5)  # fmt: skip
    table = report.format_table(report.summarize(runs, "episode_return", references=[reference]))
    assert "consistent" in table and "tests against published figures" not in table


def test_a_rate_settles_in_episodes_and_every_success_metric_prints_as_a_rate():
    """The episodes a pooled rate test needs are named episodes in the table and the CSV; APEX's, napsp's and
    mbrl's success figures print with two decimals like mpc's."""
    comparison = statistics.compare_rate(30, 40, 0.81)
    assert comparison.runs_needed
    reference = Reference(task="door_sparse", metric="success", value=0.81, source="t")
    group = report.Group("door_sparse", "mpc", {}, None, {}, [], 0.75, 0.0, statistics.Interval(0.75, 0.6, 0.86),
                         None, (30, 40), reference, comparison)  # fmt: skip
    assert f"~{comparison.runs_needed} episodes to settle" in report._comparison_text(group)
    (row,) = csv.DictReader(io.StringIO(report.to_csv(report.Summary([group], "success", "success_rate", "max", 0))))
    assert row["runs_to_settle_unit"] == "episodes"
    returns = statistics.compare_mean(np.array([5180.0, 5240.0, 5290.0, 5330.0, 5390.0]), 5236, 50.0, "std", 50)
    assert returns.runs_needed
    on_returns = reference.model_copy(update={"metric": "episode_return"})
    group = group._replace(successes=None, comparison=returns, reference=on_returns)
    assert f"~{returns.runs_needed} runs to settle" in report._comparison_text(group)
    (row,) = csv.DictReader(io.StringIO(report.to_csv(report.Summary([group], "episode_return", "r", "max", 0))))
    assert row["runs_to_settle_unit"] == "runs"
    for metric in ("policy_success", "eval_success", "frozen_success", "success"):
        assert report._number(2 / 3, metric) == "0.67"
    assert report._number(2 / 3, "episode_return") == "0.6667"


def test_one_success_flag_per_run_gets_no_interquartile_mean():
    flags = [report_run("icem", value, "success_rate") for value in (1, 1, 0, 1, 0, 1)]
    (group,) = report.summarize(flags, "success", references=[]).groups
    assert group.iqm is None and group.successes == (4, 6)
    rates = [report_run("icem", value, "success_rate") for value in (0.8, 0.9, 0.6, 1.0, 0.7, 0.9)]
    (group,) = report.summarize(rates, "success", references=[]).groups
    assert group.iqm is not None  # rates over several episodes per run: the IQM of runs means something


def test_summary_intervals_follow_the_runs():
    runs = [report_run("icem", value) for value in (1.0, 2.0, 3.0)]
    summary = report.summarize(runs, "episode_return", references=[])
    (group,) = summary.groups
    assert group.mean == 2.0 and group.interval.low < 2.0 < group.interval.high and group.comparison is None


def test_figures_say_which_interval_their_bars_show():
    rates = report.summarize([report_run("icem", v, "success_rate") for v in (1, 0, 1)], "success", references=[])
    assert "Wilson" in report.interval_caption(rates) and "episodes" in report.interval_caption(rates)
    returns = report.summarize([report_run("icem", v) for v in (1.0, 2.0, 3.0)], "episode_return", references=[])
    assert "bootstrap" in report.interval_caption(returns) and "seeds" in report.interval_caption(returns)


@pytest.mark.parametrize(
    ("values", "starred", "note"),
    [
        ({"icem": 1.0, "cem_mpc": 1.0}, [], "no single best by success: 2 configurations tie at 1.00"),
        ({"icem": 1.0, "cem_mpc": 0.5}, ["icem"], "* best by success (max)"),
    ],
)
def test_only_a_unique_best_configuration_is_starred(values, starred, note):
    runs = [report_run(algorithm, value, "success_rate") for algorithm, value in values.items()]
    table = report.format_table(report.summarize(runs, "success", references=[]))
    rows = [line for line in table.splitlines() if line.startswith("point_reach")]
    assert [row.split()[1] for row in rows if " *" in row] == starred
    assert note in table


def report_run(algorithm: str, value: float, key: str = "mean_return"):
    from orchestrator.tracking import TrialRun

    params = {"method": "mpc", "task": "point_reach", "seed": "0", "planner.algorithm": algorithm}
    return TrialRun("id", "key", FINISHED, "name", params, {"algorithm": algorithm, "budget": "50"}, {key: value})


@pytest.mark.parametrize(
    ("switched", "compared"),
    [
        ({}, True),  # the full algorithm, every switch as its defaults
        ({"planner.keep_elites": "False"}, False),  # iCEM with an improvement removed (Fig. 7)
        ({"planner.noise_beta": "0.0"}, False),  # white noise instead of the task's beta
        ({"planner.noise_release": "1.1"}, True),  # not a switch of the algorithm
    ],
)
def test_ablations_are_not_compared_with_the_full_algorithms_published_figure(tmp_path, switched, compared):
    from workers.planning.config import PlannerConfig
    from workers.tasks import make_task

    full = PlannerConfig(algorithm="icem").resolved(make_task("point_reach").colored_noise_beta)
    run = report_run("icem", -4.0)
    run.params.update({f"planner.{name}": str(getattr(full, name)) for name in ("keep_elites", "noise_beta")})
    run.params.update({"planner.budget": "50"} | switched)
    (tmp_path / "paper.yaml").write_text(REFERENCE)
    references = load_references(tmp_path / "paper.yaml")
    (group,) = report.summarize([run, run], "episode_return", references=references).groups
    assert (group.reference is not None) == compared


def test_a_seed_rerun_under_the_current_plan_replaces_its_stale_run():
    """A resumed sweep re-ran seed 0 under a new key; seed 1 has only its earlier run."""
    from orchestrator.tracking import TrialRun

    def run(key: str, seed: int, value: float) -> TrialRun:
        params = {"method": "mpc", "task": "point_reach", "seed": str(seed), "planner.algorithm": "icem"}
        return TrialRun(key, key, FINISHED, key, params, {"algorithm": "icem", "budget": "50"}, {"mean_return": value})

    runs = [run("stale0", 0, 1.0), run("new0", 0, 3.0), run("old1", 1, 5.0)]
    (group,) = report.summarize(runs, "episode_return", planned={"new0", "new1"}).groups
    assert sorted(t.trial_key for t in group.trials) == ["new0", "old1"] and group.mean == 4.0
    (everything,) = report.summarize(runs, "episode_return").groups
    assert everything.n == 3


def test_a_missing_reference_file_is_a_located_error(tmp_path):
    sweep = tmp_path / "s.yaml"
    sweep.write_text("name: s\ntask: point_reach\nreference: nowhere.yaml\n")
    with pytest.raises(SweepError) as error:
        load_sweep(sweep)
    (problem,) = error.value.problems
    assert (problem.line, problem.path) == (3, "reference") and "not found" in problem.message


def test_a_reference_entry_without_a_source_is_refused_where_it_is(tmp_path):
    (tmp_path / "paper.yaml").write_text("entries:\n  - {task: point_reach, metric: success, value: 0.5}\n")
    sweep = tmp_path / "s.yaml"
    sweep.write_text("name: s\ntask: point_reach\nreference: paper.yaml\n")
    result = cli("validate", str(sweep), cwd=tmp_path)
    assert result.returncode == 2
    assert "paper.yaml:2: entries.0.source: required key is missing" in result.stderr


def test_a_reference_spread_without_its_kind_is_refused_where_it_is(tmp_path):
    """Read as a std where it is an sem, a test is sqrt(runs) times too lenient: the kind is asked for."""
    (tmp_path / "paper.yaml").write_text(
        "entries:\n  - {task: point_reach, metric: episode_return, value: 5, spread: 1, runs: 9, source: T}\n"
    )
    with pytest.raises(SweepError) as error:
        load_references(tmp_path / "paper.yaml")
    (problem,) = error.value.problems
    assert (problem.line, problem.path) == (2, "entries.0.spread_kind") and "std" in problem.message


def test_report_of_an_unknown_sweep_changes_nothing(tmp_path):
    result = cli("report", "never_ran", cwd=tmp_path)
    assert result.returncode == 1 and "has not run" in result.stderr
    assert not (tmp_path / "reports").exists()
    assert not (tmp_path / "mlflow.db").exists()  # nor an empty store
    status = cli("status", "never_ran", cwd=tmp_path)
    assert status.returncode == 1 and "has not run" in status.stderr
    assert not (tmp_path / "mlflow.db").exists()


def test_reference_values_match_as_numbers_and_null():
    entry = Reference(task="t", match={"planner.budget": 100, "max_steps": None}, metric="m", value=1, source="s")
    assert entry.matches("t", "mpc", {"planner.budget": "100", "max_steps": "None"}, "m")
    assert not entry.matches("t", "mpc", {"planner.budget": "100", "max_steps": "50"}, "m")
    assert not entry.matches("t", "mpc", {"planner.budget": "300", "max_steps": "None"}, "m")


def test_a_report_by_name_uses_the_metric_the_sweep_file_named(tmp_path):
    """``icemlab report NAME`` (no file at hand) reads the metric from the sweep file recorded when it ran."""
    text = "name: mixed\ntask: point_reach\nmetric: {name: success, mode: max}\n"
    fabricate(tmp_path, {"icem": [1.0, 1.0, 0.0], "cem_mpc": [0.0, 0.0, 0.0]}, "success_rate", sweep_text=text)
    result = cli("report", "mixed", "--output", str(tmp_path / "out"), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    header = result.stdout.splitlines()[0]
    assert "success" in header and "episode_return" not in header
    lines = {line.split()[1]: line for line in result.stdout.splitlines() if line.startswith("point_reach")}
    assert "0.67" in lines["icem"]


def test_curves_are_drawn_against_what_the_methods_step_counts():
    from orchestrator.tracking import TrialRun
    from workers.methods.napsp import NapspProgram

    params = {"method": "napsp", "task": "point_maze", "seed": "0", "reward": "ours_her", "mode": "sync"}
    run = TrialRun("id", "key", FINISHED, "name", params, {}, {"eval_success": 0.5})
    summary = report.summarize([run], "eval_success", references=[])
    histories = {"id": {"rollouts/eval_success": [(2, 0.0), (4, 0.5)]}}
    figure = report.curves_figure(summary, histories, ["rollouts/eval_success"], NapspProgram.curve_step)
    assert figure.axes[0].get_xlabel().startswith("collected episodes")
    assert figure.axes[0].lines[0].get_xdata().tolist() == [2, 4]


def test_mbrl_report_curves_show_coverage_where_the_task_logs_it():
    """Fig. 37a (coverage against iteration) is a report curve of mbrl; a task without coverage gets no panel."""
    from orchestrator.tracking import TrialRun
    from workers.methods.mbrl import MbrlProgram

    params = {"method": "mbrl", "task": "bridge_maze", "seed": "0"}
    run = TrialRun("id", "key", FINISHED, "name", params, {}, {"final_coverage": 0.02})
    summary = report.summarize([run], "final_coverage", references=[])
    logged = {"episode_return": [(0, 1.0), (1, 3.0)], "coverage": [(0, 0.01), (1, 0.02)]}

    def panels(histories):
        figure = report.curves_figure(summary, histories, MbrlProgram.curves, MbrlProgram.curve_step)
        return [axis.get_ylabel() for axis in figure.axes]

    assert panels({"id": logged}) == ["episode_return", "coverage"]
    assert panels({"id": {"episode_return": logged["episode_return"]}}) == ["episode_return"]


def test_apex_report_curves_show_the_evaluated_final_policy_where_the_trial_evaluated_it():
    """``evaluation_episodes`` score each iteration's final policy; the report draws them beside expert and policy."""
    from orchestrator.tracking import TrialRun
    from workers.methods.apex import ApexProgram

    params = {"method": "apex", "task": "halfcheetah_running", "seed": "0"}
    run = TrialRun("id", "key", FINISHED, "name", params, {}, {"final_policy_return": 2.0})
    summary = report.summarize([run], "policy_return", references=[])
    logged = {key: [(0, 1.0), (1, 2.0)] for key in ("expert_return", "policy_return", "evaluation_return")}

    def panels(histories):
        figure = report.curves_figure(summary, histories, ApexProgram.curves, ApexProgram.curve_step)
        return [axis.get_ylabel() for axis in figure.axes]

    assert panels({"id": logged}) == ["expert_return", "policy_return", "evaluation_return"]
    assert "evaluation_return" not in panels({"id": {"expert_return": logged["expert_return"]}})


def test_noisy_fetch_drop_rates_are_drawn_against_the_aleatoric_penalty(tmp_path):
    """Fig. 19b as drawn in the thesis: one point per w_A (0 is PETS), a line per other setting, Wilson bars."""
    from orchestrator import report_mbrl
    from orchestrator.tracking import TAG_OVERRIDE, TAG_VARIANT, TrialRun

    def run(weight: float, particles: int, drops: float):
        tags = {TAG_VARIANT: f"w{weight}-{particles}", f"{TAG_OVERRIDE}ensemble.aleatoric_weight": json.dumps(weight),
                f"{TAG_OVERRIDE}ensemble.particles": json.dumps(particles)}  # fmt: skip
        params = {"method": "mpc", "task": "noisy_fetch_pick_place", "seed": "0", "episodes": "20"}
        return TrialRun(f"{weight}-{particles}", "key", FINISHED, "name", params, tags, {"mean_box_drops": drops})

    runs = [run(0.0, 4, 0.3), run(0.5, 4, 0.3), run(0.0, 16, 0.25), run(0.5, 16, 0.1)]
    for trial in runs:  # the resolved settings, as logged; the swept count is named once
        trial.params["ensemble.particles"] = trial.tags[f"{TAG_OVERRIDE}ensemble.particles"]
    summary = report.summarize(runs, "box_drops", mode="min", references=[])
    figure = report_mbrl.penalty_figure(summary)
    lines = {container.get_label(): container.lines[0] for container in figure.axes[0].containers}
    assert sorted(lines) == [f"noisy_fetch_pick_place ensemble.particles={n}" for n in (16, 4)]
    assert lines["noisy_fetch_pick_place ensemble.particles=16"].get_ydata().tolist() == pytest.approx([0.25, 0.1])
    assert lines["noisy_fetch_pick_place ensemble.particles=4"].get_xdata().tolist() == [0.0, 0.5]
    assert report_mbrl.penalty_figure(report.summarize(runs[:1], "box_drops", references=[])) is None
    assert tmp_path / "penalty.png" in report.write_files(summary, tmp_path)


def test_a_configuration_whose_runs_ran_different_settings_is_not_tested():
    """A sweep edited between sessions (max_steps 100 for a first look, then full episodes) keeps seed 0's short run
    where its new one failed: the group is shown, but not tested against Table 3 on a mixture."""
    from orchestrator.tracking import TrialRun

    params = {"method": "mpc", "task": "halfcheetah_running", "planner.algorithm": "icem", "planner.budget": "100",
              "planner.horizon": "30", "planner.sigma_init": "0.5", "planner.elites": "10"}  # fmt: skip
    runs = [
        TrialRun("a", "old", FINISHED, "n", params | {"seed": "0", "max_steps": "100"}, {}, {"mean_return": 900.0}),
        TrialRun("b", "new1", FINISHED, "n", params | {"seed": "1", "max_steps": "None"}, {}, {"mean_return": 5200.0}),
        TrialRun("c", "new2", FINISHED, "n", params | {"seed": "2", "max_steps": "None"}, {}, {"mean_return": 5300.0}),
    ]
    for order in (runs, runs[::-1]):
        (group,) = report.summarize(order, "episode_return", references=load_references(THESIS)).groups
        assert group.comparison.verdict == "untested" and "differ in max_steps" in group.comparison.test
    (same,) = report.summarize(runs[1:], "episode_return", references=load_references(THESIS)).groups
    assert same.comparison.verdict != "untested"


def test_a_configuration_whose_runs_ran_different_settings_is_neither_ranked_nor_paired():
    """Its mean is of a mixture (seed 0's short first look among full episodes): it outranks nothing, it is not
    paired with its baseline (nor is a variant with it), and the table names the setting."""
    from orchestrator.tracking import TAG_VARIANT, TrialRun

    def run(variant, seed, value, max_steps="None"):
        params = {"method": "mpc", "task": "halfcheetah_running", "seed": str(seed), "max_steps": max_steps}
        return TrialRun(f"{variant}{seed}", f"k{variant}{seed}", FINISHED, "n", params, {TAG_VARIANT: variant},
                        {"mean_return": value})  # fmt: skip

    base = [run("base", s, 5000.0 + s) for s in range(3)]
    mixed = [run("ours", 0, 9000.0, max_steps="100"), run("ours", 1, 5100.0), run("ours", 2, 5200.0)]
    summary = report.summarize(base + mixed, "episode_return", references=[], pairing=report.Pairing(("base",), ()))
    groups = {g.variant: g for g in summary.groups}
    assert groups["ours"].mixed == ("max_steps",) and groups["ours"].paired is None
    assert summary.groups[summary.best] is groups["base"]  # the mixture's mean is higher
    assert "(runs differ in max_steps)" in report.format_table(summary)
    swapped = {"base": "ours", "ours": "base"}
    flipped = [r._replace(tags={TAG_VARIANT: swapped[r.tags[TAG_VARIANT]]}) for r in base + mixed]
    summary = report.summarize(flipped, "episode_return", references=[], pairing=report.Pairing(("base",), ()))
    assert {g.variant: g for g in summary.groups}["ours"].paired is None  # its baseline is the mixed one
    clean = base + [run("ours", s, 5100.0 + s) for s in range(3)]
    summary = report.summarize(clean, "episode_return", references=[], pairing=report.Pairing(("base",), ()))
    assert {g.variant: g for g in summary.groups}["ours"].paired is not None


def test_a_setting_only_later_runs_log_does_not_make_a_configuration_mixed():
    """A setting added to the code later keeps old trials' keys only at the value they ran with, so runs that
    predate it (no such param) and runs that log it are one configuration and are tested."""
    from orchestrator.tracking import TrialRun

    params = {"method": "mpc", "task": "halfcheetah_running", "planner.algorithm": "icem", "planner.budget": "100",
              "max_steps": "None", "planner.horizon": "30", "planner.sigma_init": "0.5", "planner.elites": "10"}  # fmt: skip
    runs = [TrialRun(f"r{s}", f"k{s}", FINISHED, "n", params | {"seed": str(s)} | extra, {}, {"mean_return": v})
            for s, v, extra in [(0, 5100.0, {}), (1, 5200.0, {"planner.noise_release": "2.1"}),
                                (2, 5300.0, {"planner.noise_release": "2.1"})]]  # fmt: skip
    (group,) = report.summarize(runs, "episode_return", references=load_references(THESIS)).groups
    assert group.comparison.verdict != "untested"


def test_a_published_rate_of_one_without_runs_is_not_tested_against_per_seed_rates():
    """APEX's Door expert at Table 9's 1.0 (no run count): seeds at 0.96-1.0 are not "below" an exact 1."""
    from orchestrator.tracking import TrialRun

    params = {"method": "apex", "task": "door_sparse"}
    runs = [TrialRun(f"r{s}", f"k{s}", FINISHED, "n", params | {"seed": str(s)}, {}, {"final_expert_success": v})
            for s, v in enumerate([1.0, 0.96, 0.98, 0.97, 0.99])]  # fmt: skip
    reference = Reference(task="door_sparse", method="apex", metric="expert_success", value=1.0, source="t")
    (group,) = report.summarize(runs, "expert_success", references=[reference]).groups
    assert group.comparison.verdict == "untested" and "without its run count" in group.comparison.test


def test_a_variant_with_seeds_without_a_value_is_not_paired_with_its_baseline():
    """Seeds that never crossed the threshold would drop out of the pairs: the survivors' difference is no test."""
    from orchestrator.tracking import TAG_VARIANT, TrialRun

    def run(variant, seed, value):
        params = {"method": "napsp", "task": "point_maze", "seed": str(seed)}
        return TrialRun(f"{variant}{seed}", f"k{variant}{seed}", FINISHED, "n", params, {TAG_VARIANT: variant},
                        {"episodes_to_threshold": value})  # fmt: skip

    runs = [run("base", s, 500.0 + s) for s in range(4)] + [run("ours", s, v) for s, v in
                                                            enumerate([300.0, 310.0, math.nan, math.nan])]  # fmt: skip
    summary = report.summarize(runs, "episodes_to_threshold", "min", [], pairing=report.Pairing(("base",), ()))
    groups = {g.variant: g for g in summary.groups}
    assert groups["ours"].paired is None
    complete = [r for r in runs if r.run_id not in ("ours2", "ours3")] + [run("ours", 2, 320.0), run("ours", 3, 330.0)]
    summary = report.summarize(complete, "episodes_to_threshold", "min", [], pairing=report.Pairing(("base",), ()))
    assert {g.variant: g for g in summary.groups}["ours"].paired is not None


def test_the_penalty_figure_draws_a_line_per_planner_budget():
    """The budget is a label, not a swept setting: two budgets' groups on one line would zigzag between them."""
    from orchestrator import report_mbrl
    from orchestrator.tracking import TAG_OVERRIDE, TrialRun

    def run(weight: float, budget: int, drops: float):
        tags = {"algorithm": "icem", "budget": str(budget), f"{TAG_OVERRIDE}planner.budget": json.dumps(budget),
                f"{TAG_OVERRIDE}ensemble.aleatoric_weight": json.dumps(weight)}  # fmt: skip
        params = {"method": "mpc", "task": "noisy_fetch_pick_place", "seed": "0", "episodes": "20",
                  "planner.algorithm": "icem", "planner.budget": str(budget)}  # fmt: skip
        return TrialRun(f"{weight}-{budget}", "key", FINISHED, "name", params, tags, {"mean_box_drops": drops})

    runs = [run(0.0, 50, 0.3), run(0.5, 50, 0.2), run(0.0, 100, 0.25), run(0.5, 100, 0.1)]
    figure = report_mbrl.penalty_figure(report.summarize(runs, "box_drops", mode="min", references=[]))
    lines = {container.get_label(): container.lines[0] for container in figure.axes[0].containers}
    assert sorted(lines) == ["noisy_fetch_pick_place icem b100", "noisy_fetch_pick_place icem b50"]
    assert lines["noisy_fetch_pick_place icem b50"].get_xdata().tolist() == [0.0, 0.5]


@pytest.mark.parametrize(
    "rates, bar",
    [
        ([0.56], (0.371, 0.733)),  # 14 of 25: no second seed gives a spread, but the rate has one
        ([0.56, 0.56], (0.423, 0.688)),  # two seeds that agree: a zero sem, but 28 of 50 still have a spread
        ([0.0, 1.0], (0.0, 1.0)),  # seeds far apart: the sem (0.5) is wider than the 25 of 50's Wilson interval
    ],
)
def test_a_frozen_rows_bar_is_at_least_the_wilson_interval_of_its_pooled_episodes(rates, bar):
    """The bar of a frozen row's rate is the sem over its seeds, widened to at least the Wilson 95% interval of
    all their episodes (25 each)."""
    from orchestrator import report_mbrl
    from orchestrator.tracking import TrialRun

    def trial(seed, rate):
        metrics = {"frozen/razer_wA_0.1/success_rate": rate, "frozen/razer_wA_0.1/episodes": 25.0,
                   "frozen/razer_wA_0.1/aleatoric_weight": 0.1}  # fmt: skip
        return TrialRun(f"r{seed}", f"k{seed}", FINISHED, "n", {"method": "mbrl", "seed": str(seed)}, {}, metrics)

    runs = [trial(seed, rate) for seed, rate in enumerate(rates)]
    (point,) = report_mbrl.frozen_points(report.summarize(runs, "success", references=[]).groups[0].trials)
    mean = sum(rates) / len(rates)
    below, above = report_mbrl._rate_error(point, "success_rate")
    assert (mean - below, mean + above) == (pytest.approx(bar[0], abs=0.002), pytest.approx(bar[1], abs=0.002))


def test_noisy_fetch_drop_rates_are_drawn_against_the_noise_one_line_per_penalty(tmp_path):
    """Fig. 19b as its caption reads: a fixed w_A per line, the noise on the x-axis. Rows that ran the default
    noise (no swept setting says it) are placed by their logged settings."""
    from orchestrator import report_mbrl
    from orchestrator.tracking import TAG_OVERRIDE, TAG_VARIANT, TrialRun

    def run(weight: float, noise: float | None, drops: float):
        tags = {TAG_VARIANT: f"w{weight}", f"{TAG_OVERRIDE}ensemble.aleatoric_weight": json.dumps(weight)}
        if noise is not None:
            tags[f"{TAG_OVERRIDE}task_options.noise_std"] = json.dumps(noise)
        params = {"method": "mpc", "task": "noisy_fetch_pick_place", "seed": "0", "episodes": "20",
                  "ensemble.particles": "16", "task_options.noise_std": str(noise or 1.0),
                  "task_options.noise_mean": "0.0"}  # fmt: skip
        return TrialRun(f"{weight}-{noise}", "key", FINISHED, "name", params, tags, {"mean_box_drops": drops})

    runs = [run(0.0, None, 0.25), run(0.5, None, 0.05), run(0.0, 2.0, 0.6), run(0.5, 2.0, 0.15)]
    summary = report.summarize(runs, "box_drops", mode="min", references=[])
    figure = report_mbrl.noise_figure(summary)
    lines = {container.get_label(): container.lines[0] for container in figure.axes[0].containers}
    assert sorted(lines) == ["PETS ensemble.particles=16", "RAZER w_A=0.5 ensemble.particles=16"]
    assert lines["PETS ensemble.particles=16"].get_xdata().tolist() == [1.0, 2.0]
    assert lines["RAZER w_A=0.5 ensemble.particles=16"].get_ydata().tolist() == pytest.approx([0.05, 0.15])
    assert figure.axes[0].get_xlabel() == "noise_std"
    same_noise = report.summarize(runs[:2], "box_drops", mode="min", references=[])
    assert report_mbrl.noise_figure(same_noise) is None  # nothing to draw against
    assert tmp_path / "noise.png" in report.write_files(summary, tmp_path)


def test_the_penalty_figure_names_a_particle_count_that_the_sweep_fixed_in_its_base():
    """A sweep that sets the count in its base (razer_noisy_fetch_particles.yaml) has no swept setting that says
    it, yet its drop rates depend on it; the logged settings do."""
    from orchestrator import report_mbrl
    from orchestrator.tracking import TAG_OVERRIDE, TAG_VARIANT, TrialRun

    def run(weight: float, drops: float):
        tags = {TAG_VARIANT: f"w{weight}", f"{TAG_OVERRIDE}ensemble.aleatoric_weight": json.dumps(weight)}
        params = {"method": "mpc", "task": "noisy_fetch_pick_place", "seed": "0", "episodes": "20",
                  "ensemble.particles": "16"}  # fmt: skip
        return TrialRun(f"{weight}", "key", FINISHED, "name", params, tags, {"mean_box_drops": drops})

    summary = report.summarize([run(0.0, 0.25), run(0.5, 0.3)], "box_drops", mode="min", references=[])
    labels = [container.get_label() for container in report_mbrl.penalty_figure(summary).axes[0].containers]
    assert labels == ["noisy_fetch_pick_place ensemble.particles=16"]


def test_a_paired_success_comparison_counts_only_the_seeds_where_the_variants_disagree():
    variant = np.array([1, 0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 0])
    baseline = np.array([1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 1, 0])
    test = statistics.compare_paired(variant, baseline)
    # 1 seed gained, 8 lost: the exact binomial test of 1 in 9 at one half, two-sided: 2 * 10 / 512.
    assert test.test == "McNemar exact" and test.discordant == (1, 8) and test.pairs == 12
    assert test.p_value == pytest.approx(20 / 512) and test.difference == pytest.approx(-7 / 12)


def test_paired_returns_get_the_paired_t_test():
    variant, baseline = np.array([10.0, 12.0, 15.0, 11.0]), np.array([9.0, 10.0, 14.0, 8.0])
    test = statistics.compare_paired(variant, baseline)
    from scipy import stats

    assert test.test == "paired t-test" and test.discordant is None
    assert test.p_value == pytest.approx(stats.ttest_rel(variant, baseline).pvalue) and test.difference == 1.75


def variant_run(variant: str, algorithm: str, seed: int, value: float, key: str = "mean_return"):
    from orchestrator.tracking import TAG_VARIANT, TrialRun

    params = {"method": "mpc", "task": "point_reach", "seed": str(seed), "planner.algorithm": algorithm}
    tags = {"algorithm": algorithm, "budget": "50", TAG_VARIANT: variant}
    return TrialRun(f"{variant}{seed}", f"{variant}{seed}", FINISHED, variant, params, tags, {key: value})


def test_variants_meet_the_baseline_of_their_own_algorithm_on_shared_seeds():
    runs = [
        *(variant_run("icem", "icem", s, v) for s, v in enumerate([100.0, 200.0, 300.0])),
        *(variant_run("no-elites", "icem", s, v) for s, v in enumerate([90.0, 170.0, 290.0, 1e6])),  # seed 3 unpaired
        *(variant_run("cem_mpc", "cem_mpc", s, v) for s, v in enumerate([10.0, 20.0])),
        *(variant_run("cem_mpc+clip", "cem_mpc", s, v) for s, v in enumerate([15.0, 30.0])),
    ]
    summary = report.summarize(runs, "episode_return", pairing=report.Pairing(("icem", "cem_mpc")))
    paired = {g.variant: g.paired for g in summary.groups}
    assert paired["icem"] is None and paired["cem_mpc"] is None
    assert paired["no-elites"].baseline == "icem" and paired["no-elites"].test.pairs == 3
    assert paired["no-elites"].test.difference == pytest.approx(-50 / 3)
    assert paired["cem_mpc+clip"].baseline == "cem_mpc" and paired["cem_mpc+clip"].test.difference == 7.5
    table = report.format_table(summary)
    assert "-16.67 vs icem (paired t-test, 3 seeds, p=" in table and "+7.5 vs cem_mpc" in table
    assert report.format_table(report.summarize(runs, "episode_return")).count("vs icem") == 0


def test_variants_meet_their_baseline_episode_by_episode_where_both_logged_episodes():
    """One seed of 8 episodes per variant, starting alike: McNemar over the episodes, not one pair of seeds."""
    runs = [
        variant_run("pets", "icem", 0, 0.5, key="mean_box_drops"),
        variant_run("razer", "icem", 0, 0.125, key="mean_box_drops"),
        variant_run("unlogged", "icem", 0, 0.0, key="mean_box_drops"),
    ]
    drops = {"pets0": [1, 0, 1, 1, 0, 0, 1, 0], "razer0": [0, 0, 0, 1, 0, 0, 0, 0]}
    episodes = {run_id: {"box_drops": list(enumerate(map(float, flags)))} for run_id, flags in drops.items()}
    summary = report.summarize(runs, "box_drops", "min", pairing=report.Pairing(("pets",)), episodes=episodes)
    paired = {g.variant: g.paired.test for g in summary.groups if g.paired}
    # Episodes 0, 2 and 6 dropped under PETS alone, episode 3 under both: better in 3 (fewer drops), worse in 0.
    assert paired["razer"].unit == "episode" and paired["razer"].pairs == 8
    assert paired["razer"].discordant == (0, 3) and paired["razer"].p_value == pytest.approx(0.25)
    assert paired["razer"].difference == pytest.approx(-3 / 8)
    # A run without per-episode values falls back to its seed.
    assert paired["unlogged"].unit == "seed" and paired["unlogged"].pairs == 1
    table = report.format_table(summary)
    assert "-0.38 vs pets (McNemar exact, 3 better : 0 worse of 8 episodes, p=0.25)" in table
    assert "vs pets (too few pairs to test, 1 seed)" in table


def store_paired_success_sweep(tmp_path, name: str, flags: dict[str, dict[int, list[int]]], per_episode: bool):
    """A finished point_reach sweep with baseline ``full``: variant -> seed -> success flag of each episode, logged
    per episode (as mpc logs them) when ``per_episode``; the report reads it back."""
    from orchestrator.tracking import TAG_VARIANT

    text = f"name: {name}\ntask: point_reach\nmetric: {{name: success}}\nbaseline: full\n"
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep(name, name, "hash", text, {}, "dev")
    for variant, by_seed in flags.items():
        for seed, episodes in by_seed.items():
            params = {"method": "mpc", "task": "point_reach", "seed": seed, "planner.algorithm": "icem",
                      "planner.budget": 50, "episodes": len(episodes)}  # fmt: skip
            tags = {"method": "mpc", "task": "point_reach", "algorithm": "icem", "budget": "50", TAG_VARIANT: variant}
            run_id = tracker.start_trial(parent, f"{variant}{seed}", f"{variant}/{seed}", params, tags)
            for episode, flag in enumerate(episodes if per_episode else []):
                tracker.log_round(run_id, episode, episode, {"success": float(flag)}, {}, 0)
            tracker.end_trial(run_id, FINISHED, {"success_rate": float(np.mean(episodes))})
    tracker.end_sweep(parent, FINISHED, {})
    result = cli("report", name, "--output", str(tmp_path / "out"), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    rows = {row["variant"]: row for row in csv.DictReader(io.StringIO((tmp_path / "out" / "summary.csv").read_text()))}
    return result.stdout, rows


def store_rerun_seed(tmp_path, text: str, name: str) -> None:
    """A finished sweep (recorded ``text``) whose seed 0 ran twice: under a key the code no longer plans (-9), and
    under the current plan's key (-4), as a resume after a change of the trial's resolution leaves it."""
    sweep_file = tmp_path / f"{name}.yaml"
    sweep_file.write_text(text)
    (trial,) = load_sweep(sweep_file).trials
    sweep_file.unlink()  # reported by name: only the store knows the sweep
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep(name, name, "hash", text, {}, "dev")
    for key, value in (("stale-key", -9.0), (trial.key, -4.0)):
        params = {"method": "mpc", "task": "point_reach", "seed": 0, "planner.algorithm": "icem", "planner.budget": 100}
        tags = {"method": "mpc", "task": "point_reach", "algorithm": "icem", "budget": "100"}
        run_id = tracker.start_trial(parent, key, key, params, tags)
        tracker.end_trial(run_id, FINISHED, {"mean_return": value})
    tracker.end_sweep(parent, FINISHED, {})


def test_a_report_by_name_counts_each_seed_once_as_the_recorded_sweep_plans_it(tmp_path):
    """``icemlab report NAME`` plans the recorded sweep again, as ``report FILE`` and the sweep's own summary do:
    a seed run again under a new key counts once, not twice."""
    store_rerun_seed(tmp_path, "name: byname\ntask: point_reach\nseeds: [0]\n", "byname")
    result = cli("report", "byname", "--output", str(tmp_path / "out"), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (row,) = csv.DictReader(io.StringIO((tmp_path / "out" / "summary.csv").read_text()))
    assert row["trials"] == "1" and float(row["episode_return_mean"]) == -4.0


def test_the_table_says_how_many_planned_trials_are_not_in_it():
    """Two of three planned seeds finished: the third (failed, or not run) is named, not silently left out."""
    runs = [report_run("icem", value) for value in (1.0, 2.0)]
    planned = {run.trial_key for run in runs} | {"failed-seed"}
    table = report.format_table(report.summarize(runs, "episode_return", references=[], planned=planned))
    assert "1 planned trial(s) have no finished run" in table
    assert "planned trial" not in report.format_table(report.summarize(runs, "episode_return", references=[]))


def test_a_report_by_name_says_when_the_sweeps_own_reference_cannot_be_read(tmp_path):
    (tmp_path / "paper.yaml").write_text(REFERENCE)
    store_rerun_seed(tmp_path, "name: own_ref\ntask: point_reach\nseeds: [0]\nreference: paper.yaml\n", "own_ref")
    result = cli("report", "own_ref", "--output", str(tmp_path / "out"), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "compared with paper.yaml, which a report by name cannot read" in result.stderr


def test_a_report_by_name_goes_on_when_the_recorded_sweep_fails_to_plan_for_any_reason(monkeypatch, capsys):
    """Not only a refused file or an unreadable reference: whatever loading the recorded sweep raises (a task that
    no longer builds), the report by name falls back on what the file names, and says why."""
    from orchestrator import cli as cli_module
    from orchestrator import sweep as sweep_module

    def fails(path):
        raise RuntimeError("task 'point_reach' no longer builds\nsecond line")

    monkeypatch.setattr(sweep_module, "load_sweep", fails)
    store = type("Store", (), {"recorded_sweep": lambda self, run_id: "name: x\ntask: point_reach\n"})()
    assert cli_module._reloaded_sweep(store, "run") is None
    err = capsys.readouterr().err
    assert "does not load here (RuntimeError: task 'point_reach' no longer builds)" in err


def test_a_report_by_name_pairs_variants_with_the_recorded_baseline(tmp_path):
    """``icemlab report NAME`` reads the baseline from the sweep file recorded when it ran."""
    flags = {"full": [1, 1, 1, 0], "ablated": [0, 1, 0, 0]}
    by_seed = {variant: {seed: [flag] for seed, flag in enumerate(values)} for variant, values in flags.items()}
    table, rows = store_paired_success_sweep(tmp_path, "paired", by_seed, per_episode=False)
    assert "-0.50 vs full (McNemar exact, 0 better : 2 worse of 4 seeds, p=0.5)" in table
    assert rows["ablated"]["paired_baseline"] == "full" and rows["ablated"]["paired_test"] == "McNemar exact"
    assert rows["ablated"]["paired_unit"] == "seed" and rows["full"]["paired_baseline"] == ""


def test_report_pairs_mpc_episodes_that_start_alike(tmp_path):
    """``icemlab report`` reads the per-episode metric of an mpc sweep with a baseline and pairs episodes."""
    flags = {"full": {0: [1, 1, 1, 0, 1, 1]}, "ablated": {0: [0, 1, 0, 0, 0, 0]}}
    table, rows = store_paired_success_sweep(tmp_path, "episodes", flags, per_episode=True)
    assert "-0.67 vs full (McNemar exact, 0 better : 4 worse of 6 episodes, p=0.12)" in table
    assert rows["ablated"]["paired_unit"] == "episode" and rows["ablated"]["paired_pairs"] == "6"


def test_a_variants_name_stands_for_its_overrides_and_a_grid_over_it_stays_in_the_name():
    import json

    from orchestrator.tracking import TAG_OVERRIDE

    runs = []
    for release in ("2.1", "1.1"):
        for horizon in (15, 30):
            run = variant_run(f"colorednoise-{release}", "icem", 0, float(horizon))
            overrides = {"planner.noise_release": release, "planner.horizon": horizon}
            run.tags.update({TAG_OVERRIDE + k: json.dumps(v) for k, v in overrides.items()})
            runs.append(run._replace(run_id=f"{release}-{horizon}", trial_key=f"{release}-{horizon}"))
    summary = report.summarize(runs, "episode_return")
    names = sorted(g.name() for g in summary.groups)
    assert names == [
        f"icem b50 colorednoise-{release} planner.horizon={h}" for release in ("1.1", "2.1") for h in (15, 30)
    ]
    assert all(g.setting["planner.noise_release"] in ("1.1", "2.1") for g in summary.groups)  # still in the CSV
    rows = list(csv.DictReader(io.StringIO(report.to_csv(summary))))
    assert sorted(row["planner.noise_release"] for row in rows) == ["1.1", "1.1", "2.1", "2.1"]


def test_status_shows_each_trials_sweep_metric_and_a_running_trials_figure_so_far(tmp_path):
    tracker = Tracker(default_tracking_uri(tmp_path))
    text = "name: drops\ntask: noisy_fetch_pick_place\nmetric: {name: box_drops, mode: min}\n"
    parent = tracker.start_sweep("drops", "drops", "hash", text, {}, "dev", planned_trials=2)
    params = {"method": "mpc", "task": "noisy_fetch_pick_place", "seed": 0, "episodes": 4}
    done = tracker.start_trial(parent, "done", "done", params, {"method": "mpc"})
    tracker.end_trial(done, FINISHED, {"mean_box_drops": 0.25, "mean_return": -12.0})
    running = tracker.start_trial(parent, "running", "running", params, {"method": "mpc"})
    for episode, drops in enumerate([1.0, 0.0, 1.0]):  # three of four episodes so far
        tracker.log_round(running, episode, episode, {"box_drops": drops}, {}, 0)
    tracker.log_round(running, 2, 2, {"box_drops": 1.0}, {}, 0)  # a round logged again after a restart
    lines = {line.split()[0]: line for line in cli("status", "drops", cwd=tmp_path).stdout.splitlines()[1:]}
    assert lines["done"].endswith("box_drops 0.25")  # the summary, not the return
    assert lines["running"].endswith("box_drops 0.667 so far (mean of the 3 logged)")


def test_status_tells_a_running_trials_rounds_and_time_to_go_from_its_recent_rounds(tmp_path):
    from orchestrator.tracking import TAG_PLANNED_ROUNDS

    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("long", "long", "hash", "name: long\n", {}, "dev", planned_trials=1)
    run_id = tracker.start_trial(parent, "slow", "slow", {"method": "mpc", "seed": 0}, {"method": "mpc"})
    tracker.set_tags(run_id, {TAG_PLANNED_ROUNDS: "10"})
    for index, seconds in enumerate([600.0, 60.0, 60.0, 120.0, 120.0, 240.0]):  # the first round is left out
        tracker.log_round(run_id, index, index, {}, {}, 0, seconds=seconds)
    line = cli("status", "long", cwd=tmp_path).stdout.splitlines()[1]
    # 4 rounds to go at the mean of the last 5 (120 s): 8 minutes.
    assert "rounds    6/10" in line and line.endswith("about 8 min 00 s to go (4 rounds at the pace of its last 5)")
    tracker.end_sweep(parent, "KILLED", {})
    assert "to go" not in cli("status", "long", cwd=tmp_path).stdout  # a stopped sweep is not on its way


def test_status_weighs_the_rounds_to_go_by_their_recorded_work(tmp_path):
    """An MBRL trial's three frozen rows of 13 episodes each after 40 one-episode iterations of a minute: about
    39 minutes to go, not the 3 minutes of three rounds at the iterations' pace."""
    from orchestrator.tracking import TAG_PLANNED_ROUNDS, TAG_ROUND_WORK, encode_round_work

    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("loop", "loop", "hash", "name: loop\n", {}, "dev", planned_trials=1)
    run_id = tracker.start_trial(parent, "mbrl", "mbrl", {"method": "mbrl", "seed": 0}, {"method": "mbrl"})
    work = [0.0] + [1.0] * 40 + [13.0] * 3
    tracker.set_tags(run_id, {TAG_PLANNED_ROUNDS: "44", TAG_ROUND_WORK: encode_round_work(work)})
    for index in range(41):
        tracker.log_round(run_id, index, index, {}, {}, 0, seconds=300.0 if index == 0 else 60.0)
    young = tracker.start_trial(parent, "young", "young", {"method": "mbrl", "seed": 1}, {"method": "mbrl"})
    tracker.set_tags(young, {TAG_PLANNED_ROUNDS: "44", TAG_ROUND_WORK: encode_round_work(work)})
    for index, seconds in enumerate([600.0, 60.0, 60.0]):  # round 0's random episodes say nothing of the pace
        tracker.log_round(young, index, index, {}, {}, 0, seconds=seconds)
    lines = cli("status", "loop", cwd=tmp_path).stdout.splitlines()[1:]
    line = next(text for text in lines if "#" not in text and " mbrl " in text and "41/44" in text)
    assert line.endswith("about 39 min 00 s to go (3 rounds at the pace of its last 5)")
    young_line = next(text for text in lines if " young " in text)
    # 38 iterations and 3 rows of 13 to go at 60 s each: 77 minutes.
    assert young_line.endswith("about 1 h 17 min to go (41 rounds at the pace of its last 2)")


@pytest.mark.parametrize(
    "work, code",
    [([1.0] * 5, "1*5"), ([0.0, 1.0, 1.0, 13.0, 13.0, 2.5], "0,1*2,13*2,2.5"), ([7.0], "7")],
)
def test_round_work_travels_in_a_short_tag(work, code):
    from orchestrator.tracking import decode_round_work, encode_round_work

    assert encode_round_work(work) == code and decode_round_work(code) == work
    assert decode_round_work("") is None and decode_round_work("1*x") is None


def test_report_of_a_sweep_without_a_finished_trial_points_to_status(tmp_path):
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("young", "young", "hash", "name: young\n", {}, "dev", planned_trials=2)
    tracker.start_trial(parent, "running", "running", {"method": "mpc", "seed": 0}, {"method": "mpc"})
    result = cli("report", "young", cwd=tmp_path)
    assert result.returncode == 1 and "no finished trial yet (1 running" in result.stderr
    assert "icemlab status young" in result.stderr
    assert not (tmp_path / "reports").exists()  # no empty table written


def test_status_tells_a_running_sweeps_time_to_go_at_its_sessions_pace(tmp_path):
    """Four trials that started together finish seconds apart ten minutes into a session: the pace is four per ten
    minutes, not one a second; a trial finished in an earlier session counts as done but not for the pace, one
    that failed then is being retried (to go), and with the sweep file only its trials count."""
    import time

    from orchestrator.tracking import TAG_SESSION_STARTED

    tracker = Tracker(default_tracking_uri(tmp_path))
    sweep = Path(__file__).resolve().parents[1] / "sweeps" / "quickstart.yaml"
    keys = [trial.key for trial in load_sweep(sweep).trials]
    parent = tracker.start_sweep("quickstart", "quickstart", "hash", sweep.read_text(), {}, "dev", planned_trials=4)
    began = time.time() - 600
    tracker.client.set_tag(parent, TAG_SESSION_STARTED, f"{began:.3f}")

    def trial(key, status, ended):
        run_id = tracker.start_trial(parent, key, key, {"seed": 0}, {})
        tracker.client.set_terminated(run_id, status=status, end_time=int(ended * 1000))

    for index in range(4):  # stale keys of an earlier plan, finished seconds apart in this session
        trial(f"stale{index}", FINISHED, began + 590 + index)
    trial(keys[0], FINISHED, began - 3600)  # finished in an earlier session
    trial(keys[1], FAILED, began - 60)  # failed in an earlier session: retried now
    trial(keys[2], FINISHED, began + 300)
    everything = cli("status", cwd=tmp_path).stdout
    assert "finished 6 of 4" in everything  # without the file nothing says which runs are stale
    asked = time.time()
    status = cli("status", str(sweep), cwd=tmp_path).stdout
    answered = time.time()
    assert "finished 2 of 4  running 0  failed 1  killed 0" in status
    assert "stale" not in status and "and 4 runs of trials this file no longer defines" in status
    # 2 to go (the retried failure and the last trial) at 1 trial per session so far (600 s and the time the
    # commands took): twice the session's length.
    pace = re.search(
        r"about (\d+) min (\d+) s to go at this session's pace \(1 finished in (\d+) min (\d+) s\)", status
    )
    assert pace, status
    to_go, session = (60 * int(pace[1]) + int(pace[2])), (60 * int(pace[3]) + int(pace[4]))
    assert asked - began <= session <= answered - began + 1 and 2 * session - 2 <= to_go <= 2 * session + 1
    tracker.end_sweep(parent, "KILLED", {})
    assert "to go" not in cli("status", str(sweep), cwd=tmp_path).stdout  # a stopped sweep is not on its way


def test_a_report_copies_each_trials_chosen_plots_into_a_folder_named_after_its_run(tmp_path):
    """The method picks the files (MbrlProgram.report_plots); a method that picks none gets no folder."""
    from orchestrator.tracking import TrialRun

    class Store:
        files = {"mbrl": ["plots/visited_states.png", "plots/uncertainty_v003.png", "plots/uncertainty_v011.png"]}

        def list_files(self, run_id, path):
            assert path == "plots"
            return self.files.get(run_id, ["plots/anything.png"])

        def download(self, run_id, path, directory):  # as MLflow: the file under the directory, its path returned
            target = Path(directory) / path
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(f"{run_id}:{path}")
            return target

    params = {"method": "mbrl", "task": "bridge_maze", "seed": "0"}
    mbrl = report.result_from_run(TrialRun("mbrl", "k1", FINISHED, "bridge_maze/pets/s0#ab12", params, {}, {}))
    mpc = report.result_from_run(report_run("icem", 1.0))
    names = {"mbrl": "bridge_maze/pets/s0#ab12", "id": "point_reach/icem/s0#cd34"}
    copied = report.copy_trial_plots(Store(), [mbrl, mpc], names, tmp_path)
    folder = tmp_path / "trials" / "bridge_maze_pets_s0_ab12"
    assert sorted(copied) == [folder / "uncertainty_v011.png", folder / "visited_states.png"]
    assert (folder / "uncertainty_v011.png").read_text() == "mbrl:plots/uncertainty_v011.png"
    assert sorted(p.name for p in (tmp_path / "trials").iterdir()) == ["bridge_maze_pets_s0_ab12"]
