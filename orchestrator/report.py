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
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NamedTuple

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from orchestrator.tracking import TAG_VARIANT, TrialRun  # noqa: E402
from workers.methods import METHODS  # noqa: E402

OVERRIDE_PREFIX = "icemlab.override."

# Table 3 (ground-truth models; 50 runs, Fetch 100): (task, algorithm, budget) -> (value, +-).
# Returns for HalfCheetah and Humanoid, success rates for the rest (no spread given).
PUBLISHED: dict[tuple[str, str, int], tuple[float, float | None]] = {
    ("halfcheetah_running", "icem", 100): (5236, 167), ("halfcheetah_running", "cem_mpc", 100): (699, 120),
    ("halfcheetah_running", "icem", 300): (7633, 250), ("halfcheetah_running", "cem_mpc", 300): (3682, 119),
    ("halfcheetah_running", "icem", 500): (8756, 255), ("halfcheetah_running", "cem_mpc", 500): (5059, 179),
    ("humanoid_standup", "icem", 100): (368e3, 12e3), ("humanoid_standup", "cem_mpc", 100): (155e3, 488),
    ("humanoid_standup", "icem", 300): (411e3, 5e3), ("humanoid_standup", "cem_mpc", 300): (163e3, 495),
    ("humanoid_standup", "icem", 500): (416e3, 1.8e3), ("humanoid_standup", "cem_mpc", 500): (164e3, 158),
    ("fetch_pick_place_sparse", "icem", 100): (0.81, None), ("fetch_pick_place_sparse", "cem_mpc", 100): (0.29, None),
    ("fetch_pick_place_sparse", "icem", 300): (0.95, None), ("fetch_pick_place_sparse", "cem_mpc", 300): (0.64, None),
    ("fetch_pick_place_sparse", "icem", 500): (0.96, None), ("fetch_pick_place_sparse", "cem_mpc", 500): (0.75, None),
    ("door", "icem", 100): (1.0, None), ("door", "cem_mpc", 100): (1.0, None),
    ("door", "icem", 300): (1.0, None), ("door", "cem_mpc", 300): (1.0, None),
    ("door", "icem", 500): (1.0, None), ("door", "cem_mpc", 500): (1.0, None),
    ("door_sparse", "icem", 100): (0.96, None), ("door_sparse", "cem_mpc", 100): (0.0, None),
    ("door_sparse", "icem", 300): (0.96, None), ("door_sparse", "cem_mpc", 300): (0.0, None),
    ("door_sparse", "icem", 500): (0.98, None), ("door_sparse", "cem_mpc", 500): (0.0, None),
    ("relocate", "icem", 100): (0.9, None), ("relocate", "cem_mpc", 100): (0.0, None),
    ("relocate", "icem", 300): (1.0, None), ("relocate", "cem_mpc", 300): (0.22, None),
    ("relocate", "icem", 500): (1.0, None), ("relocate", "cem_mpc", 500): (0.62, None),
}  # fmt: skip
SUCCESS_TASKS = {"fetch_pick_place_sparse", "door", "door_sparse", "relocate"}

# Table 2: seconds per environment step of iCEM with MuJoCo (Xeon Gold 6154), by (task, threads, budget).
PUBLISHED_SECONDS_PER_STEP: dict[tuple[str, int, int], float] = {
    ("halfcheetah_running", 1, 100): 0.326, ("halfcheetah_running", 1, 300): 0.884,
    ("halfcheetah_running", 1, 500): 1.520, ("halfcheetah_running", 1, 2000): 5.851,
    ("halfcheetah_running", 32, 100): 0.027, ("halfcheetah_running", 32, 300): 0.066,
    ("halfcheetah_running", 32, 500): 0.109, ("halfcheetah_running", 32, 2000): 0.399,
    ("humanoid_standup", 1, 100): 2.745, ("humanoid_standup", 1, 300): 8.811,
    ("humanoid_standup", 1, 500): 13.259, ("humanoid_standup", 1, 2000): 47.469,
    ("humanoid_standup", 32, 100): 0.163, ("humanoid_standup", 32, 300): 0.456,
    ("humanoid_standup", 32, 500): 0.719, ("humanoid_standup", 32, 2000): 2.79,
    ("fetch_pick_place_sparse", 1, 100): 8.391, ("fetch_pick_place_sparse", 1, 300): 26.988,
    ("fetch_pick_place_sparse", 1, 500): 40.630, ("fetch_pick_place_sparse", 1, 2000): 166.223,
    ("fetch_pick_place_sparse", 32, 100): 0.368, ("fetch_pick_place_sparse", 32, 300): 1.068,
    ("fetch_pick_place_sparse", 32, 500): 1.573, ("fetch_pick_place_sparse", 32, 2000): 6.010,
}  # fmt: skip


