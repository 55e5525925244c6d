"""Goal-conditioned SAC and DDPG with HER (section 6.6, Table 19), rewards computed at sampling time.

The policy phase of an iteration (Alg. 4 lines 21-24) as one object, the
learner, separate from the distance trainer: it keeps its own replay buffer
(5e5 transitions, Table 19), receives the same collected episodes, and gets
the distance as weights (:meth:`GoalLearner.set_reward_weights`) once per
iteration. Every update draws a HER batch, asks the pluggable reward for
rewards, and takes one SAC or DDPG step.

Table 19 repeats OpenAI baselines' HER defaults, which this follows where the
thesis is silent: inputs clipped to +-200 and normalised with running
statistics of HER-relabelled transitions of each new batch of episodes (then
clipped to +-5); Q-targets clipped to [q_clip_low, 0] (rewards are <= 0, so no
return is positive); a uniformly random action with probability 0.3 when
exploring; DDPG with Gaussian action noise 0.2 and an L2 penalty 1 on the
actor's actions; polyak 0.95 applied after every 40 updates (baselines'
batches per cycle). SAC's temperature is tuned to entropy -|A| (the thesis
gives no SAC temperature). Episodes never terminate (fixed horizon), so
targets always bootstrap.

Why not stable-baselines3: see :data:`SB3_DECISION`.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from workers.distance.buffer import EpisodeBuffer, Episodes
from workers.distance.config import LearnerSettings
from workers.distance.her import GoalTransitions, sample_her_transitions
from workers.distance.network import mlp, seeded
from workers.distance.normalizer import RunningNormalizer
from workers.distance.rewards import RewardFunction
from workers.distance.state import (
    State,
    generator_state,
    load_module_arrays,
    load_optimizer_state,
    module_arrays,
    optimizer_state,
    part_of,
    restore_generator,
    restore_torch_generator,
    torch_generator_array,
    with_prefix,
)

SB3_DECISION = """\
stable-baselines3 2.9.2 was considered and not used. Its HerReplayBuffer
stores rewards at collection time and recomputes them only for relabelled
("virtual") transitions, through env.compute_reward(achieved_goal,
desired_goal, info): the reward cannot see the observation or the action, so
-d(s, a, g) cannot be expressed, and real transitions would keep stale
rewards from older distance weights. Its SAC owns the environment and the
collection loop (learn / collect_rollouts), while neural APSP needs a learner
that only receives finished episodes and distance weights from another actor
once per iteration. It also has no Q-target clipping, no epsilon-random
actions and no per-batch input normalisation of HER samples, all part of
Table 19, and it checkpoints through pickled zip archives. Wrapping all of
that would override most of SAC.train and the buffer's sampling; writing the
learner here was smaller and keeps every state as plain arrays.
"""

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


class SquashedGaussianActor(nn.Module):
    """SAC policy: tanh of a Gaussian whose mean and log-std come from one MLP."""

    def __init__(self, input_dim: int, action_dim: int, hidden: tuple[int, ...]):
        super().__init__()
        self.net = mlp(input_dim, hidden, 2 * action_dim)

    def forward(self, inputs: torch.Tensor, noise: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(actions, log-probabilities); noise None gives the deterministic tanh(mean) and no log-probability."""
        mean, log_std = self.net(inputs).chunk(2, dim=-1)
        if noise is None:
            return torch.tanh(mean), None
        log_std = log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)
        pre = mean + log_std.exp() * noise
        gaussian = (-0.5 * noise.pow(2) - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
        # log |d tanh(u) / du| = log(1 - tanh(u)^2), written stably.
        squash = (2.0 * (np.log(2.0) - pre - F.softplus(-2.0 * pre))).sum(-1)
        return torch.tanh(pre), gaussian - squash


class DeterministicActor(nn.Module):
    """DDPG policy: tanh of an MLP (actions in [-1, 1])."""

    def __init__(self, input_dim: int, action_dim: int, hidden: tuple[int, ...]):
        super().__init__()
        self.net = mlp(input_dim, hidden, action_dim)

    def forward(self, inputs: torch.Tensor, noise: torch.Tensor | None = None) -> tuple[torch.Tensor, None]:
        return torch.tanh(self.net(inputs)), None


class Critics(nn.Module):
    """One or two Q(s, g, a) MLPs (two for SAC's clipped double Q)."""

    def __init__(self, input_dim: int, action_dim: int, hidden: tuple[int, ...], count: int):
        super().__init__()
        self.heads = nn.ModuleList(mlp(input_dim + action_dim, hidden, 1) for _ in range(count))

    def forward(self, inputs: torch.Tensor, actions: torch.Tensor) -> list[torch.Tensor]:
        x = torch.cat([inputs, actions], dim=-1)
        return [head(x).squeeze(-1) for head in self.heads]


class GoalPolicy:
    """The acting part of a learner: actor, input normalisation and exploration.

    A rollout actor rebuilds it from :meth:`weights` (plain arrays) and acts
    without the critics or buffers.

    Args:
        algorithm: ``sac`` or ``ddpg``.
        obs_dim, goal_dim, action_dim: sizes.
        hidden: actor hidden widths.
        clip_obs, clip_normalized: normalisation clips (Table 19).
        random_eps: probability of a uniform random action when exploring (Table 19).
        action_noise: DDPG Gaussian noise when exploring (Table 19).
        seed: weight initialisation and exploration noise.
    """

    def __init__(
        self,
        algorithm: str,
        obs_dim: int,
        goal_dim: int,
        action_dim: int,
        hidden: tuple[int, ...],
        clip_obs: float = 200.0,
        clip_normalized: float = 5.0,
        random_eps: float = 0.3,
        action_noise: float = 0.2,
        seed: int = 0,
    ):
        self.algorithm = algorithm
        self.dims = (obs_dim, goal_dim, action_dim)
        self.hidden = tuple(hidden)
        self.random_eps, self.action_noise = random_eps, action_noise
        actor_class = SquashedGaussianActor if algorithm == "sac" else DeterministicActor
        with seeded(seed):
            self.actor = actor_class(obs_dim + goal_dim, action_dim, self.hidden)
        self.obs_norm = RunningNormalizer(obs_dim, clip_obs, clip_normalized)
        self.goal_norm = RunningNormalizer(goal_dim, clip_obs, clip_normalized)
        self.rng = np.random.default_rng(seed)

    def inputs(self, observations: np.ndarray, goals: np.ndarray) -> torch.Tensor:
        """[norm(s); norm(g)] as float32."""
        return torch.from_numpy(
            np.concatenate([self.obs_norm.normalize(observations), self.goal_norm.normalize(goals)], axis=-1)
        )

    def act(self, observations: np.ndarray, goals: np.ndarray, explore: bool = True) -> np.ndarray:
        """Actions in [-1, 1] for one (obs_dim,) or a batch (N, obs_dim) of observations."""
        single = np.ndim(observations) == 1
        observations, goals = np.atleast_2d(observations), np.atleast_2d(goals)
        count, action_dim = len(observations), self.dims[2]
        with torch.no_grad():
            inputs = self.inputs(observations, goals)
            noise = None
            if explore and self.algorithm == "sac":
                noise = torch.from_numpy(self.rng.standard_normal((count, action_dim)).astype(np.float32))
            actions = self.actor(inputs, noise)[0].numpy().astype(np.float64)
        if explore:
            if self.algorithm == "ddpg":
                actions = np.clip(actions + self.action_noise * self.rng.standard_normal(actions.shape), -1.0, 1.0)
            random = self.rng.random(count) < self.random_eps
            actions[random] = self.rng.uniform(-1.0, 1.0, (int(random.sum()), action_dim))
        return actions[0] if single else actions

    def weights(self) -> State:
        """Actor, normaliser statistics and exploration settings."""
        obs, goal = self.obs_norm.state(), self.goal_norm.state()
        arrays = {f"actor/{k}": v for k, v in module_arrays(self.actor).items()}
        arrays |= {f"obs_norm/{k}": v for k, v in obs.arrays.items()}
        arrays |= {f"goal_norm/{k}": v for k, v in goal.arrays.items()}
        meta = {
            "algorithm": self.algorithm,
            "dims": list(self.dims),
            "hidden": list(self.hidden),
            "clip_obs": self.obs_norm.clip_input,
            "clip_normalized": self.obs_norm.clip_output,
            "random_eps": self.random_eps,
            "action_noise": self.action_noise,
            "obs_norm": obs.meta,
            "goal_norm": goal.meta,
        }
        return State(arrays, meta)

    def load_weights(self, weights: State) -> None:
        def part(prefix: str) -> dict[str, np.ndarray]:
            return with_prefix(weights.arrays, prefix)

        load_module_arrays(self.actor, part("actor/"))
        self.obs_norm.load(State(part("obs_norm/"), weights.meta["obs_norm"]))
        self.goal_norm.load(State(part("goal_norm/"), weights.meta["goal_norm"]))

    @classmethod
    def from_weights(cls, weights: State, seed: int = 0) -> GoalPolicy:
        """A policy for acting elsewhere (rollout or evaluation actors)."""
        meta = weights.meta
        obs_dim, goal_dim, action_dim = meta["dims"]
        policy = cls(
            meta["algorithm"],
            obs_dim,
            goal_dim,
            action_dim,
            tuple(meta["hidden"]),
            meta["clip_obs"],
            meta["clip_normalized"],
            meta["random_eps"],
            meta["action_noise"],
            seed,
        )
        policy.load_weights(weights)
        return policy


def default_q_clip(reward_kind: str, gamma: float, horizon: int) -> float:
    """Lower Q-target clip of Table 19.

    Sparse+HER: -1 / (1 - gamma) (= -50 at gamma 0.98, Table 19's [-50, 0]),
    the return of never reaching the goal. Distance rewards: Table 19's
    [-1275, 0] is -T (T + 1) / 2 for T = 50, the undiscounted sum of distances
    T, T - 1, ..., 1 along one episode; we apply the same formula to other
    horizons (-5050 on the 100-step Point Maze), which the thesis does not list.
    """
    if reward_kind == "sparse":
        return -1.0 / (1.0 - gamma)
    return -horizon * (horizon + 1) / 2.0


class GoalLearner:
    """SAC or DDPG + HER with a pluggable reward.

    Args:
        settings: Table 19 settings.
        obs_dim, action_dim, goal_dim, horizon: problem sizes.
        reward: called on every sampled batch; a DistanceReward gets new weights by :meth:`set_reward_weights`.
        q_clip_low: lower Q-target clip for unscaled rewards (see :func:`default_q_clip`), multiplied by
            ``settings.reward_scale``; ``settings.q_clip_low`` wins when set.
        seed: initialisation, sampling and exploration derive from it.
    """

    def __init__(
        self,
        settings: LearnerSettings,
        obs_dim: int,
        action_dim: int,
        goal_dim: int,
        horizon: int,
        reward: RewardFunction,
        q_clip_low: float,
        seed: int = 0,
    ):
        self.settings = settings
        self.reward = reward
        self.horizon = horizon
        derived = q_clip_low * settings.reward_scale
        self.q_clip_low = settings.q_clip_low if settings.q_clip_low is not None else derived
        seeds = [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(seed).spawn(4)]
        self.policy = GoalPolicy(
            settings.algorithm,
            obs_dim,
            goal_dim,
            action_dim,
            settings.hidden,
            settings.clip_obs,
            settings.clip_normalized,
            settings.random_eps,
            settings.action_noise,
            seeds[0],
        )
        self.actor = self.policy.actor
        sac = settings.algorithm == "sac"
        with seeded(seeds[1]):
            self.critics = Critics(obs_dim + goal_dim, action_dim, settings.hidden, 2 if sac else 1)
        self.critic_targets = copy.deepcopy(self.critics).requires_grad_(False)
        self.actor_target = None if sac else copy.deepcopy(self.actor).requires_grad_(False)
        lr = settings.learning_rate
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=lr)
        self.critic_optimizer = torch.optim.Adam(self.critics.parameters(), lr=lr)
        self.log_alpha = torch.tensor(float(np.log(settings.init_alpha)), requires_grad=sac and settings.auto_alpha)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=lr) if self.log_alpha.requires_grad else None
        self.target_entropy = -float(action_dim)
        self.buffer = EpisodeBuffer(settings.buffer_size, horizon, obs_dim, action_dim, goal_dim)
        self.rng = np.random.default_rng(seeds[2])
        self.torch_rng = torch.Generator().manual_seed(seeds[3])
        self.updates = 0

    # ------------------------------------------------------------ exchange
    def set_reward_weights(self, weights: State) -> None:
        """Hand the distance trainer's latest weights to the reward (once per iteration)."""
        load = getattr(self.reward, "load_weights", None)
        if load is None:
            raise TypeError(f"the reward {type(self.reward).__name__} takes no weights")
        load(weights)

    def add_episodes(self, episodes: Episodes) -> None:
        """Store episodes; update the input statistics with HER-relabelled transitions of them (baselines)."""
        self.buffer.add(episodes)
        sample = sample_her_transitions(episodes, len(episodes) * episodes.horizon, self.settings.her_k, self.rng)
        self.policy.obs_norm.update(sample.observations)
        self.policy.goal_norm.update(sample.goals)

    def policy_weights(self) -> State:
        """What a rollout actor needs to act (:meth:`GoalPolicy.from_weights`)."""
        return self.policy.weights()

    def act(self, observations: np.ndarray, goals: np.ndarray, explore: bool = True) -> np.ndarray:
        return self.policy.act(observations, goals, explore)

    # ------------------------------------------------------------ training
    def sample(self) -> tuple[GoalTransitions, np.ndarray]:
        """A HER batch and its rewards from the current reward function."""
        batch = sample_her_transitions(self.buffer, self.settings.batch_size, self.settings.her_k, self.rng)
        return batch, self.settings.reward_scale * np.asarray(self.reward(batch), dtype=np.float64)

    def train(self, updates: int | None = None, episodes: int | None = None) -> dict[str, float]:
        """``updates`` gradient steps (default: updates_per_episode x ``episodes``); mean metrics."""
        if updates is None:
            updates = self.settings.updates_per_episode * (episodes or 0)
        if updates <= 0 or self.buffer.size == 0:
            return {}
        history = [self.update() for _ in range(updates)]
        return {f"learner/{key}": float(np.mean([h[key] for h in history])) for key in history[0]}

    def update(self) -> dict[str, float]:
        """One gradient step on a fresh HER batch."""
        batch, rewards = self.sample()
        return self.update_on(batch, rewards)

    def update_on(self, batch: GoalTransitions, rewards: np.ndarray) -> dict[str, float]:
        """One gradient step on a given batch (tests and benchmarks call this directly)."""
        policy = self.policy
        inputs = policy.inputs(batch.observations, batch.goals)
        next_inputs = policy.inputs(batch.next_observations, batch.goals)
        actions = torch.as_tensor(batch.actions, dtype=torch.float32)
        reward = torch.as_tensor(rewards, dtype=torch.float32)
        if self.settings.algorithm == "sac":
            metrics = self._sac_step(inputs, actions, next_inputs, reward)
        else:
            metrics = self._ddpg_step(inputs, actions, next_inputs, reward)
        self.updates += 1
        if self.updates % self.settings.target_update_interval == 0:
            self._polyak()
        metrics["reward_mean"] = float(rewards.mean())
        return metrics

    def q_targets(self, rewards: torch.Tensor, next_values: torch.Tensor) -> torch.Tensor:
        """r + gamma V(s'), clipped to [q_clip_low, 0] (Table 19, "Q-target clipping")."""
        return (rewards + self.settings.gamma * next_values).clamp(self.q_clip_low, 0.0)

    def _critic_step(self, inputs, actions, targets) -> tuple[float, float]:
        values = self.critics(inputs, actions)
        loss = sum(F.mse_loss(value, targets) for value in values)
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_optimizer.step()
        return float(loss.detach()), float(values[0].detach().mean())

    def _sac_step(self, inputs, actions, next_inputs, rewards) -> dict[str, float]:
        alpha = self.log_alpha.exp().detach()
        shape = (len(inputs), actions.shape[-1])
        with torch.no_grad():
            next_actions, next_log_prob = self.actor(next_inputs, torch.randn(shape, generator=self.torch_rng))
            next_q = torch.min(*self.critic_targets(next_inputs, next_actions))
            targets = self.q_targets(rewards, next_q - alpha * next_log_prob)
        critic_loss, q_mean = self._critic_step(inputs, actions, targets)

        self.critics.requires_grad_(False)  # the actor's loss needs dQ/da only
        new_actions, log_prob = self.actor(inputs, torch.randn(shape, generator=self.torch_rng))
        actor_loss = (alpha * log_prob - torch.min(*self.critics(inputs, new_actions))).mean()
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optimizer.step()
        self.critics.requires_grad_(True)

        if self.alpha_optimizer is not None:
            alpha_loss = -(self.log_alpha * (log_prob.detach() + self.target_entropy)).mean()
            self.alpha_optimizer.zero_grad(set_to_none=True)
            alpha_loss.backward()
            self.alpha_optimizer.step()
        return {
            "critic_loss": critic_loss,
            "actor_loss": float(actor_loss.detach()),
            "q_mean": q_mean,
            "alpha": float(alpha),
            "entropy": float(-log_prob.detach().mean()),
            "target_clipped": float(((targets <= self.q_clip_low) | (targets >= 0)).float().mean()),
        }

    def _ddpg_step(self, inputs, actions, next_inputs, rewards) -> dict[str, float]:
        assert self.actor_target is not None
        with torch.no_grad():
            next_actions, _ = self.actor_target(next_inputs)
            targets = self.q_targets(rewards, self.critic_targets(next_inputs, next_actions)[0])
        critic_loss, q_mean = self._critic_step(inputs, actions, targets)

        self.critics.requires_grad_(False)
        new_actions, _ = self.actor(inputs)
        actor_loss = -self.critics(inputs, new_actions)[0].mean() + self.settings.action_l2 * new_actions.pow(2).mean()
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optimizer.step()
        self.critics.requires_grad_(True)
        return {
            "critic_loss": critic_loss,
            "actor_loss": float(actor_loss.detach()),
            "q_mean": q_mean,
            "target_clipped": float(((targets <= self.q_clip_low) | (targets >= 0)).float().mean()),
        }

    @torch.no_grad()
    def _polyak(self) -> None:
        """target <- polyak target + (1 - polyak) online (Table 19: polyak 0.95)."""
        pairs = [(self.critic_targets, self.critics)]
        if self.actor_target is not None:
            pairs.append((self.actor_target, self.actor))
        for target, online in pairs:
            for t, o in zip(target.parameters(), online.parameters()):
                t.mul_(self.settings.polyak).add_(o, alpha=1.0 - self.settings.polyak)

    # --------------------------------------------------------------- state
    def state(self) -> State:
        """Networks, targets, optimisers, temperature, buffer, generators and counters."""
        parts: dict[str, State] = {
            "policy": self.policy.weights(),
            "critics": State(module_arrays(self.critics), {}),
            "critic_targets": State(module_arrays(self.critic_targets), {}),
            "actor_optimizer": optimizer_state(self.actor_optimizer),
            "critic_optimizer": optimizer_state(self.critic_optimizer),
            "buffer": self.buffer.state(),
        }
        if self.actor_target is not None:
            parts["actor_target"] = State(module_arrays(self.actor_target), {})
        if self.alpha_optimizer is not None:
            parts["alpha_optimizer"] = optimizer_state(self.alpha_optimizer)
        arrays = {f"{name}/{k}": v for name, part in parts.items() for k, v in part.arrays.items()}
        arrays["log_alpha"] = self.log_alpha.detach().numpy().copy()
        arrays["torch_rng"] = torch_generator_array(self.torch_rng)
        meta: dict[str, Any] = {name: part.meta for name, part in parts.items()}
        meta |= {
            "rng": generator_state(self.rng),
            "policy_rng": generator_state(self.policy.rng),
            "updates": self.updates,
            "q_clip_low": self.q_clip_low,
        }
        return State(arrays, meta)

    def load(self, state: State) -> None:
        """Restore :meth:`state` into a learner built with the same settings."""

        def part(name: str) -> State:
            return part_of(state, name)

        self.policy.load_weights(part("policy"))
        load_module_arrays(self.critics, part("critics").arrays)
        load_module_arrays(self.critic_targets, part("critic_targets").arrays)
        if self.actor_target is not None:
            load_module_arrays(self.actor_target, part("actor_target").arrays)
        load_optimizer_state(self.actor_optimizer, part("actor_optimizer"))
        load_optimizer_state(self.critic_optimizer, part("critic_optimizer"))
        if self.alpha_optimizer is not None:
            load_optimizer_state(self.alpha_optimizer, part("alpha_optimizer"))
        with torch.no_grad():
            self.log_alpha.copy_(torch.as_tensor(state.arrays["log_alpha"]))
        self.buffer.load(part("buffer"))
        restore_generator(self.rng, state.meta["rng"])
        restore_generator(self.policy.rng, state.meta["policy_rng"])
        restore_torch_generator(self.torch_rng, state.arrays["torch_rng"])
        self.updates = int(state.meta["updates"])
        self.q_clip_low = float(state.meta["q_clip_low"])
