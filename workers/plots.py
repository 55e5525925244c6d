"""Plots that workers draw for their trial's run, returned as PNG bytes."""

from __future__ import annotations

import io

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def to_png(figure) -> bytes:
    """The figure as PNG bytes; the figure is closed."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    plt.close(figure)
    return buffer.getvalue()


def episode_png(title: str, rewards: np.ndarray, planning_seconds: np.ndarray) -> bytes:
    """Reward, return and planning time per step of one MPC episode."""
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
    return to_png(figure)
