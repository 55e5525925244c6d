"""How sure a result is, and whether it differs from a published one.

scipy.stats does the estimation and the tests, statsmodels the power
analysis of means; the power of a rate test is the closed-form normal
approximation (Cohen's h), which statsmodels' solver fails on for very large
effects.

* Intervals (95%): for returns a bootstrap of the runs' mean (BCa); for
  success rates the Wilson score interval of the successes; for five runs or
  more also the interquartile mean (IQM, the mean of the middle 50% of runs,
  as rliable defines it) with a bootstrap interval. rliable itself does not
  import beside this stack (its ``arch`` dependency fails with pandas 3), and
  with one task per configuration its stratified bootstrap is the plain
  bootstrap of runs used here.
* Verdicts against a reference: an exact binomial test of the measured
  successes against a published success rate; for returns Welch's t-test
  against the published mean, spread and run count (a one-sample t-test when
  the reference gives no spread). Tests are one-sided in the direction of the
  observed difference, at the 5% level: ``below`` or ``above`` when the
  difference is significant, ``consistent`` when it is not.
* Variants against a baseline on the same seeds (a sweep's ``baseline``):
  McNemar's exact test for one success flag per seed, the paired t-test
  otherwise; two-sided.
* Runs to settle: for a comparison that is not significant, how many runs
  (episodes, for rates) a one-sided test at 5% needs to detect the observed
  difference with 80% power.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats

LEVEL = 0.95
ALPHA = 0.05
POWER = 0.80
IQM_MIN_RUNS = 5
BOOTSTRAP_RESAMPLES = 2000


class Interval(NamedTuple):
    """A point estimate with its 95% interval (nan bounds when there is too little data)."""

    estimate: float
    low: float
    high: float


def error_bars(intervals: Sequence[Interval]) -> np.ndarray:
    """(2, n) distances from each estimate down and up to its interval, for matplotlib's yerr/xerr (0 where
    there is no interval)."""
    low = [i.estimate - i.low if math.isfinite(i.low) else 0.0 for i in intervals]
    high = [i.high - i.estimate if math.isfinite(i.high) else 0.0 for i in intervals]
    return np.array([low, high], dtype=float).reshape(2, len(intervals))


class Comparison(NamedTuple):
    """A measured figure against a published one."""

    verdict: str
    """consistent, below or above."""
    test: str
    """The test that decided it."""
    p_value: float
    """One-sided, in the direction of the observed difference."""
    runs_needed: int | None
    """Runs (episodes for rates) that would detect the observed difference at 5% with 80% power; None once
    the difference is significant or when there is none."""


MIN_BOOTSTRAP_RUNS = 3
"""Below this many runs a bootstrap interval says nothing; none is given."""


def mean_interval(values: np.ndarray) -> Interval:
    """The runs' mean with a 95% bootstrap (BCa) interval, from three runs on."""
    values = np.asarray(values, dtype=float)
    if len(values) == 0:
        return Interval(math.nan, math.nan, math.nan)
    if len(values) < MIN_BOOTSTRAP_RUNS or np.ptp(values) == 0:
        return Interval(float(values.mean()), math.nan, math.nan)
    result = stats.bootstrap((values,), np.mean, confidence_level=LEVEL, n_resamples=BOOTSTRAP_RESAMPLES,
                             random_state=0)  # fmt: skip
    return Interval(float(values.mean()), float(result.confidence_interval.low), float(result.confidence_interval.high))


