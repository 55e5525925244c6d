"""Plots of chapter 5's sweeps (``mbrl``, and ``mpc`` on noisy-simulator ensembles), as pure functions of
summarised trial runs.

* :func:`success_figure`: success rate of the frozen model against the aleatoric penalty weight w_A, PETS
  as a reference line (Fig. 19a), mean +- sem over the seeds of each configuration.
* :func:`drop_rate_figure`: the rate of failures (box drops, else falls) of each frozen row against a swept
  task option such as the noise strength (Fig. 19b).
* :func:`coverage_figure`: final state coverage of each configuration (the end point of Fig. 37a); the whole
  coverage-over-iterations curves are among the program's report curves (``MbrlProgram.curves``).
* :func:`penalty_figure`: the sweep's metric against ``ensemble.aleatoric_weight`` for ``mpc`` sweeps that plan
  on an ensemble of noisy simulators (Noisy-FetchPickAndPlace: box drops against w_A, Fig. 19b as drawn).
* :func:`noise_figure`: the same sweeps' metric against a swept noise option, one line per w_A (Fig. 19b as its
  caption reads: a fixed w_A, the noise varied).

The frozen rows come from the trials' summary metrics ``frozen/<row>/<key>`` (workers/methods/mbrl.py):
``pets``, ``razer_wA_<w>`` and ``razer_wA_<w>_means`` (Var_A read at the mean states) rows with
``success_rate``, ``mean_return``, ``falls_rate``, ``box_drops_rate``, ``aleatoric_weight``.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from orchestrator import statistics  # noqa: E402
from workers.methods.mbrl import MEANS_ROW_SUFFIX  # noqa: E402

FAILURE_KEYS = ("box_drops_rate", "falls_rate")
"""Failure rates of frozen rows, in order of preference (Noisy-FetchPickAndPlace drops boxes, BridgeMaze falls)."""


class FrozenPoint(NamedTuple):
    """One frozen-evaluation row of one configuration, over its trials (seeds)."""

    row: str
    """Row name: ``pets``, ``razer_wA_<w>`` or ``razer_wA_<w>_means``."""
    pets: bool
    aleatoric_weight: float
    values: dict[str, tuple[float, float, int]]
    """key -> (mean, sem, trials) over the configuration's trials."""

    @property
    def aleatoric_states(self) -> str:
        """Where the row read Var_A: ``means`` for the ``_means`` rows, else ``particles`` (eq. 22)."""
        return "means" if self.row.endswith(MEANS_ROW_SUFFIX) else "particles"

    def mean(self, key: str) -> float | None:
        return self.values[key][0] if key in self.values else None


def _mean_sem(values: Sequence[float]) -> tuple[float, float, int]:
    array = np.asarray([v for v in values if math.isfinite(v)], dtype=float)
    if not len(array):
        return math.nan, math.nan, 0
    sem = float(array.std(ddof=1) / math.sqrt(len(array))) if len(array) > 1 else 0.0
    return float(array.mean()), sem, len(array)


def frozen_points(trials: Iterable[Any]) -> list[FrozenPoint]:
    """The frozen rows of a configuration's trials (objects with a ``values`` dict of summary metrics)."""
    collected: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for trial in trials:
        for key, value in trial.values.items():
            parts = key.split("/")
            if len(parts) == 3 and parts[0] == "frozen":
                collected[parts[1]][parts[2]].append(float(value))
    points = []
    for row, keys in collected.items():
        values = {key: _mean_sem(v) for key, v in keys.items()}
        pets = bool(values.get("pets", (0.0,))[0]) or row == "pets"
        weight = values.get("aleatoric_weight", (0.0,))[0]
        points.append(FrozenPoint(row, pets, float(weight), values))
    points.sort(key=lambda p: (not p.pets, p.aleatoric_states == "means", p.aleatoric_weight))
    return points


def _configuration(group: Any) -> list[str]:
    """What names a group beside its swept settings: its labels (planner algorithm and budget, model preset: the
    report keeps them out of the settings, so lines named by settings alone would join groups that differ there)
    and its variant."""
    return [*group.label_parts(), group.variant or ""]


