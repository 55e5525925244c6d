"""Tables and plots of sweep results, next to the thesis's published numbers.

Pure functions of trial runs read back from MLflow (plain records): the
scheduler summarises a sweep when it ends, the ``report`` command whenever
asked. Trials are grouped by everything that distinguishes their
configurations: task, method, variant and every swept override (seeds are
what a group averages over). The sweep's metric (``metric.name``) is the
figure of each group, and ``metric.mode`` says which group is best.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import tempfile
from collections import defaultdict
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from orchestrator import report_mbrl, statistics  # noqa: E402
from orchestrator.references import Reference, find, same_param  # noqa: E402
from orchestrator.tracking import TrialRun  # noqa: E402
from workers.methods import METHODS  # noqa: E402

RATE_METRICS = {"success", "box_drops"}
"""Metrics of method mpc that are rates of per-episode successes over the trial's ``episodes``: intervals and
tests treat them as binomial."""
EPISODES_SUFFIX = "_episodes"
"""A summary figure ``<key>`` logged with ``<key>_episodes`` beside it is a rate over that many episodes (APEX's
success rates, mbrl's final success rate): binomial too."""


def is_rate(metric: str) -> bool:
    """Whether a sweep metric is a rate in [0, 1] (printed with two decimals): mpc's pooled rates and every
    method's success figure (APEX's policy_success, napsp's eval_success, mbrl's frozen_success, ...)."""
    return metric in RATE_METRICS or metric.endswith("success")


class TrialResult(NamedTuple):
    """One finished trial, reduced to what reports need."""

    run_id: str
    trial_key: str
    task: str
    method: str
    seed: int
    labels: dict[str, str]
    """The method's identifying labels (mpc: algorithm, budget)."""
    variant: str | None
    overrides: dict[str, Any]
    """Swept values of the trial (variant overrides, grid and random parameters)."""
    values: dict[str, float]
    """The trial's summary metrics (mpc: mean_return, success_rate, mean_planning_seconds_per_step)."""
    params: dict[str, str]


def result_from_run(run: TrialRun) -> TrialResult:
    method = run.params.get("method", run.tags.get("method", "mpc"))
    program = METHODS.get(method)
    labels = {k: run.tags[k] for k in (program.label_paths if program else ()) if k in run.tags}
    overrides = run.overrides
    return TrialResult(
        run_id=run.run_id,
        trial_key=run.trial_key,
        task=run.params.get("task", run.tags.get("task", "?")),
        method=method,
        seed=int(run.params.get("seed", "0")),
        labels=labels,
        variant=run.variant,
        overrides=overrides,
        values=dict(run.metrics),
        params=dict(run.params),
    )


class Pairing(NamedTuple):
    """Which variants the others are compared with, seed by seed (a sweep's ``baseline``)."""

    baselines: tuple[str, ...]
    """Variant names; a configuration is compared with the first whose task and labels (algorithm, budget, ...)
    are its own."""
    grid_keys: tuple[str, ...] = ()
    """The sweep's parameters: a configuration meets its baseline at the same grid point."""


def pairing(sweep) -> Pairing | None:
    """The pairing a sweep asks for (its ``baseline``), or None."""
    return Pairing(tuple(sweep.baseline), tuple(sweep.parameters)) if sweep.baseline else None


class PairedComparison(NamedTuple):
    """A configuration against its baseline on the seeds both ran."""

    baseline: str
    """The baseline variant's name."""
    test: statistics.PairedTest


class Group(NamedTuple):
    """The trials of one configuration (all its seeds) and what they say about the sweep's metric."""

    task: str
    method: str
    labels: dict[str, str]
    variant: str | None
    setting: dict[str, Any]
    """Swept values that define the configuration, beyond the labels."""
    trials: list[TrialResult]
    mean: float
    """Mean of the sweep's metric over the trials (the success rate over all episodes, for rates)."""
    sem: float
    """Standard error of that mean over trials (0 with one trial)."""
    interval: statistics.Interval
    """95% interval of the mean: Student's t over trials (a bootstrap from 15), Wilson for success rates."""
    iqm: statistics.Interval | None
    """Interquartile mean over trials with its bootstrap interval (five trials or more)."""
    successes: tuple[int, int] | None
    """(successes, episodes) for rate metrics."""
    reference: Reference | None
    """The published figure for this configuration, if there is one."""
    comparison: statistics.Comparison | None
    """The test of the result against the reference."""
    paired: PairedComparison | None = None
    """The comparison with the sweep's baseline variant on the seeds both ran."""
    implied: frozenset[str] = frozenset()
    """Setting keys the variant's name stands for (one value across all its configurations): left out of
    :meth:`name`, kept in ``setting`` and the CSV."""
    missing: int = 0
    """Trials without a finite value of the metric (e.g. a seed that never reached the threshold): the mean and
    interval are of the others, so the group is neither tested nor ranked best."""
    mixed: tuple[str, ...] = ()
    """Settings its runs differ in (a sweep file edited between sessions): the mean is of a mixture, so the group is
    neither tested, ranked best nor paired."""

    @property
    def n(self) -> int:
        return len(self.trials)

    @property
    def published(self) -> tuple[float, float | None] | None:
        return None if self.reference is None else (self.reference.value, self.reference.spread)

    def value(self, key: str) -> float | None:
        values = [t.values[key] for t in self.trials if key in t.values]
        return float(np.mean(values)) if values else None

    def label_parts(self) -> list[str]:
        """The group's labels as its method writes them (``icem``, ``b100``; a model preset)."""
        program = METHODS.get(self.method)
        return program.label_text(self.labels) if program and self.labels else list(self.labels.values())

    def name(self) -> str:
        parts = self.label_parts()
        if self.variant:
            parts.append(self.variant)
        parts += self.setting_text()
        return " ".join(parts) or self.method

    def setting_text(self) -> list[str]:
        """``key=value`` for each setting that the labels and the variant's name do not already say."""
        return [f"{k}={v}" for k, v in self.setting.items() if k not in self.implied]


class Summary(NamedTuple):
    groups: list[Group]
    metric: str
    """The sweep's metric (e.g. episode_return)."""
    summary_key: str
    """The trial summary metric that holds it (e.g. mean_return)."""
    mode: str
    best: int | None
    """Index of the best group by the metric and mode; None when several tie at the best value."""
    tied: tuple[int, ...] = ()
    """Indices of the groups that share the best value, when more than one does."""
    baselines: tuple[str, ...] = ()
    """The sweep's baseline variants, when it names any (each group then carries its paired comparison)."""
    unfinished: int = 0
    """Trials of the sweep's plan without a finished run (failed, stopped, or not run yet): not in the figures."""


def _rate_episodes(trial: TrialResult, metric: str, summary_key: str) -> int | None:
    """How many independent episodes the trial's figure is a success rate over; None when it is not a rate of
    independent episodes. The episodes of one trained policy or model (APEX, MBRL, neural APSP) share it, so
    pooling them over seeds would count one draw of the method many times: the seed is their unit."""
    program = METHODS.get(trial.method)
    if program is None or not program.independent_episodes:
        return None
    logged = trial.values.get(summary_key + EPISODES_SUFFIX)
    if logged is not None and math.isfinite(logged) and logged >= 1:
        return int(logged)
    if trial.method == "mpc" and metric in RATE_METRICS:
        return int(float(trial.params.get("episodes", "1") or 1))
    return None


def ablated_switches(task: str, params: dict[str, str]) -> list[str]:
    """Planner switches of a run that differ from its algorithm's defaults (an ablation or addition, Fig. 7).

    Table 3's figures are the full algorithms: a run that switches an improvement off (or adds one to
    CEM_MPC) is not compared with them.
    """
    from workers.planning.config import PRESETS, PlannerConfig
    from workers.tasks import make_task

    algorithm = params.get("planner.algorithm")
    if algorithm not in PRESETS:
        return []
    defaults = PlannerConfig(algorithm=algorithm).resolved(make_task(task).colored_noise_beta)
    return [
        name
        for name in PRESETS[algorithm]
        if f"planner.{name}" in params and not same_param(params[f"planner.{name}"], getattr(defaults, name))
    ]


def _with_implied_settings(groups: list[Group]) -> list[Group]:
    """Mark the settings a variant's name stands for: those with one value in every configuration of the variant
    (its overrides, "colorednoise-1.1" rather than "colorednoise-1.1 planner.noise_release=1.1"); settings that
    vary within the variant (a grid over it) stay in its configurations' names."""
    by_variant: dict[tuple, list[Group]] = defaultdict(list)
    for group in groups:
        if group.variant:
            by_variant[(group.task, group.method, group.variant)].append(group)
    implied: dict[tuple, frozenset[str]] = {}
    for key, members in by_variant.items():
        values = [{k: json.dumps(v, sort_keys=True) for k, v in m.setting.items()} for m in members]
        shared = set.intersection(*(set(v.items()) for v in values))
        implied[key] = frozenset(k for k, _ in shared)
    return [g._replace(implied=implied.get((g.task, g.method, g.variant), frozenset())) for g in groups]


RUN_ONLY_PARAMS = frozenset({"seed", "resources.threads_per_worker", "resources.simulation_workers"})
"""Params that say how a trial ran, not what it ran: they may differ within one configuration."""


def _settings_that_differ(members: list[TrialResult]) -> list[str]:
    """The logged settings in which a configuration's runs differ (the seed and run-only params aside). A setting
    only some runs log is no difference: settings added later keep the trial's key only at the value that
    reproduces the earlier behaviour, which the runs that predate them ran with."""
    keys = set.intersection(*(set(m.params) for m in members)) - RUN_ONLY_PARAMS
    return sorted(key for key in keys if len({m.params.get(key) for m in members}) > 1)


def _group(task, method, labels, variant, setting, members, metric, summary_key, references) -> Group:
    values = np.array([m.values.get(summary_key, math.nan) for m in members], dtype=float)
    missing = int(np.sum(~np.isfinite(values)))
    values = values[np.isfinite(values)]
    sem = float(values.std(ddof=1) / math.sqrt(len(values))) if len(values) > 1 else 0.0
    # The first run that has one: a group mixed by an edited sweep file is shown beside it whichever run comes first
    # (and not tested, below).
    found = ((m, find(references, task, method, m.params, metric)) for m in members)
    first, reference = next(((m, r) for m, r in found if r is not None), (members[0], None))
    if reference is not None and "planner.algorithm" in reference.match and ablated_switches(task, first.params):
        reference = None
    successes = None
    episodes = [_rate_episodes(m, metric, summary_key) for m in members
                if math.isfinite(m.values.get(summary_key, math.nan))]  # fmt: skip
    if len(values) and None not in episodes:
        successes = (int(round(sum(v * e for v, e in zip(values, episodes)))), int(sum(episodes)))
        interval = statistics.rate_interval(*successes)
        mean = interval.estimate
        comparison = statistics.compare_rate(*successes, reference.value, reference.runs) if reference else None
    else:
        interval = statistics.mean_interval(values, bounds=(0.0, 1.0) if is_rate(metric) else None)
        mean = interval.estimate
        comparison = None
        if reference is not None and len(values):
            comparison = statistics.compare_mean(values, reference.value, reference.spread, reference.spread_kind,
                                                 reference.runs)  # fmt: skip
    differences = reference.differences(first.params) if reference is not None else []
    if differences:  # a reduced run: the published figure stands beside it, untested (e.g. Table 9 at n = 2)
        comparison = statistics.Comparison("untested", "not tested: ran " + ", ".join(differences), math.nan, None)
    boundary = statistics.exact_boundary_rate(reference.value, reference.runs) if reference is not None else None
    if boundary is not None and len(values) and bool(np.all((values >= 0) & (values <= 1))):  # per-seed rates too
        comparison = boundary
    mixed = _settings_that_differ(members)
    if mixed and reference is not None:
        # Runs of one configuration that ran different settings: a sweep file edited between sessions (a base
        # value changed) whose earlier run of a seed is still the seed's only finished one.
        comparison = statistics.Comparison(
            "untested", "not tested: its runs differ in " + ", ".join(mixed), math.nan, None
        )
    if missing and reference is not None:
        # A run without the figure is most often censored, not missing (a seed that never reached the threshold
        # has no episodes_to_threshold): the mean of the others would favour the configuration that failed more.
        comparison = statistics.Comparison(
            "untested", f"not tested: {missing} of {len(members)} runs have no value", math.nan, None
        )
    # The IQM trims the best and worst quarter of runs; of one success flag per run it would trim outcomes, not
    # outliers, and say nothing the rate does not.
    flags = successes is not None and bool(np.isin(values, (0.0, 1.0)).all())
    return Group(task, method, dict(labels), variant or None, setting, members, mean, sem, interval,
                 None if flags else statistics.iqm_interval(values), successes, reference, comparison,
                 missing=missing, mixed=tuple(mixed))  # fmt: skip


def summarize(
    runs: Iterable[TrialRun],
    metric: str,
    mode: str = "max",
    references: list[Reference] = (),
    planned: set[str] | None = None,
    pairing: Pairing | None = None,
    episodes: Histories | None = None,
) -> Summary:
    """Group finished trial runs by configuration, summarise the sweep's metric, test it against the references.

    ``pairing``: compare each variant with its baseline seed by seed (see :class:`Pairing`).

    ``episodes``: run id -> {metric: [(episode, value), ...]}, the sweep's metric per episode, for a method whose
    episodes start alike across configurations (``Program.paired_episodes``): where both sides have them, a
    variant meets its baseline episode by episode.

    ``planned``: the trial keys of the sweep's current plan. A resumed sweep whose code resolves a configuration
    differently (a new key) runs it again under the same parent; where a configuration and seed has a planned
    run, its other runs are left out, so each seed counts once, as the current code runs it.
    """
    results = [result_from_run(run) for run in runs]
    method = results[0].method if results else "mpc"
    program = METHODS.get(method)
    summary_key = (program.metrics if program else {}).get(metric, metric)
    covered = {"task", *(path for paths in (program.label_paths if program else {}).values() for path in paths)}
    grouped: dict[tuple, list[TrialResult]] = defaultdict(list)
    for result in results:
        setting = {k: v for k, v in result.overrides.items() if k not in covered}
        key = (result.task, result.method, tuple(result.labels.items()), result.variant or "",
               json.dumps(setting, sort_keys=True))  # fmt: skip
        grouped[key].append(result)
    if planned is not None:
        for key, members in grouped.items():
            current = {m.seed for m in members if m.trial_key in planned}
            grouped[key] = [m for m in members if m.trial_key in planned or m.seed not in current]
    groups = [
        _group(task, method_name, labels, variant, json.loads(setting), members, metric, summary_key, list(references))
        for (task, method_name, labels, variant, setting), members in grouped.items()
    ]
    groups.sort(key=lambda g: (g.task, _sort_labels(g.labels), g.variant or "", json.dumps(g.setting, sort_keys=True)))
    groups = _with_implied_settings(groups)
    if pairing is not None:
        groups = [group._replace(paired=_paired(group, groups, pairing, summary_key, metric, episodes))
                  for group in groups]  # fmt: skip
    finite = [i for i, g in enumerate(groups) if math.isfinite(g.mean) and not g.missing and not g.mixed]
    best, tied = None, ()
    if finite:
        pick = max if mode == "max" else min
        value = pick(groups[i].mean for i in finite)
        leaders = tuple(i for i in finite if groups[i].mean == value)
        # A star on one of several equal groups (e.g. two 10/10 success rates) would rank what the data do not.
        best, tied = (leaders[0], ()) if len(leaders) == 1 else (None, leaders)
    unfinished = len(planned - {r.trial_key for r in results}) if planned is not None else 0
    return Summary(groups, metric, summary_key, mode, best, tied, pairing.baselines if pairing else (), unfinished)


def _paired(group: Group, groups: list[Group], pairing: Pairing, summary_key: str, metric: str,
            episodes: Histories | None) -> PairedComparison | None:  # fmt: skip
    """``group`` against its baseline on their shared episodes where both logged them, else on their shared
    seeds; None for a baseline or where none matches."""
    if group.variant in pairing.baselines or group.missing or group.mixed:
        # A seed without a value (censored) would drop out of the pairs, leaving survivors; a mixed group's seeds
        # ran different settings, so their differences are not the variant's effect.
        return None

    def point(g: Group) -> dict[str, Any]:
        return {key: g.setting.get(key) for key in pairing.grid_keys}

    for name in pairing.baselines:
        for baseline in groups:
            if (baseline.variant, baseline.task, baseline.labels, point(baseline)) != (
                name, group.task, group.labels, point(group)
            ):
                continue
            if baseline.missing or baseline.mixed:
                return None
            mine, theirs = _per_episode(group, metric, episodes), _per_episode(baseline, metric, episodes)
            unit = "episode"
            if not mine or not theirs:
                mine, theirs, unit = _per_seed(group, summary_key), _per_seed(baseline, summary_key), "seed"
            shared = sorted(mine.keys() & theirs.keys())
            test = statistics.compare_paired([mine[k] for k in shared], [theirs[k] for k in shared], unit)
            return PairedComparison(name, test)
    return None


def _per_episode(group: Group, metric: str, episodes: Histories | None) -> dict[tuple[int, int], float]:
    """The group's metric by (seed, episode); empty unless every trial logged it per episode."""
    if not episodes:
        return {}
    by_episode: dict[tuple[int, int], list[float]] = defaultdict(list)
    for trial in group.trials:
        # An episode logged twice counts once, with its last value.
        history = dict(episodes.get(trial.run_id, {}).get(metric, []))
        if not history:
            return {}
        for episode, value in history.items():
            if math.isfinite(value):
                by_episode[(trial.seed, int(episode))].append(value)
    return {key: float(np.mean(values)) for key, values in by_episode.items()}


def _per_seed(group: Group, summary_key: str) -> dict[int, float]:
    """The group's metric by seed (the mean where a seed ran more than once)."""
    by_seed: dict[int, list[float]] = defaultdict(list)
    for trial in group.trials:
        value = trial.values.get(summary_key, math.nan)
        if math.isfinite(value):
            by_seed[trial.seed].append(value)
    return {seed: float(np.mean(values)) for seed, values in by_seed.items()}


def _sort_labels(labels: dict[str, str]) -> tuple:
    return tuple((k, int(v)) if v.isdigit() else (k, 0, v) for k, v in labels.items())


def _number(value: float, metric: str) -> str:
    if not math.isfinite(value):
        return "-"
    if is_rate(metric):
        return f"{value:.2f}"
    return f"{value:.4g}" if abs(value) < 10 else f"{value:.1f}"


def _published_text(group: Group, metric: str) -> str:
    if group.reference is None:
        return "-"
    r = group.reference
    text = _number(r.value, metric)
    if r.spread is not None:
        text += f" +- {_number(r.spread, metric)}"
    return text


def _comparison_text(group: Group) -> str:
    c = group.comparison
    if c is None:
        return "-"
    if not math.isfinite(c.p_value):
        return c.test
    text = f"{c.verdict} ({c.test}, p={c.p_value:.2g})"
    if c.runs_needed:
        unit = _settle_unit(group)
        text += f"; ~{c.runs_needed} {unit[:-1] if c.runs_needed == 1 else unit} to settle"
    elif not c.attainable:
        text += f"; no number of runs settles it against {group.reference.runs} published runs"
    return text


def _settle_unit(group: Group) -> str:
    """What a comparison's ``runs_needed`` counts: episodes where the rate test pooled them, else runs."""
    return "episodes" if group.successes else "runs"


def _paired_text(group: Group, summary: Summary) -> str:
    if group.variant in summary.baselines:
        return "baseline"
    if group.paired is None:
        return "-"
    name, t = group.paired.baseline, group.paired.test
    difference = f"{t.difference:+.2f}" if is_rate(summary.metric) else f"{t.difference:+.4g}"
    units = f"{t.pairs} {t.unit}{'' if t.pairs == 1 else 's'}"
    if t.discordant is not None:
        # Better and worse by the sweep's mode: a box dropped in fewer episodes is the gain of a min metric.
        higher, lower = t.discordant
        better, worse = (higher, lower) if summary.mode == "max" else (lower, higher)
        detail = f"McNemar exact, {better} better : {worse} worse of {units}"
    else:
        detail = f"{t.test}, {units}"
    if math.isfinite(t.p_value):
        detail += f", p={t.p_value:.2g}"
    return f"{difference} vs {name} ({detail})"


def _estimate_text(group: Group, metric: str) -> str:
    low, high = group.interval.low, group.interval.high
    text = _number(group.mean, metric)
    if group.successes:
        text += f" ({group.successes[0]}/{group.successes[1]})"
    if group.missing:
        text += f" (of {group.n - group.missing}; {group.missing} without a value)"
    if group.mixed:
        text += f" (runs differ in {', '.join(group.mixed)})"
    if math.isfinite(low):
        text += f" [{_number(low, metric)}, {_number(high, metric)}]"
    return text


def format_table(summary: Summary) -> str:
    """A plain-text table, one line per configuration: estimate with 95% interval, IQM, the thesis, the test."""
    metric = summary.metric
    header = ("task", "configuration", "n", f"{metric} [95% CI]", "IQM", "s/step", "published", "vs published")
    if summary.baselines:
        header += ("vs baseline (paired)",)
    rows = [header]
    for index, g in enumerate(summary.groups):
        seconds = g.value("mean_planning_seconds_per_step")
        estimate = _estimate_text(g, metric)
        if index == summary.best and len(summary.groups) > 1:
            estimate += " *"
        iqm = "-" if g.iqm is None else _number(g.iqm.estimate, metric)
        rows.append((
            g.task, g.name(), str(g.n), estimate, iqm,
            "-" if seconds is None else f"{seconds:.3f}",
            _published_text(g, metric), _comparison_text(g),
        ) + ((_paired_text(g, summary),) if summary.baselines else ()))  # fmt: skip
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    notes = []
    if summary.best is not None and len(summary.groups) > 1:
        notes.append(f"* best by {metric} ({summary.mode})")
    elif summary.tied:
        value = _number(summary.groups[summary.tied[0]].mean, metric)
        notes.append(f"no single best by {metric}: {len(summary.tied)} configurations tie at {value}")
    if summary.unfinished:
        # A seed that failed is as much a result as one that finished; its absence would go unseen in n.
        notes.append(f"{summary.unfinished} planned trial(s) have no finished run (failed, stopped or not run "
                     "yet); where an earlier run of the same configuration and seed finished (other code, another "
                     "key), it stands in; `icemlab status` lists them")  # fmt: skip
    sources = sorted({g.reference.source for g in summary.groups if g.reference})
    if sources:
        notes.append("published: " + "; ".join(sources) + "; tests two-sided, 5%")
    tests = sum(g.comparison is not None and g.comparison.verdict != "untested" for g in summary.groups)
    if tests > 1:
        # Each test errs 5% of the time where the figures truly agree: over a whole table some will.
        notes.append(f"{tests} tests against published figures, each at 5% and not corrected for their number: "
                     f"about {tests * 0.05:.1f} of them would read below or above by chance alone")  # fmt: skip
    if summary.baselines:
        notes.append("vs baseline: mean difference over the seeds both ran, or over their episodes where each "
                     "starts alike in both; tests two-sided")
    return "\n".join(lines + notes)


def to_csv(summary: Summary) -> str:
    import csv
    import io

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    label_keys = sorted({k for g in summary.groups for k in g.labels})
    setting_keys = sorted({k for g in summary.groups for k in g.setting})
    m = summary.metric
    writer.writerow(
        ["task", "method", *label_keys, "variant", *setting_keys, "trials", "trials_without_value", f"{m}_mean",
         f"{m}_sem", f"{m}_ci_low", f"{m}_ci_high", f"{m}_iqm", f"{m}_iqm_ci_low", f"{m}_iqm_ci_high", "successes",
         "episodes",
         "seconds_per_step", "published", "published_spread", "published_runs", "published_source", "verdict",
         "test", "p_value", "runs_to_settle", "runs_to_settle_unit", "best", "paired_baseline", "paired_pairs",
         f"paired_{m}_difference",
         "paired_test", "paired_p_value", "paired_unit"]
    )  # fmt: skip

    def cell(value) -> str:
        return "" if value is None or (isinstance(value, float) and not math.isfinite(value)) else f"{value:.6g}"

    for index, g in enumerate(summary.groups):
        r, c = g.reference, g.comparison
        writer.writerow(
            [g.task, g.method, *[g.labels.get(k, "") for k in label_keys], g.variant or "",
             *[g.setting.get(k, "") for k in setting_keys], g.n, g.missing, cell(g.mean), cell(g.sem),
             cell(g.interval.low), cell(g.interval.high),
             cell(g.iqm.estimate if g.iqm else None), cell(g.iqm.low if g.iqm else None),
             cell(g.iqm.high if g.iqm else None),
             g.successes[0] if g.successes else "", g.successes[1] if g.successes else "",
             cell(g.value("mean_planning_seconds_per_step")),
             cell(r.value if r else None), cell(r.spread if r else None), r.runs if r and r.runs else "",
             r.source if r else "", c.verdict if c else "", c.test if c else "", cell(c.p_value if c else None),
             c.runs_needed if c and c.runs_needed else ("unattainable" if c and not c.attainable else ""),
             _settle_unit(g) if c and c.runs_needed else "",
             int(index == summary.best),
             *_paired_cells(g, cell)]
        )  # fmt: skip
    return buffer.getvalue()


def _paired_cells(group: Group, cell) -> list[Any]:
    if group.paired is None:
        return ["", "", "", "", "", ""]
    t = group.paired.test
    return [group.paired.baseline, t.pairs, cell(t.difference), t.test, cell(t.p_value), t.unit]


def _error_bars(groups: list[Group]) -> np.ndarray:
    """(2, n) distances from each mean to its 95% interval (0 where there is none)."""
    return statistics.error_bars([g.interval for g in groups])


def budget_figure(summary: Summary):
    """Metric against budget, one line per algorithm and variant (the style of the thesis's Fig. 5).

    Filled markers with 95% intervals are this sweep; hollow squares are the published figures.
    """
    groups = [g for g in summary.groups if g.labels.get("budget", "None").isdigit()]
    tasks = sorted({g.task for g in groups})
    figure, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 3.8), squeeze=False)
    for axis, task in zip(axes[0], tasks):
        lines: dict[str, list[Group]] = defaultdict(list)
        for g in groups:
            if g.task == task:
                name = " ".join(
                    [g.labels.get("algorithm", g.method), g.variant or "", *g.setting_text()]
                )  # noqa: E501
                lines[name.strip()].append(g)
        for name, members in sorted(lines.items()):
            members.sort(key=lambda g: int(g.labels["budget"]))
            budgets = [int(g.labels["budget"]) for g in members]
            line = axis.errorbar(budgets, [g.mean for g in members], yerr=_error_bars(members),
                                 marker="o", capsize=3, label=name)  # fmt: skip
            published = [(int(g.labels["budget"]), g.published[0]) for g in members if g.published]
            if published:
                axis.plot(*zip(*published), linestyle="none", marker="s", markerfacecolor="none",
                          color=line[0].get_color(), label=f"{name} (thesis)")  # fmt: skip
        budgets = sorted({int(g.labels["budget"]) for g in groups if g.task == task})
        axis.set_xscale("log")
        axis.set_xticks(budgets, [str(b) for b in budgets])
        axis.minorticks_off()
        axis.set_xlabel("budget (trajectories per step)")
        axis.set_ylabel(summary.metric.replace("_", " "))
        axis.set_title(task)
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    figure.tight_layout()
    return figure