def iqm(values: np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50% of the values."""
    return float(stats.trim_mean(values, 0.25))


def iqm_interval(values: np.ndarray) -> Interval | None:
    """IQM with a bootstrap interval, from five runs on (None with fewer)."""
    values = np.asarray(values, dtype=float)
    if len(values) < IQM_MIN_RUNS:
        return None
    if np.ptp(values) == 0:
        return Interval(iqm(values), math.nan, math.nan)
    result = stats.bootstrap((values,), lambda x, axis=-1: stats.trim_mean(x, 0.25, axis=axis),
                             confidence_level=LEVEL, n_resamples=BOOTSTRAP_RESAMPLES, method="percentile",
                             random_state=0)  # fmt: skip
    return Interval(iqm(values), float(result.confidence_interval.low), float(result.confidence_interval.high))


def rate_interval(successes: int, trials: int) -> Interval:
    """Success rate with its Wilson score interval."""
    if trials == 0:
        return Interval(math.nan, math.nan, math.nan)
    interval = stats.binomtest(successes, trials).proportion_ci(confidence_level=LEVEL, method="wilson")
    return Interval(successes / trials, float(interval.low), float(interval.high))


def _verdict(p_value: float, below: bool) -> str:
    if p_value >= ALPHA:
        return "consistent"
    return "below" if below else "above"


def compare_rate(successes: int, trials: int, published: float) -> Comparison:
    """Exact binomial test of ``successes`` out of ``trials`` against a published success rate."""
    observed = successes / trials
    below = observed < published
    alternative = "less" if below else "greater"
    p_value = float(stats.binomtest(successes, trials, published, alternative=alternative).pvalue)
    verdict = _verdict(p_value, below)
    needed = None
    if verdict == "consistent" and observed != published:
        needed = _episodes_to_detect(observed, published)
    return Comparison(verdict, "exact binomial", p_value, needed)


def _episodes_to_detect(observed: float, published: float) -> int | None:
    """One-sample test of a proportion (Cohen's h, normal approximation) at 5%, one-sided, 80% power.

    n = ((z_(1 - alpha) + z_power) / h)^2 in closed form: a numerical power solver fails to converge for
    effects so large that a single episode would do (0 of 1 against 0.9).
    """
    effect = abs(2 * math.asin(math.sqrt(observed)) - 2 * math.asin(math.sqrt(published)))
    if effect == 0:
        return None
    z = stats.norm.ppf(1 - ALPHA) + stats.norm.ppf(POWER)
    return max(1, int(math.ceil((z / effect) ** 2)))


def compare_mean(values: np.ndarray, published: float, spread: float | None, spread_kind: str | None,
                 runs: int | None) -> Comparison:  # fmt: skip
    """Welch's t-test of the runs' values against a published mean (one-sample t-test without a spread)."""
    values = np.asarray(values, dtype=float)
    n = len(values)
    if n < 2 or np.std(values, ddof=1) == 0 and spread is None:
        return Comparison("consistent", "too few runs to test", math.nan, None)
    mean, std = float(values.mean()), float(np.std(values, ddof=1))
    below = mean < published
    alternative = "less" if below else "greater"
    if spread is not None and runs:
        published_std = spread * math.sqrt(runs) if spread_kind == "sem" else spread
        result = stats.ttest_ind_from_stats(mean, std, n, published, published_std, runs, equal_var=False,
                                            alternative=alternative)  # fmt: skip
        test = "Welch t-test"
        scale = math.sqrt((std**2 + published_std**2) / 2) or 1.0
    else:
        result = stats.ttest_1samp(values, published, alternative=alternative)
        test = "one-sample t-test"
        scale = std or 1.0
    p_value = float(result.pvalue)
    verdict = _verdict(p_value, below)
    needed = None
    if verdict == "consistent" and mean != published:
        from statsmodels.stats.power import TTestPower

        effect = abs(mean - published) / scale
        needed = int(math.ceil(TTestPower().solve_power(effect_size=effect, alpha=ALPHA, power=POWER,
                                                        alternative="larger")))  # fmt: skip
    return Comparison(verdict, test, p_value, needed)


class PairedTest(NamedTuple):
    """Two configurations measured on the same seeds, compared seed by seed."""

    pairs: int
    difference: float
    """Mean over the shared seeds of (configuration - baseline)."""
    test: str
    p_value: float
    """Two-sided: which way an ablation goes is the question, not an assumption."""
    discordant: tuple[int, int] | None = None
    """McNemar: (pairs only the configuration succeeded on, pairs only the baseline succeeded on)."""
    unit: str = "seed"
    """What a pair is: a seed, or an episode (same seed and episode index, so the same start)."""


def compare_paired(values: np.ndarray, baseline: np.ndarray, unit: str = "seed") -> PairedTest:
    """Paired test of values against the baseline's on the same seeds (or the same episodes of them).

    Success flags (every value 0 or 1: one episode per pair) get McNemar's exact test, the binomial test of
    the discordant pairs: pairs where both succeed or both fail say nothing about the difference, and with
    paired starts the test needs far fewer episodes than comparing two rates. Other values (returns, rates over
    several episodes) get the paired t-test.
    """
    values, baseline = np.asarray(values, dtype=float), np.asarray(baseline, dtype=float)
    differences = values - baseline
    n = len(differences)
    mean = float(differences.mean()) if n else math.nan
    if n and np.isin(values, (0.0, 1.0)).all() and np.isin(baseline, (0.0, 1.0)).all():
        gained, lost = int(np.sum(differences > 0)), int(np.sum(differences < 0))
        p_value = float(stats.binomtest(gained, gained + lost, 0.5).pvalue) if gained + lost else 1.0
        return PairedTest(n, mean, "McNemar exact", p_value, (gained, lost), unit)
    if n < 2 or np.ptp(differences) == 0:
        test = "too few pairs to test" if n < 2 else "paired t-test undefined"
        return PairedTest(n, mean, test, math.nan, unit=unit)
    return PairedTest(n, mean, "paired t-test", float(stats.ttest_rel(values, baseline).pvalue), unit=unit)