def _label(group: Any) -> str:
    parts = [*_configuration(group), *[f"{k}={v}" for k, v in group.setting.items()]]
    return " ".join(p for p in parts if p) or group.task


def _rate_error(point: FrozenPoint, key: str) -> tuple[float, float]:
    """(below, above) the row's mean rate: the sem over seeds, widened to at least the Wilson 95% interval of
    all their frozen episodes pooled. A rate over 25 episodes has an error even when no second seed shows it, or
    when two seeds happen to agree (a zero sem); where the seeds disagree more than their episodes explain, the
    sem is the wider."""
    mean, sem, n = point.values[key]
    episodes = point.mean("episodes")
    if not n:  # no seed has a finite rate: nothing to draw a bar for
        return 0.0, 0.0
    if not (episodes and episodes >= 1):
        return sem, sem
    pooled = int(round(episodes * n))
    interval = statistics.rate_interval(int(round(mean * pooled)), pooled)
    return max(sem, mean - interval.low), max(sem, interval.high - mean)


def _bars(points: Sequence[FrozenPoint], key: str) -> list[list[float]]:
    errors = [_rate_error(p, key) for p in points]
    return [[below for below, _ in errors], [above for _, above in errors]]


def success_figure(summary: Any):
    """Fig. 19a: frozen success rate (and mean return) against w_A per configuration; None without frozen rows."""
    groups = [(g, frozen_points(g.trials)) for g in summary.groups]
    groups = [(g, points) for g, points in groups if any("success_rate" in p.values for p in points)]
    if not groups:
        return None
    figure, (success_axis, return_axis) = plt.subplots(1, 2, figsize=(11, 4))
    for group, points in groups:
        label = _label(group)
        color = None
        for states in ("particles", "means"):  # one line each: the two read Var_A at different states
            razer = [p for p in points if not p.pets and p.aleatoric_states == states and "success_rate" in p.values]
            if not razer:
                continue
            name = f"RAZER {label}".strip() + (" (Var_A at mean states)" if states == "means" else "")
            line = success_axis.errorbar(
                [p.aleatoric_weight for p in razer],
                [p.values["success_rate"][0] for p in razer],
                yerr=_bars(razer, "success_rate"),
                marker="o" if states == "particles" else "s", capsize=3, label=name,
            )  # fmt: skip
            color = color or line[0].get_color()
            if all("mean_return" in p.values for p in razer):
                return_axis.errorbar(
                    [p.aleatoric_weight for p in razer],
                    [p.values["mean_return"][0] for p in razer],
                    yerr=[p.values["mean_return"][1] for p in razer],
                    marker="o" if states == "particles" else "s", capsize=3, color=line[0].get_color(), label=name,
                )  # fmt: skip
        for p in points:
            if p.pets and "success_rate" in p.values:
                mean, _, n = p.values["success_rate"]
                success_axis.axhline(
                    mean, linestyle="--", color=color or "tab:red", label=f"PETS {label} (n={n})".strip()
                )
                below, above = _rate_error(p, "success_rate")
                if below or above:
                    success_axis.axhspan(mean - below, mean + above, color=color or "tab:red", alpha=0.1)
                if "mean_return" in p.values:
                    return_axis.axhline(p.values["mean_return"][0], linestyle="--", color=color or "tab:red")
    for axis, name in ((success_axis, "success rate"), (return_axis, "mean return")):
        axis.set_xlabel("aleatoric penalty weight w_A")
        axis.set_ylabel(name)
        axis.grid(alpha=0.3)
    success_axis.set_ylim(-0.02, 1.02)
    success_axis.set_title("frozen model: success, +- sem over seeds, at least Wilson 95% over their episodes\n"
                           "(thesis Fig. 19a: PETS 0.58, RAZER up to 0.96)", fontsize=9)  # fmt: skip
    return_axis.set_title("frozen model: return, +- sem over seeds (dashed: PETS)", fontsize=9)
    success_axis.legend(fontsize=7)
    figure.tight_layout()
    return figure


def _finished(figure, axis, title: str):
    """Title, grid and legend of a one-axis chapter 5 figure, laid out."""
    axis.set_title(title, fontsize=9)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    return figure


