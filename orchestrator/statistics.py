"""How sure a result is, and whether it differs from a published one.

scipy.stats does the estimation, the tests and the power analysis: the power
of a t-test from the noncentral t distribution, with the fewest runs that reach
80% found by search over whole numbers of runs (a continuous solver fails, or
names too few runs, for effects so large that two or three runs would do); the
power of a rate test from the closed-form normal approximation (Cohen's h).

* Intervals (95%): for returns Student's t interval of the runs' mean below
  ``BOOTSTRAP_MIN_RUNS`` runs and a bootstrap (BCa) from there on (the
  bootstrap of a handful of runs undercovers: about 71% of true means with
  three runs, 86% with five); for success rates the Wilson score interval of
  the successes (a mean of per-seed rates gets the t interval, cut to [0, 1]);
  for five runs or more also the interquartile mean (IQM: the mean after trimming
  floor(n/4) runs from each end, as rliable's ``trim_mean`` at 25% does; the middle 50% when n is a
  multiple of 4, 60-71% of 5-7 runs) with a bootstrap interval. rliable itself does not
  import beside this stack (its ``arch`` dependency fails with pandas 3), and
  with one task per configuration its stratified bootstrap is the plain
  bootstrap of runs used here.
* Verdicts against a reference: for a published success rate over a known
  number of runs Fisher's exact test of the two samples (the published rate
  is itself an estimate: 9 of 10 against 50 of 50 is p = 0.17, not 0); an
  exact binomial test against the rate taken as exact when the run count is
  not published (untested for a published 0 or 1, which no failure or
  success could then meet); success rates pool episodes only where they are
  independent draws (ground-truth MPC), else the seed is the unit and its
  rates are means; for returns Welch's t-test
  against the published mean, spread and run count (a one-sample t-test when
  the reference gives no spread, or one run, or no run count: the test's
  name then says the spread went unused). A configuration with runs that
  have no value (a seed that never reached a threshold) is not tested, nor
  ranked best: the mean of the others would be survivors'. Tests are two-sided at the 5%
  level: ``below`` or ``above`` (the side of the observed difference) when
  the difference is significant, ``consistent`` when it is not, and
  ``untested`` when no test is defined (one run, or constant runs against a
  mean without a spread): never a verdict without a test. A one-sided
  test in the direction the data happen to point would call a true null
  ``below`` or ``above`` in about 10% of comparisons, not 5%.
* Variants against a baseline on the same seeds (a sweep's ``baseline``):
  McNemar's exact test for one success flag per seed, the paired t-test
  otherwise (the sign test where every pair differs by the same amount);
  two-sided.
* Runs to settle: for a comparison that is not significant, how many runs
  (episodes, for rates) the same two-sided test at 5% needs to detect the
  observed difference with 80% power. Against a published mean with a spread
  over a few runs, the published runs' own uncertainty stays however many
  runs are added; where no number of runs reaches 80% power, none is named
  (``Comparison.attainable`` is false).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from scipy import integrate, stats

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
    """consistent, below, above, or untested (no test is defined for the data)."""
    test: str
    """The test that decided it."""
    p_value: float
    """Two-sided."""
    runs_needed: int | None
    """Runs (episodes for rates) that would detect the observed difference at 5% with 80% power; None once
    the difference is significant, when there is none, or when no number of runs would (``attainable``)."""
    attainable: bool = True
    """False when even infinitely many runs would not detect the difference with 80% power against the
    published runs (their own spread over their few runs bounds the test)."""


BOOTSTRAP_MIN_RUNS = 15
"""From this many runs on the mean's interval is a bootstrap; below, Student's t (whose coverage holds for
few runs of roughly normal returns, where the bootstrap's does not)."""


def mean_interval(values: np.ndarray, bounds: tuple[float, float] | None = None) -> Interval:
    """The runs' mean with a 95% interval: Student's t from two runs on, a bootstrap (BCa) from 15.

    ``bounds`` is the range the true mean lies in (a mean of per-seed success rates: (0, 1)); the interval is
    cut to it. That keeps its coverage, since the true mean is never outside, and a rate's bar never reads
    above 1 or below 0 (Student's t over 1.0 and 0.9 reaches 1.59).
    """
    values = np.asarray(values, dtype=float)
    if len(values) == 0:
        return Interval(math.nan, math.nan, math.nan)
    if len(values) < 2 or np.ptp(values) == 0:
        return Interval(float(values.mean()), math.nan, math.nan)
    if len(values) < BOOTSTRAP_MIN_RUNS:
        low, high = stats.t.interval(LEVEL, len(values) - 1, loc=values.mean(), scale=stats.sem(values))
    else:
        result = stats.bootstrap((values,), np.mean, confidence_level=LEVEL, n_resamples=BOOTSTRAP_RESAMPLES,
                                 random_state=0)  # fmt: skip
        low, high = result.confidence_interval.low, result.confidence_interval.high
    if bounds is not None:
        low, high = max(float(low), bounds[0]), min(float(high), bounds[1])
    return Interval(float(values.mean()), float(low), float(high))


def iqm(values: np.ndarray) -> float:
    """Interquartile mean: the mean after trimming floor(n/4) values from each end (the middle 50% when n is a
    multiple of 4)."""
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


UNTESTED = Comparison("untested", "too few runs to test", math.nan, None)
"""No test is defined for the data: the report says so rather than giving a verdict."""


def _verdict(p_value: float, below: bool) -> str:
    if math.isnan(p_value):
        return "untested"
    if not p_value < ALPHA:
        return "consistent"
    return "below" if below else "above"


def exact_boundary_rate(published: float, published_runs: int | None) -> Comparison | None:
    """The untested comparison with a published rate of 0 or 1 given without its run count, else None. Taken as
    exact, a published 100% makes a single failure impossible (p = 0); it was itself counted over runs the
    reference does not give."""
    if published_runs is None and published in (0.0, 1.0):
        return Comparison("untested", f"not tested: a published rate of {published:g} without its run count",
                          math.nan, None)  # fmt: skip
    return None


def compare_rate(successes: int, trials: int, published: float, published_runs: int | None = None) -> Comparison:
    """``successes`` out of ``trials`` against a published success rate: Fisher's exact test against the
    published successes when ``published_runs`` says how many runs the rate came from, else the exact binomial
    test with the published rate taken as exact."""
    if trials == 0:
        return UNTESTED
    observed = successes / trials
    if published_runs:
        theirs = int(round(published * published_runs))
        table = [[successes, trials - successes], [theirs, published_runs - theirs]]
        p_value = float(stats.fisher_exact(table).pvalue)
        test = "Fisher exact"
        published = theirs / published_runs
    else:
        boundary = exact_boundary_rate(published, published_runs)
        if boundary is not None:
            return boundary
        p_value = float(stats.binomtest(successes, trials, published).pvalue)
        test = "exact binomial"
    verdict = _verdict(p_value, observed < published)
    if verdict != "consistent" or observed == published:
        return Comparison(verdict, test, p_value, None)
    needed = _episodes_to_detect(observed, published, published_runs)
    return Comparison(verdict, test, p_value, needed, attainable=needed is not None)


def _episodes_to_detect(observed: float, published: float, published_runs: int | None = None) -> int | None:
    """Episodes for a test of proportions (Cohen's h, normal approximation) at 5%, two-sided, 80% power.

    Against an exact rate n = (z / h)^2 with z = z_(1 - alpha/2) + z_power, in closed form: a numerical power
    solver fails to converge for effects so large that a single episode would do (0 of 1 against 0.9). Against
    m published runs the test's standard error is sqrt(1/n + 1/m), so n = z^2 / (h^2 - z^2 / m); None when
    h^2 <= z^2 / m, where the published runs alone leave the difference undetectable at 80% power.
    """
    effect = abs(2 * math.asin(math.sqrt(observed)) - 2 * math.asin(math.sqrt(published)))
    if effect == 0:
        return None
    z = stats.norm.ppf(1 - ALPHA / 2) + stats.norm.ppf(POWER)
    if published_runs is None:
        return max(1, int(math.ceil((z / effect) ** 2)))
    margin = effect**2 - z**2 / published_runs
    if margin <= 0:
        return None
    return max(1, int(math.ceil(z**2 / margin)))


def compare_mean(values: np.ndarray, published: float, spread: float | None, spread_kind: str | None,
                 runs: int | None) -> Comparison:  # fmt: skip
    """Welch's t-test of the runs' values against a published mean, spread and run count; a one-sample t-test
    when the reference gives no spread or a single run (its mean taken as exact)."""
    values = np.asarray(values, dtype=float)
    n = len(values)
    std = float(np.std(values, ddof=1)) if n > 1 else 0.0
    published_std = None
    if spread is not None and runs is not None and runs >= 2:
        published_std = spread * math.sqrt(runs) if spread_kind == "sem" else spread
    welch = bool(published_std)
    if n < 2 or (std == 0 and not welch):
        return UNTESTED
    mean = float(values.mean())
    if welch:
        result = stats.ttest_ind_from_stats(mean, std, n, published, published_std, runs, equal_var=False)
        test = "Welch t-test"
    else:
        result = stats.ttest_1samp(values, published)
        # Without a run count a published spread says nothing about the published mean's own error (Table 9):
        # the mean is taken as exact, and the test's name says the spread went unused.
        test = "one-sample t-test"
        if spread is not None:
            why = "no run count" if runs is None else "one run" if runs < 2 else "a spread of 0"
            test += f", published spread unused ({why})"
    p_value = float(result.pvalue)
    verdict = _verdict(p_value, mean < published)
    if verdict != "consistent" or mean == published:
        return Comparison(verdict, test, p_value, None)
    if welch:
        needed = _runs_to_detect_welch(abs(mean - published), std, published_std, runs)
    else:
        effect = abs(mean - published) / std
        needed = _fewest_runs(lambda n: _one_sample_power(effect, n))
    return Comparison(verdict, test, p_value, needed, attainable=needed is not None)


MAX_RUNS_TO_SETTLE = 10**6
"""Beyond this many runs the question is called not settleable by runs."""


def _t_power(critical: float, df: float, shift: float) -> float:
    """Probability that a t statistic with noncentrality ``shift`` falls beyond +-``critical``.

    scipy's noncentral t; where it returns nan (one degree of freedom and a large shift: two runs against a
    distant published mean), the same probability as T = (Z + shift) / sqrt(V / df), V chi-square on ``df``
    degrees of freedom: the normal tail probabilities integrated over V.
    """
    power = float(stats.nct.sf(critical, df, shift) + stats.nct.cdf(-critical, df, shift))
    if math.isfinite(power):
        return power

    def beyond(v: float) -> float:
        scale = critical * math.sqrt(v / df)
        return float(stats.norm.sf(scale - shift) + stats.norm.cdf(-scale - shift)) * float(stats.chi2.pdf(v, df))

    return min(1.0, integrate.quad(beyond, 0.0, float(stats.chi2.isf(1e-12, df)), points=[df], limit=200)[0])


def _one_sample_power(effect: float, n: int) -> float:
    """Power of the two-sided one-sample t-test at 5% with ``n`` runs for a true difference of ``effect``
    standard deviations (noncentral t, n - 1 degrees of freedom, noncentrality effect * sqrt(n))."""
    return _t_power(stats.t.ppf(1 - ALPHA / 2, n - 1), n - 1, effect * math.sqrt(n))


def _fewest_runs(power: Callable[[int], float]) -> int | None:
    """The fewest runs, at least 2, at which ``power(runs)`` reaches 80%, for a power that grows with the runs;
    None beyond ``MAX_RUNS_TO_SETTLE``."""
    low, high = 2, 2
    while power(high) < POWER:
        low, high = high, high * 2
        if high > MAX_RUNS_TO_SETTLE:
            return None
    return low + bisect.bisect_left(range(low, high + 1), True, key=lambda runs: power(runs) >= POWER)


def _welch_power(difference: float, std: float, n: int, published_std: float, runs: int) -> float:
    """Power of the two-sided Welch t-test at 5% for a true ``difference``, with ``n`` own runs of spread
    ``std`` against ``runs`` published runs of spread ``published_std`` (noncentral t, Welch-Satterthwaite df)."""
    own, theirs = std**2 / n, published_std**2 / runs
    error = math.sqrt(own + theirs)
    df = (own + theirs) ** 2 / (own**2 / max(n - 1, 1) + theirs**2 / (runs - 1))
    return _t_power(stats.t.ppf(1 - ALPHA / 2, df), df, difference / error)


def _runs_to_detect_welch(difference: float, std: float, published_std: float, runs: int) -> int | None:
    """Fewest own runs at which the Welch test reaches 80% power with the published runs fixed; None when no
    number does (the limit of infinitely many own runs is a one-sample test against the published mean's
    standard error with runs - 1 degrees of freedom)."""
    limit = stats.t.ppf(1 - ALPHA / 2, runs - 1)
    if _t_power(limit, runs - 1, difference / (published_std / math.sqrt(runs))) < POWER:
        return None
    return _fewest_runs(lambda n: _welch_power(difference, std, n, published_std, runs))


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
    if n < 2:
        return PairedTest(n, mean, "too few pairs to test", math.nan, unit=unit)
    if np.ptp(differences) == 0:
        # Every pair differs by the same amount: the t statistic is undefined, but the sign test is not (all n
        # differences on one side, p = 2 / 2^n; none at all, p = 1).
        higher = int(np.sum(differences > 0))
        p_value = float(stats.binomtest(higher, n, 0.5).pvalue) if mean != 0 else 1.0
        return PairedTest(n, mean, "sign test", p_value, unit=unit)
    return PairedTest(n, mean, "paired t-test", float(stats.ttest_rel(values, baseline).pvalue), unit=unit)