def interval_caption(summary: Summary) -> str:
    """What the bars of a figure show: a rate's Wilson interval is over episodes, a mean's over seeds."""
    metric = summary.metric.replace("_", " ")
    if summary.groups and all(g.successes is not None for g in summary.groups):
        return f"{metric} (rate over all episodes, 95% Wilson interval)"
    within = ", cut to [0, 1]" if is_rate(summary.metric) else ""
    return f"{metric} (mean over seeds, 95% interval: Student's t from two seeds on, a bootstrap from 15{within})"


def variant_figure(summary: Summary):
    """One bar per variant with its 95% interval, per task (the style of the thesis's Fig. 7 ablations)."""
    tasks = sorted({g.task for g in summary.groups})
    longest = max(len(g.name()) for g in summary.groups)
    width = max(8.0, 4.0 + 0.075 * longest)  # room for the labels, which name every switched setting
    figure, axes = plt.subplots(len(tasks), 1, figsize=(width, 1.0 + 0.45 * len(summary.groups)), squeeze=False)
    for axis, task in zip(axes[:, 0], tasks):
        members = [g for g in summary.groups if g.task == task]
        names = [g.name() for g in members]
        positions = np.arange(len(members))
        axis.barh(positions, [g.mean for g in members], xerr=_error_bars(members), capsize=3, color="tab:blue")
        marks = [(g.reference.value, i) for i, g in enumerate(members) if g.reference]
        if marks:
            axis.plot(*zip(*marks), linestyle="none", marker="s", markerfacecolor="none", color="black",
                      label="published")  # fmt: skip
            axis.legend(fontsize=8)
        axis.set_yticks(positions, names)
        axis.invert_yaxis()
        axis.set_xlabel(interval_caption(summary))
        axis.set_title(task)
        axis.grid(alpha=0.3, axis="x")
    figure.tight_layout()
    return figure