def _task_option(group: Any, option: str) -> float | None:
    """The value of a task option all of a group's trials ran with, from their logged settings (a group that ran
    the option's default has no swept setting that says it); None when it varies or is not logged."""
    values = {trial.params.get(option) for trial in group.trials}
    if len(values) != 1 or None in values:
        return None
    try:
        return float(values.pop())
    except ValueError:
        return None


def _logged_task_option(summary: Any) -> str | None:
    """The numeric task option the groups ran with different values of (the noise strength), if exactly one."""
    keys = {key for g in summary.groups for t in g.trials for key in t.params if key.startswith("task_options.")}
    swept = [key for key in sorted(keys) if len({_task_option(g, key) for g in summary.groups} - {None}) > 1]
    return swept[0] if len(swept) == 1 else None


def drop_rate_figure(summary: Any, option: str | None = None):
    """Fig. 19b: failure rate of each frozen row against a task option the configurations ran with different
    values of (read from the trials' logged settings, as :func:`noise_figure` reads it: a configuration that ran
    the option's default is placed too); None when nothing fits."""
    option = option or _logged_task_option(summary)
    if option is None:
        return None
    lines: dict[str, list[tuple[float, float, float]]] = defaultdict(list)
    key_used = None
    for group in summary.groups:
        x = _task_option(group, option)
        if x is None:
            continue
        for point in frozen_points(group.trials):
            key = next((k for k in FAILURE_KEYS if k in point.values), None)
            if key is None:
                continue
            key_used = key_used or key
            mean = point.values[key][0]
            below, above = _rate_error(point, key)
            rest = " ".join(f"{k}={v}" for k, v in group.setting.items() if k != option)
            lines[" ".join(filter(None, [point.row, *_configuration(group), rest]))].append((x, mean, below, above))
    if not lines:
        return None
    figure, axis = plt.subplots(figsize=(6, 4))
    for name, values in sorted(lines.items()):
        values.sort()
        axis.errorbar([v[0] for v in values], [v[1] for v in values],
                      yerr=[[v[2] for v in values], [v[3] for v in values]], marker="o", capsize=3,
                      label=name)  # fmt: skip
    axis.set_xlabel(option.removeprefix("task_options."))
    axis.set_ylabel(key_used.replace("_", " "))
    axis.set_ylim(-0.02, 1.02)
    return _finished(figure, axis, f"frozen rows: failure rate against {option.removeprefix('task_options.')}, "
                     "+- sem over seeds, at least Wilson 95% over their episodes (thesis Fig. 19b: RAZER < 0.2)")


def coverage_figure(summary: Any):
    """Final state coverage per configuration (the end of Fig. 37a), mean +- sem over seeds; None without it."""
    rows = []
    for group in summary.groups:
        mean, sem, n = _mean_sem([t.values["final_coverage"] for t in group.trials if "final_coverage" in t.values])
        if n:
            rows.append((_label(group), mean, sem, n))
    if not rows:
        return None
    figure, axis = plt.subplots(figsize=(7, 0.6 + 0.45 * len(rows)))
    positions = np.arange(len(rows))
    axis.barh(positions, [r[1] for r in rows], xerr=[r[2] for r in rows], capsize=3, color="tab:green")
    axis.set_yticks(positions, [f"{r[0]} (n={r[3]})" for r in rows])
    axis.invert_yaxis()
    axis.set_xlabel("state coverage after the last iteration (fraction of 50 x 50 cells), +- sem over seeds")
    axis.grid(alpha=0.3, axis="x")
    figure.tight_layout()
    return figure


PENALTY_SETTING = "ensemble.aleatoric_weight"
"""The sweep setting that is RAZER's w_A when ``mpc`` plans on a noisy-simulator ensemble (w_A = 0: PETS)."""
PARTICLES_SETTING = "ensemble.particles"
"""Particles per sequence: a line's drop rate depends on it (docs/results/razer.md, Fig. 19b), so every line names it."""


def _particles(group: Any) -> str:
    """``ensemble.particles=P`` of a group whose trials all ran with P particles, from the resolved settings
    (a count set in the sweep's base is no swept setting); empty when the setting names it or it varies."""
    if PARTICLES_SETTING in group.setting:
        return ""
    counts = {trial.params.get(PARTICLES_SETTING) for trial in group.trials}
    return f"{PARTICLES_SETTING}={counts.pop()}" if len(counts) == 1 and None not in counts else ""


