"""Roll a trained policy checkpoint in the real environment (the ``icemlab policy`` command)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from workers.checkpoint import CheckpointError
from workers.policy.network import Policy, PolicyWeights

FRAMES_IN_STRIP = 8


class PolicyCheckpointError(ValueError):
    """A file that is not a policy checkpoint of the requested task."""


class PolicyRollouts(NamedTuple):
    task: str
    version: int
    returns: list[float]
    successes: list[bool | None]
    steps: int
    """Steps per episode."""
    frames_note: str | None
    """Where the frame strip went, or why there is none."""


CHAPTER_4_EPISODE_STEPS: dict[str, int] = {"humanoid_standup": 500}
"""Episode lengths that chapter 4 changes (section 4.4: Humanoid standup runs 500 steps)."""


def read_checkpoint(path: str | Path, task: str | None) -> Policy:
    """The policy in ``path``; refuses files that are not policy checkpoints, or of another task than ``task``."""
    from workers.tasks import TASKS, unknown_task_message

    path = Path(path)
    try:
        weights = PolicyWeights.from_bytes(path.read_bytes())
        policy = Policy(weights)
    except OSError as error:
        raise PolicyCheckpointError(f"{path}: cannot read: {error.strerror or error}") from None
    except (CheckpointError, KeyError, ValueError, TypeError) as error:  # a damaged or foreign file, whichever way
        reason = f"{type(error).__name__}: {error}"
        raise PolicyCheckpointError(f"{path}: not an APEX policy checkpoint ({reason})") from None
    if weights.task and weights.task not in TASKS:
        raise PolicyCheckpointError(f"{path}: the checkpoint's task: {unknown_task_message(weights.task)}")
    if task is not None and weights.task and weights.task != task:
        raise PolicyCheckpointError(
            f"{path}: a policy of task {weights.task!r}, not {task!r}; roll it on {weights.task} (drop --task)"
        )
    if not weights.task and task is None:
        raise PolicyCheckpointError(f"{path}: the checkpoint does not name its task; give --task")
    return policy


def _render_env(task, steps: int):
    """A real environment of the task that renders rgb frames, or (None, reason)."""
    import gymnasium as gym

    from workers.tasks.base import register_robotics_envs

    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        register_robotics_envs()
        env = gym.make(
            task.env_id, max_episode_steps=steps, render_mode="rgb_array", width=240, height=180, **task.env_kwargs
        )
        env.reset(seed=0)
        if env.render() is None:
            raise RuntimeError("the environment returned no frame")
        return env, None
    except Exception as error:  # noqa: BLE001 - any GL failure means: no frames here
        reason = str(error).strip().splitlines()[-1][:160] if str(error).strip() else type(error).__name__
        return None, (
            f"no frames: MuJoCo cannot render headless here with MUJOCO_GL={os.environ.get('MUJOCO_GL')} "
            f"({type(error).__name__}: {reason}); try MUJOCO_GL=osmesa or egl with the system's GL libraries"
        )


def roll_policy(
    path: str | Path,
    task_name: str | None = None,
    episodes: int = 1,
    seed: int = 0,
    steps: int | None = None,
    frames: str | Path | None = None,
    task_options: dict[str, Any] | None = None,
) -> PolicyRollouts:
    """Roll the policy of a checkpoint for ``episodes`` episodes (seeds seed, seed + 1, ...) of ``steps`` steps
    (default: as long as chapter 4's episodes of the task, which APEX trains and evaluates on)."""
    from workers.tasks import make_task

    policy = read_checkpoint(path, task_name)
    task = make_task(task_name or policy.task, task_options)
    steps = steps or CHAPTER_4_EPISODE_STEPS.get(task.name, task.episode_length)
    env = task.make_env()
    note = None
    render_env = None
    if frames is not None:
        render_env, note = _render_env(task, steps)
    returns, successes = [], []
    try:
        for episode in range(episodes):
            current = render_env if (episode == 0 and render_env is not None) else env
            observation, _ = current.reset(seed=seed + episode)
            vector = task.observe(observation)
            if vector.shape[0] != policy.obs_dim:
                raise PolicyCheckpointError(
                    f"{path}: the policy takes {policy.obs_dim} observation values, {task.name} gives {vector.shape[0]}"
                )
            strip, total, flags = [], 0.0, []
            for t in range(steps):
                if current is render_env and t % max(1, steps // FRAMES_IN_STRIP) == 0:
                    strip.append(current.render())
                outcome = task.step_env(current, policy(vector))
                total += outcome.reward
                flags.append(outcome.goal_achieved)
                vector = task.observe(outcome.observation)
            returns.append(total)
            achieved = [f for f in flags if f is not None]
            successes.append(task.episode_success(achieved) if task.has_success else None)
            if strip:
                import matplotlib

                matplotlib.use("Agg")
                import matplotlib.pyplot as plt

                plt.imsave(str(frames), np.concatenate(strip[:FRAMES_IN_STRIP], axis=1))
                note = f"frames of episode 0 in {frames}"
    finally:
        env.close()
        if render_env is not None:
            render_env.close()
    return PolicyRollouts(task.name, policy.version, returns, successes, steps, note)
