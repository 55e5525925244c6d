"""Speed measurements of neural APSP for ``icemlab bench --methods``.

:func:`measure_learner_updates` times :meth:`GoalLearner.update` (HER
sampling from a filled buffer, the reward computed at sampling time through a
distance network, input normalisation, the SAC or DDPG step, polyak steps)
and, back to back in alternating blocks, a bare torch loop that performs the
same gradient steps on the same network shapes with one fixed batch already in
tensors, including the distance network's forward pass for the reward. The
ratio of the two is the share of the update rate that the learner's
bookkeeping leaves; the blocks alternate so the slow phases of a shared
machine hit both alike. :func:`compare_modes` times whole iterations of the
method in its ``sync`` and ``pipelined`` modes, interleaved. No figure is
asserted here.
"""

from __future__ import annotations

import copy
import time
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from workers.distance.buffer import Episodes
from workers.distance.config import LearnerSettings
from workers.distance.learners import Critics, DeterministicActor, GoalLearner, SquashedGaussianActor, default_q_clip
from workers.distance.network import DistanceFunction, mlp
from workers.distance.rewards import DistanceReward, SparseReward


def random_episodes(
    count: int, horizon: int, obs_dim: int, action_dim: int, goal_dim: int, rng: np.random.Generator
) -> Episodes:
    """Random-walk episodes with achieved goals = the first goal_dim observation components."""
    steps = rng.normal(0.0, 0.05, (count, horizon + 1, obs_dim))
    observations = np.cumsum(steps, axis=1)
    achieved = observations[..., :goal_dim].copy()
    return Episodes(
        observations=observations,
        actions=rng.uniform(-1.0, 1.0, (count, horizon, action_dim)),
        achieved_goals=achieved,
        goals=achieved[:, -1] + rng.normal(0.0, 0.1, (count, goal_dim)),
        successes=np.zeros((count, horizon)),
    )


def _bare_step(nets: dict, batch: dict, settings: LearnerSettings, q_clip: float) -> None:
    """One SAC or DDPG step written directly in torch (no buffer, no numpy, no normalisation)."""
    x, a, x2 = batch["inputs"], batch["actions"], batch["next_inputs"]
    if nets["distance"] is None:
        reward = batch["rewards"]
    else:
        with torch.no_grad():
            reward = -nets["distance"](batch["reward_inputs"]).squeeze(-1)
    sac = settings.algorithm == "sac"
    with torch.no_grad():
        if sac:
            a2, logp2 = nets["actor"](x2, torch.randn_like(a))
            next_value = torch.min(*nets["critic_target"](x2, a2)) - 0.1 * logp2
        else:
            a2, _ = nets["actor_target"](x2)
            next_value = nets["critic_target"](x2, a2)[0]
        target = (reward + settings.gamma * next_value).clamp(q_clip, 0.0)
    critic_loss = sum(F.mse_loss(q, target) for q in nets["critic"](x, a))
    nets["critic_opt"].zero_grad(set_to_none=True)
    critic_loss.backward()
    nets["critic_opt"].step()
    nets["critic"].requires_grad_(False)
    if sac:
        new_a, logp = nets["actor"](x, torch.randn_like(a))
        actor_loss = (0.1 * logp - torch.min(*nets["critic"](x, new_a))).mean()
    else:
        new_a, _ = nets["actor"](x)
        actor_loss = -nets["critic"](x, new_a)[0].mean() + settings.action_l2 * new_a.pow(2).mean()
    nets["actor_opt"].zero_grad(set_to_none=True)
    actor_loss.backward()
    nets["actor_opt"].step()
    nets["critic"].requires_grad_(True)
    if sac:
        alpha_loss = -(nets["log_alpha"] * (logp.detach() - a.shape[-1])).mean()
        nets["alpha_opt"].zero_grad(set_to_none=True)
        alpha_loss.backward()
        nets["alpha_opt"].step()