Histories = dict[str, dict[str, list[tuple[int, float]]]]
"""run id -> metric -> [(step, value)], the curves of finished trials."""


def curves_figure(summary: Summary, histories: Histories, metrics: Iterable[str], step_label: str = "step"):
    """Each curve metric against its step: one line per configuration, mean over seeds with +- sem shading.

    Metrics no trial logged (coverage on a task without a coverage grid) get no panel.
    """
    metrics = list(metrics)
    logged = {metric for runs in histories.values() for metric, points in runs.items() if points}
    metrics = [m for m in metrics if m in logged] or metrics[:1]
    figure, axes = plt.subplots(1, len(metrics), figsize=(6.5 * len(metrics), 4), squeeze=False)
    for axis, metric in zip(axes[0], metrics):
        for group in summary.groups:
            series = [dict(histories.get(t.run_id, {}).get(metric, [])) for t in group.trials]
            steps = sorted({step for s in series for step in s})
            if not steps:
                continue
            values = np.array([[s.get(step, np.nan) for step in steps] for s in series])
            counts = np.sum(np.isfinite(values), axis=0)
            mean = np.nanmean(values, axis=0)
            sem = np.where(counts > 1, np.nanstd(values, axis=0, ddof=min(1, len(series) - 1)) / np.sqrt(counts), 0.0)
            label = f"{group.task} {group.name()} (n={group.n})"
            axis.plot(steps, mean, label=label)
            axis.fill_between(steps, mean - sem, mean + sem, alpha=0.2)
        axis.set_xlabel(step_label)
        axis.set_ylabel(metric)
        axis.set_title(f"{metric}: mean +- sem over seeds")
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    figure.tight_layout()
    return figure


