"""Tables and plots of sweep results, next to the thesis's published numbers.

Pure functions of plain records: the scheduler feeds them finished trials, the
``report`` command feeds them runs read back from MLflow.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable
from typing import NamedTuple

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

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
    algorithm: str
    budget: int
    seed: int
    episode_return: float
    """Mean return over the trial's episodes."""
    success: float | None
    """Success rate over the trial's episodes (None: task without success)."""
    seconds_per_step: float
    """Mean planning seconds per environment step."""


class GroupSummary(NamedTuple):
    """All seeds of one (task, algorithm, budget) configuration."""

    task: str
    algorithm: str
    budget: int
    trials: int
    return_mean: float
    return_sem: float
    success_rate: float | None
    seconds_per_step: float
    published: tuple[float, float | None] | None


def summarize(results: Iterable[TrialResult]) -> list[GroupSummary]:
    groups: dict[tuple[str, str, int], list[TrialResult]] = defaultdict(list)
    for result in results:
        groups[(result.task, result.algorithm, result.budget)].append(result)
    summaries = []
    for (task, algorithm, budget), members in sorted(groups.items()):
        returns = np.array([m.episode_return for m in members])
        successes = [m.success for m in members if m.success is not None]
        summaries.append(
            GroupSummary(
                task=task,
                algorithm=algorithm,
                budget=budget,
                trials=len(members),
                return_mean=float(returns.mean()),
                return_sem=float(returns.std(ddof=1) / math.sqrt(len(returns))) if len(returns) > 1 else 0.0,
                success_rate=float(np.mean(successes)) if successes else None,
                seconds_per_step=float(np.mean([m.seconds_per_step for m in members])),
                published=PUBLISHED.get((task, algorithm, budget)),
            )
        )
    return summaries


def _published_text(group: GroupSummary) -> str:
    if group.published is None:
        return "-"
    value, spread = group.published
    if group.task in SUCCESS_TASKS:
        return f"{value:.2f} success"
    return f"{value:.0f} +- {spread:.0f}" if spread is not None else f"{value:.0f}"


def format_table(groups: list[GroupSummary]) -> str:
    """A plain-text table, one line per configuration, with the thesis's Table 3 figure."""
    header = ("task", "algorithm", "budget", "n", "return (mean +- sem)", "success", "s/step", "thesis (Table 3)")
    rows = [header]
    for g in groups:
        rows.append((
            g.task, g.algorithm, str(g.budget), str(g.trials),
            f"{g.return_mean:.1f} +- {g.return_sem:.1f}",
            "-" if g.success_rate is None else f"{g.success_rate:.2f}",
            f"{g.seconds_per_step:.3f}",
            _published_text(g),
        ))  # fmt: skip
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def to_csv(groups: list[GroupSummary]) -> str:
    lines = ["task,algorithm,budget,trials,return_mean,return_sem,success_rate,seconds_per_step,published"]
    for g in groups:
        published = "" if g.published is None else str(g.published[0])
        success = "" if g.success_rate is None else f"{g.success_rate:.4f}"
        lines.append(
            f"{g.task},{g.algorithm},{g.budget},{g.trials},{g.return_mean:.4f},{g.return_sem:.4f},"
            f"{success},{g.seconds_per_step:.5f},{published}"
        )
    return "\n".join(lines) + "\n"


def budget_figure(groups: list[GroupSummary], metric: str = "episode_return"):
    """Performance against budget per algorithm and task (the style of the thesis's Fig. 5).

    Filled markers with error bars are this sweep; hollow markers are Table 3.
    """
    tasks = sorted({g.task for g in groups})
    figure, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 3.8), squeeze=False)
    for axis, task in zip(axes[0], tasks):
        use_success = metric == "success" or (task in SUCCESS_TASKS and metric != "episode_return")
        for algorithm in sorted({g.algorithm for g in groups if g.task == task}):
            members = sorted((g for g in groups if g.task == task and g.algorithm == algorithm), key=lambda g: g.budget)
            budgets = [g.budget for g in members]
            if use_success:
                values, errors = [g.success_rate or 0.0 for g in members], None
            else:
                values, errors = [g.return_mean for g in members], [g.return_sem for g in members]
            line = axis.errorbar(budgets, values, yerr=errors, marker="o", capsize=3, label=algorithm)
            published = [(g.budget, g.published[0]) for g in members if g.published]
            if published:
                axis.plot(*zip(*published), linestyle="none", marker="s", markerfacecolor="none",
                          color=line[0].get_color(), label=f"{algorithm} (thesis)")  # fmt: skip
        axis.set_xscale("log")
        budgets = sorted({g.budget for g in groups if g.task == task})
        axis.set_xticks(budgets, [str(b) for b in budgets])
        axis.minorticks_off()
        axis.set_xlabel("budget (trajectories per step)")
        axis.set_ylabel("success rate" if use_success else "episode return")
        axis.set_title(task)
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    figure.tight_layout()
    return figure


def episode_figure(title: str, rewards: np.ndarray, planning_seconds: np.ndarray):
    """Reward, return and planning time per step of one episode."""
    figure, axes = plt.subplots(1, 3, figsize=(13, 3.2))
    steps = np.arange(len(rewards))
    axes[0].plot(steps, rewards)
    axes[0].set_title("reward per step")
    axes[1].plot(steps, np.cumsum(rewards))
    axes[1].set_title("return so far")
    axes[2].plot(steps, planning_seconds)
    axes[2].set_title("planning seconds per step")
    for axis in axes:
        axis.set_xlabel("environment step")
        axis.grid(alpha=0.3)
    figure.suptitle(title)
    figure.tight_layout()
    return figure


def close(figure) -> None:
    plt.close(figure)