def measure_learner_updates(
    settings: LearnerSettings,
    obs_dim: int,
    action_dim: int,
    goal_dim: int,
    horizon: int = 50,
    updates: int = 100,
    blocks: int = 5,
    reward: str = "distance",
    distance_hidden: tuple[int, ...] = (256, 256, 256),
    episodes: int = 20,
    seed: int = 0,
) -> dict[str, float]:
    """Updates per second of the learner and of a bare torch loop, measured back to back.

    Args:
        settings: learner settings (network sizes, batch, algorithm) for both sides.
        obs_dim, action_dim, goal_dim, horizon: problem sizes.
        updates: updates per side in total, split into ``blocks`` alternating blocks.
        reward: ``distance`` (a randomly initialised d(s, a, g) of ``distance_hidden``, whose forward pass the
            bare loop also runs) or ``sparse`` (the bare loop uses fixed rewards).
        episodes: random episodes in the learner's buffer.
        seed: networks and data.

    Returns:
        learner and bare updates per second (totals over all blocks), their
        ratio, and the median of the per-block ratios.
    """
    rng = np.random.default_rng(seed)
    data = random_episodes(episodes, horizon, obs_dim, action_dim, goal_dim, rng)
    if reward == "distance":
        function = DistanceFunction(obs_dim, action_dim, goal_dim, distance_hidden, seed=seed)
        reward_fn: DistanceReward | SparseReward = DistanceReward(function)
    else:
        reward_fn = SparseReward(lambda achieved, goals: np.linalg.norm(achieved - goals, axis=-1) < 0.05)
    q_clip = default_q_clip(reward_fn.kind, settings.gamma, horizon)
    learner = GoalLearner(settings, obs_dim, action_dim, goal_dim, horizon, reward_fn, q_clip, seed)
    learner.add_episodes(data)

    # The bare loop: the same shapes, one batch made once, everything already in tensors.
    sac = settings.algorithm == "sac"
    torch.manual_seed(seed)
    inputs_dim = obs_dim + goal_dim
    actor = (SquashedGaussianActor if sac else DeterministicActor)(inputs_dim, action_dim, settings.hidden)
    critic = Critics(inputs_dim, action_dim, settings.hidden, 2 if sac else 1)
    log_alpha = torch.zeros((), requires_grad=True)
    nets = {
        "actor": actor,
        "actor_target": copy.deepcopy(actor),
        "critic": critic,
        "critic_target": copy.deepcopy(critic),
        "distance": mlp(obs_dim + action_dim + goal_dim, distance_hidden, 1) if reward == "distance" else None,
        "actor_opt": torch.optim.Adam(actor.parameters(), lr=settings.learning_rate),
        "critic_opt": torch.optim.Adam(critic.parameters(), lr=settings.learning_rate),
        "log_alpha": log_alpha,
        "alpha_opt": torch.optim.Adam([log_alpha], lr=settings.learning_rate),
    }
    size = settings.batch_size
    batch = {
        "inputs": torch.randn(size, inputs_dim),
        "next_inputs": torch.randn(size, inputs_dim),
        "actions": torch.rand(size, action_dim) * 2 - 1,
        "reward_inputs": torch.randn(size, obs_dim + action_dim + goal_dim),
        "rewards": -(torch.rand(size) < 0.8).float(),
    }

    def bare(count: int) -> None:
        for step in range(count):
            _bare_step(nets, batch, settings, q_clip)
            if (step + 1) % settings.target_update_interval == 0:
                with torch.no_grad():
                    for target, online in ((nets["critic_target"], critic), (nets["actor_target"], actor)):
                        for t, o in zip(target.parameters(), online.parameters()):
                            t.mul_(settings.polyak).add_(o, alpha=1 - settings.polyak)

    def learned(count: int) -> None:
        for _ in range(count):
            learner.update()

    learned(2)  # warm-up: first calls allocate
    bare(2)
    per_block = max(1, updates // blocks)
    seconds = {"learner": 0.0, "bare": 0.0}
    ratios = []
    for _ in range(blocks):
        block = {}
        for name, run in (("learner", learned), ("bare", bare)):
            start = time.perf_counter()
            run(per_block)
            block[name] = time.perf_counter() - start
            seconds[name] += block[name]
        ratios.append(block["bare"] / block["learner"])
    total = per_block * blocks
    learner_rate, bare_rate = total / seconds["learner"], total / seconds["bare"]
    return {
        "learner_updates_per_second": learner_rate,
        "bare_updates_per_second": bare_rate,
        "ratio": learner_rate / bare_rate,
        "ratio_median_over_blocks": float(np.median(ratios)),
        "updates_per_side": float(total),
        "torch_threads": float(torch.get_num_threads()),
    }


def compare_modes(programs: dict[str, Any], iterations: int, warmup: int = 1) -> dict[str, Any]:
    """Seconds per iteration of napsp programs that differ only in ``mode``, iterations interleaved.

    Each program must run one iteration per round (``iterations_per_round: 1``)
    and plan at least ``warmup + iterations`` of them. The programs take turns
    iteration by iteration, so the slow phases of a shared machine hit every
    mode alike; the first ``warmup`` iterations of each are not counted (they
    allocate, and a pipelined run's first iteration is in sync order because
    there are no distance weights yet to train on).

    Returns:
        per mode, the median seconds per counted iteration (``time/iteration``
        of the round), plus ``pipelined_over_sync`` when both modes are there.
    """
    seconds: dict[str, list[float]] = {mode: [] for mode in programs}
    for index in range(warmup + iterations):
        for mode, program in programs.items():
            (elapsed,) = program.run_round(index).series["time/iteration"]
            if index >= warmup:
                seconds[mode].append(elapsed)
    result: dict[str, Any] = {
        "seconds_per_iteration": {mode: float(np.median(values)) for mode, values in seconds.items()},
        "iterations": min(len(values) for values in seconds.values()),
    }
    medians = result["seconds_per_iteration"]
    if {"sync", "pipelined"} <= set(medians):
        result["pipelined_over_sync"] = medians["pipelined"] / medians["sync"]
    return result