class TrialResult(NamedTuple):
    """One finished trial, reduced to what reports need."""

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
    overrides = {
        key.removeprefix(OVERRIDE_PREFIX): json.loads(value)
        for key, value in run.tags.items()
        if key.startswith(OVERRIDE_PREFIX)
    }
    return TrialResult(
        trial_key=run.trial_key,
        task=run.params.get("task", run.tags.get("task", "?")),
        method=method,
        seed=int(run.params.get("seed", "0")),
        labels=labels,
        variant=run.tags.get(TAG_VARIANT),
        overrides=overrides,
        values=dict(run.metrics),
        params=dict(run.params),
    )


class Group(NamedTuple):
    """The trials of one configuration (all its seeds)."""

    task: str
    method: str
    labels: dict[str, str]
    variant: str | None
    setting: dict[str, Any]
    """Swept values that define the configuration, beyond the labels."""
    trials: list[TrialResult]
    mean: float
    """Mean of the sweep's metric over the trials."""
    sem: float
    """Standard error of that mean (0 with one trial)."""
    published: tuple[float, float | None] | None
    """The thesis's figure for this configuration, if it has one."""

    @property
    def n(self) -> int:
        return len(self.trials)

    def value(self, key: str) -> float | None:
        values = [t.values[key] for t in self.trials if key in t.values]
        return float(np.mean(values)) if values else None

    def name(self) -> str:
        parts = [*self.labels.values()]
        if self.variant:
            parts.append(self.variant)
        parts += [f"{k}={v}" for k, v in self.setting.items()]
        return " ".join(parts) or self.method


class Summary(NamedTuple):
    groups: list[Group]
    metric: str
    """The sweep's metric (e.g. episode_return)."""
    summary_key: str
    """The trial summary metric that holds it (e.g. mean_return)."""
    mode: str
    best: int | None
    """Index of the best group by the metric and mode."""


def _published(task: str, method: str, params: dict[str, str], metric: str) -> tuple[float, float | None] | None:
    if method != "mpc":
        return None
    budget = params.get("planner.budget", "None")
    if budget == "None":
        return None
    entry = PUBLISHED.get((task, params.get("planner.algorithm", "?"), int(budget)))
    if entry is None:
        return None
    # Table 3 gives success rates for success tasks and returns for the others.
    is_success = task in SUCCESS_TASKS
    return entry if (metric == "success") == is_success else None


def summarize(runs: Iterable[TrialRun], metric: str, mode: str = "max") -> Summary:
    """Group finished trial runs by configuration and summarise the sweep's metric per group."""
    results = [result_from_run(run) for run in runs]
    method = results[0].method if results else "mpc"
    program = METHODS.get(method)
    summary_key = (program.metrics if program else {}).get(metric, metric)
    covered = {"task", *(path for paths in (program.label_paths if program else {}).values() for path in paths)}
    grouped: dict[tuple, list[TrialResult]] = defaultdict(list)
    for result in results:
        setting = {k: v for k, v in result.overrides.items() if k not in covered}
        key = (result.task, result.method, tuple(result.labels.items()), result.variant or "", json.dumps(setting, sort_keys=True))
        grouped[key].append(result)
    groups = []
    for (task, method_name, labels, variant, setting), members in grouped.items():
        values = np.array([m.values.get(summary_key, math.nan) for m in members], dtype=float)
        values = values[np.isfinite(values)]
        mean = float(values.mean()) if len(values) else math.nan
        sem = float(values.std(ddof=1) / math.sqrt(len(values))) if len(values) > 1 else 0.0
        groups.append(
            Group(
                task, method_name, dict(labels), variant or None, json.loads(setting), members, mean, sem,
                _published(task, method_name, members[0].params, metric),
            )
        )  # fmt: skip
    groups.sort(key=lambda g: (g.task, _sort_labels(g.labels), g.variant or "", json.dumps(g.setting, sort_keys=True)))
    finite = [i for i, g in enumerate(groups) if math.isfinite(g.mean)]
    best = None
    if finite:
        pick = max if mode == "max" else min
        best = pick(finite, key=lambda i: groups[i].mean)
    return Summary(groups, metric, summary_key, mode, best)


def _sort_labels(labels: dict[str, str]) -> tuple:
    return tuple((k, int(v)) if v.isdigit() else (k, 0, v) for k, v in labels.items())


def _published_text(group: Group, metric: str) -> str:
    if group.published is None:
        return "-"
    value, spread = group.published
    if metric == "success":
        return f"{value:.2f}"
    return f"{value:.0f} +- {spread:.0f}" if spread is not None else f"{value:.0f}"


def _figure_text(value: float, metric: str) -> str:
    return f"{value:.2f}" if metric == "success" else f"{value:.1f}"