def penalty_figure(summary: Any):
    """Fig. 19b as the thesis draws it: the sweep's metric against w_A, one line per other setting; None unless
    the configurations differ in w_A. Bars are the groups' 95% intervals (Wilson over episodes for rates)."""
    weights = {g.setting[PENALTY_SETTING] for g in summary.groups if PENALTY_SETTING in g.setting}
    if len(weights) < 2:
        return None
    lines: dict[str, list[Any]] = defaultdict(list)
    for group in summary.groups:
        if PENALTY_SETTING in group.setting:
            rest = " ".join(f"{k}={v}" for k, v in sorted(group.setting.items()) if k != PENALTY_SETTING)
            # The variant is left out: in these sweeps it names the penalty, the x-axis.
            lines[" ".join(filter(None, [group.task, *group.label_parts(), _particles(group), rest]))].append(group)
    points = {name: [(g.setting[PENALTY_SETTING], g) for g in members] for name, members in lines.items()}
    return _group_lines_figure(points, "aleatoric penalty w_A (0: PETS)", summary.metric,
                               "against the aleatoric penalty (thesis Fig. 19b: RAZER's drop rate < 0.2)")  # fmt: skip


def _group_lines_figure(lines: dict[str, list[tuple[float, Any]]], xlabel: str, metric: str, title: str):
    """One line per name through its (x, group) points: the groups' means with their 95% intervals as bars
    (Wilson over episodes for rates, whose axis then spans 0-1)."""
    figure, axis = plt.subplots(figsize=(6, 4))
    for name, points in sorted(lines.items()):
        points = sorted(points, key=lambda point: point[0])
        axis.errorbar([x for x, _ in points], [g.mean for _, g in points],
                      yerr=statistics.error_bars([g.interval for _, g in points]), marker="o", capsize=3,
                      label=name)  # fmt: skip
    axis.set_xlabel(xlabel)
    axis.set_ylabel(metric.replace("_", " "))
    if all(g.successes is not None for points in lines.values() for _, g in points):
        axis.set_ylim(-0.02, 1.02)
    return _finished(figure, axis, title)


def noise_figure(summary: Any):
    """Fig. 19b as its caption and text read it (a fixed w_A, "even when considerable noise is applied"): the
    sweep's metric against the noise, a swept task option such as ``task_options.noise_std``, one line per w_A
    (0: PETS); None unless the configurations plan on a noisy-simulator ensemble and differ in one task option.
    Bars are the groups' 95% intervals (Wilson over episodes for rates)."""
    groups = [g for g in summary.groups if PENALTY_SETTING in g.setting]
    option = _logged_task_option(summary) if groups else None
    if option is None:
        return None
    lines: dict[str, list[tuple[float, Any]]] = defaultdict(list)
    for group in groups:
        x = _task_option(group, option)
        if x is None:
            continue
        weight = group.setting[PENALTY_SETTING]
        rest = " ".join(f"{k}={v}" for k, v in sorted(group.setting.items()) if k not in (PENALTY_SETTING, option))
        name = "PETS" if weight == 0 else f"RAZER w_A={weight}"
        lines[" ".join(filter(None, [name, *group.label_parts(), _particles(group), rest]))].append((x, group))
    return _group_lines_figure(lines, option.removeprefix("task_options."), summary.metric,
                               "against the noise (thesis Fig. 19b: RAZER's drop rate < 0.2)")  # fmt: skip


def write_files(summary: Any, directory: Path) -> list[Path]:
    """The chapter 5 plots that fit the sweep (frozen_success.png, failure_rate.png, coverage.png,
    penalty.png, noise.png) in ``directory``."""
    paths = []
    for name, make in (
        ("frozen_success", success_figure),
        ("failure_rate", drop_rate_figure),
        ("coverage", coverage_figure),
        ("penalty", penalty_figure),
        ("noise", noise_figure),
    ):
        figure = make(summary)
        if figure is None:
            continue
        paths.append(directory / f"{name}.png")
        figure.savefig(paths[-1], dpi=110)
        plt.close(figure)
    return paths