def copy_trial_plots(
    tracker: Any, results: Sequence[TrialResult], names: dict[str, str], directory: Path
) -> list[Path]:
    """Each trial's plots its method picks (:meth:`Program.report_plots`) into ``directory/trials/<run name>/``.

    Args:
        tracker: reads the runs' artifacts (list_files, download).
        results: the finished trials.
        names: run id -> the run's name (the folder, with '/' and '#' made file-name safe).
    """
    copied = []
    for result in results:
        program = METHODS.get(result.method)
        chosen = program.report_plots(tracker.list_files(result.run_id, "plots")) if program else []
        if not chosen:
            continue
        folder = directory / "trials" / re.sub(r"[^A-Za-z0-9._=-]+", "_", names.get(result.run_id, result.run_id))
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory() as scratch:
            for path in chosen:
                target = folder / Path(path).name
                shutil.move(str(tracker.download(result.run_id, path, scratch)), target)
                copied.append(target)
    return copied


def write_files(summary: Summary, directory: Path, histories: Histories | None = None) -> list[Path]:
    """summary.txt, summary.csv and the plots that fit the sweep, in ``directory``; returns their paths."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = [directory / "summary.txt", directory / "summary.csv"]
    paths[0].write_text(format_table(summary) + "\n")
    paths[1].write_text(to_csv(summary))
    if not summary.groups:
        return paths
    if len({g.labels.get("budget") for g in summary.groups if g.labels.get("budget", "None").isdigit()}) > 1:
        figure = budget_figure(summary)
        paths.append(directory / "budget_curve.png")
        figure.savefig(paths[-1], dpi=110)
        plt.close(figure)
    program = METHODS.get(summary.groups[0].method)
    if histories and program is not None and program.curves:
        figure = curves_figure(summary, histories, program.curves, program.curve_step)
        paths.append(directory / "curves.png")
        figure.savefig(paths[-1], dpi=110)
        plt.close(figure)
    if any(g.variant for g in summary.groups):
        figure = variant_figure(summary)
        paths.append(directory / "variants.png")
        figure.savefig(paths[-1], dpi=110)
        plt.close(figure)
    if any(g.method == "mbrl" or report_mbrl.PENALTY_SETTING in g.setting for g in summary.groups):
        # chapter 5's figures (Fig. 19a/b, 37a)
        paths += report_mbrl.write_files(summary, directory)
    return paths