def format_table(summary: Summary) -> str:
    """A plain-text table, one line per configuration, best marked, with the thesis's figure."""
    metric = summary.metric
    header = ("task", "configuration", "n", f"{metric} (mean +- sem)", "s/step", "thesis")
    rows = [header]
    for index, g in enumerate(summary.groups):
        seconds = g.value("mean_planning_seconds_per_step")
        figure = f"{_figure_text(g.mean, metric)} +- {_figure_text(g.sem, metric)}"
        if index == summary.best and len(summary.groups) > 1:
            figure += " *"
        rows.append((
            g.task, g.name(), str(g.n), figure,
            "-" if seconds is None else f"{seconds:.3f}",
            _published_text(g, metric),
        ))  # fmt: skip
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    if summary.best is not None and len(summary.groups) > 1:
        lines.append(f"* best by {metric} ({summary.mode})")
    return "\n".join(lines)


def to_csv(summary: Summary) -> str:
    import csv
    import io

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    label_keys = sorted({k for g in summary.groups for k in g.labels})
    setting_keys = sorted({k for g in summary.groups for k in g.setting})
    writer.writerow(
        ["task", "method", *label_keys, "variant", *setting_keys, "trials", f"{summary.metric}_mean",
         f"{summary.metric}_sem", "seconds_per_step", "published", "published_spread", "best"]
    )  # fmt: skip
    for index, g in enumerate(summary.groups):
        seconds = g.value("mean_planning_seconds_per_step")
        published, spread = g.published if g.published else ("", "")
        writer.writerow(
            [g.task, g.method, *[g.labels.get(k, "") for k in label_keys], g.variant or "",
             *[g.setting.get(k, "") for k in setting_keys], g.n, f"{g.mean:.6g}", f"{g.sem:.6g}",
             "" if seconds is None else f"{seconds:.5f}", published, "" if spread is None else spread,
             int(index == summary.best)]
        )  # fmt: skip
    return buffer.getvalue()


def budget_figure(summary: Summary):
    """Metric against budget, one line per algorithm and variant (the style of the thesis's Fig. 5).

    Filled markers with error bars are this sweep; hollow markers are Table 3.
    """
    groups = [g for g in summary.groups if g.labels.get("budget", "None").isdigit()]
    tasks = sorted({g.task for g in groups})
    figure, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 3.8), squeeze=False)
    for axis, task in zip(axes[0], tasks):
        lines: dict[str, list[Group]] = defaultdict(list)
        for g in groups:
            if g.task == task:
                name = " ".join([g.labels.get("algorithm", g.method), g.variant or "", *[f"{k}={v}" for k, v in g.setting.items()]])
                lines[name.strip()].append(g)
        for name, members in sorted(lines.items()):
            members.sort(key=lambda g: int(g.labels["budget"]))
            budgets = [int(g.labels["budget"]) for g in members]
            line = axis.errorbar(budgets, [g.mean for g in members], yerr=[g.sem for g in members],
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


def variant_figure(summary: Summary):
    """One bar per variant with its standard error, per task (the style of the thesis's Fig. 7 ablations)."""
    tasks = sorted({g.task for g in summary.groups})
    figure, axes = plt.subplots(len(tasks), 1, figsize=(8, 0.5 + 0.45 * len(summary.groups)), squeeze=False)
    for axis, task in zip(axes[:, 0], tasks):
        members = [g for g in summary.groups if g.task == task]
        names = [g.name() for g in members]
        positions = np.arange(len(members))
        axis.barh(positions, [g.mean for g in members], xerr=[g.sem for g in members], capsize=3, color="tab:blue")
        axis.set_yticks(positions, names)
        axis.invert_yaxis()
        axis.set_xlabel(summary.metric.replace("_", " "))
        axis.set_title(f"{task}: variants (mean +- sem over seeds)")
        axis.grid(alpha=0.3, axis="x")
    figure.tight_layout()
    return figure


def write_files(summary: Summary, directory: Path) -> list[Path]:
    """summary.txt, summary.csv and the plots that fit the sweep, in ``directory``; returns their paths."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = [directory / "summary.txt", directory / "summary.csv"]
    paths[0].write_text(format_table(summary) + "\n")
    paths[1].write_text(to_csv(summary))
    if not summary.groups:
        return paths
    if any(g.labels.get("budget", "None").isdigit() for g in summary.groups):
        figure = budget_figure(summary)
        paths.append(directory / "budget_curve.png")
        figure.savefig(paths[-1], dpi=110)
        plt.close(figure)
    if any(g.variant for g in summary.groups):
        figure = variant_figure(summary)
        paths.append(directory / "variants.png")
        figure.savefig(paths[-1], dpi=110)
        plt.close(figure)
    if any(g.method == "mbrl" for g in summary.groups):
        from orchestrator import report_mbrl  # chapter 5's figures (Fig. 19a/b, 37a)

        paths += report_mbrl.write_files(summary, directory)
    return paths
