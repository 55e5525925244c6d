"""The distance phase of an iteration (Alg. 4 lines 4-20), as one object the service can put on an actor.

A :class:`DistanceTrainer` owns everything the distance needs and nothing the
policy needs: the replay buffer D (1e6 transitions, Table 20), the count
models (App. E.1), d_theta and d_old. Once per iteration it receives the
episodes just collected (D_last), merges them into D, updates the counts and
trains; the learner then receives :meth:`DistanceTrainer.reward_weights`.

Alg. 4 merges D_last into D only at the end of the iteration, which leaves the
first iteration with nothing to train the temporal loss on; we merge right
after collecting (SPEC reading notes), so s_j of the triangular loss may also
come from D_last.
"""

from __future__ import annotations

import math

import numpy as np

from workers.distance.buffer import EpisodeBuffer, Episodes
from workers.distance.config import CountSettings, DistanceSettings
from workers.distance.counts import CountModels
from workers.distance.losses import (
    count_uncertainty,
    merge_and_relax_rates,
    regression_targets,
    sample_temporal,
    sample_triangular,
    temporal_targets,
    triangular_targets,
)
from workers.distance.network import DistanceModel
from workers.distance.state import State, generator_state, part_of, restore_generator


class DistanceTrainer:
    """Count models, distance network, target and buffer; trains once per iteration.

    Args:
        settings: the distance's network and losses (Ours: both losses; Off-policy DDL: temporal only;
            DDL: d(s, g) by plain regression).
        counts: hash sizes and sigma (Table 20); unused by DDL's regression.
        obs_dim, action_dim, goal_dim, horizon: problem sizes.
        seed: network initialisation, count-model hashes and sampling all derive from it.
    """

    def __init__(
        self,
        settings: DistanceSettings,
        counts: CountSettings,
        obs_dim: int,
        action_dim: int,
        goal_dim: int,
        horizon: int,
        seed: int = 0,
    ):
        self.settings = settings
        self.horizon = horizon
        seeds = np.random.SeedSequence(seed).spawn(3)
        self.model = DistanceModel(settings, obs_dim, action_dim, goal_dim, int(seeds[0].generate_state(1)[0]))
        self.counts = (
            CountModels(counts, obs_dim, action_dim, goal_dim, int(seeds[1].generate_state(1)[0]))
            if settings.temporal == "off_policy"
            else None
        )
        self.buffer = EpisodeBuffer(settings.buffer_size, horizon, obs_dim, action_dim, goal_dim)
        self.rng = np.random.default_rng(seeds[2])
        self.recent: Episodes | None = None

    @property
    def uses_action(self) -> bool:
        return self.settings.conditioning == "state_action"

    # ------------------------------------------------------------- merging
    def add_episodes(self, episodes: Episodes) -> None:
        """D_last <- episodes; merge into D; update count models and input statistics (Alg. 4 lines 3-4)."""
        self.recent = episodes
        self.buffer.add(episodes)
        if self.counts is not None:
            self.counts.update(episodes, pairs=self.settings.triangular)
        self.model.function.update_normalizers(episodes)

    # ------------------------------------------------------------ training
    def train(self) -> dict[str, float]:
        """Temporal phase, target copy, triangular phase for the episodes last added (Alg. 4 lines 5-20)."""
        if self.recent is None:
            raise RuntimeError("add_episodes before train")
        episodes = len(self.recent)
        settings = self.settings
        temporal = [self.temporal_step() for _ in range(episodes * settings.temporal_updates_per_episode)]
        self.model.copy_target()
        metrics: dict[str, float] = {}
        if temporal:
            for key in temporal[0]:
                name = {"loss": "temporal_loss", "target_mean": "temporal_target_mean"}.get(key, key)
                metrics[f"distance/{name}"] = float(np.mean([m[key] for m in temporal]))
        if settings.triangular:
            triangular = [self.triangular_step() for _ in range(episodes * settings.triangular_updates_per_episode)]
            if triangular:
                for key in triangular[0]:
                    metrics[f"distance/triangular_{key}"] = float(np.mean([m[key] for m in triangular]))
                # An update no sample passed (Alg. 4 line 20) trains nothing and has no loss: the loss is that of the
                # samples that trained (nan when none did), and the share of such idle updates is logged beside it.
                trained = np.array([m["masked_fraction"] for m in triangular])
                losses = np.array([m["loss"] for m in triangular])
                loss = float(losses @ trained / trained.sum()) if trained.sum() > 0 else math.nan
                metrics["distance/triangular_loss"] = loss
                metrics["distance/triangular_idle_fraction"] = float(np.mean(trained == 0))
        if self.counts is not None:
            metrics["counts/single_increments"] = float(self.counts.single.sketch.total)
            metrics["counts/pair_increments"] = float(self.counts.pair.sketch.total)
        metrics["distance/buffer_episodes"] = float(self.buffer.size)
        return metrics

    def temporal_step(self) -> dict[str, float]:
        """One update of the temporal loss (eq. 31a; DDL: plain regression)."""
        regression = self.settings.temporal == "regression"
        min_gap = 0 if regression and not self.uses_action else 1
        batch = sample_temporal(self.buffer, self.settings.batch_size, self.rng, min_gap=min_gap)
        if regression:
            targets = regression_targets(batch.steps)
            # DDL's d(s, g) scores the state; the pair (s_i, s_j) is j - i steps apart.
            actions = batch.actions if self.uses_action else None
            loss, _ = self.model.fit(batch.observations, actions, batch.goals, targets)
            return {"loss": loss, "target_mean": float(targets.mean())}
        assert self.counts is not None
        estimates = self.model.predict_target(batch.observations, batch.actions, batch.goals)
        counts = self.counts.single.query(batch.observations, batch.actions)
        uncertainty = count_uncertainty(
            counts,
            self.settings.uncertainty_scale,
            self.settings.uncertainty_exponent,
        )
        targets = temporal_targets(batch.steps, estimates, uncertainty)
        loss, _ = self.model.fit(batch.observations, batch.actions, batch.goals, targets)
        return {
            "loss": loss,
            "target_mean": float(targets.mean()),
            "bootstrapped_fraction": float(np.mean(targets < batch.steps)),
            "count_mean": float(np.mean(counts)),
            "uncertainty_mean": float(np.mean(uncertainty)),
        }

    def triangular_step(self) -> dict[str, float]:
        """One update of the triangular loss (eq. 31b, Alg. 4 lines 11-20)."""
        assert self.counts is not None and self.recent is not None
        batch = sample_triangular(self.recent, self.buffer, self.settings.batch_size, self.rng)
        pair = self.counts.pair
        first_leg = self.model.predict_target(batch.observations, batch.actions, batch.via_goals)
        second_leg = self.model.predict_target(batch.via_observations, batch.via_actions, batch.goals)
        to_goal = pair.query(batch.observations, batch.actions, batch.goals)
        via_to_goal = pair.query(batch.via_observations, batch.via_actions, batch.goals)
        targets, mask = triangular_targets(
            first_leg, second_leg, to_goal, via_to_goal, self.settings.triangular_target_cap
        )
        loss, predictions = self.model.fit(batch.observations, batch.actions, batch.goals, targets, mask)
        merge, relax = merge_and_relax_rates(predictions, targets, mask)
        return {
            "loss": loss,
            "merge_rate": merge,
            "relax_rate": relax,
            "masked_fraction": float(mask.mean()),
            "unreached_fraction": float(np.mean(to_goal == 0)),
            "via_reached_fraction": float(np.mean(via_to_goal > 0)),
        }

    # ------------------------------------------------------------ exchange
    def reward_weights(self) -> State:
        """d_theta and its input statistics, for the learner's reward."""
        return self.model.function.weights()

    def state(self) -> State:
        """Everything: network, target, Adam, count sketches, buffer, sampler RNG, D_last."""
        parts = {"model": self.model.state(), "buffer": self.buffer.state()}
        if self.counts is not None:
            parts["counts"] = self.counts.state()
        arrays = {f"{name}/{k}": v for name, part in parts.items() for k, v in part.arrays.items()}
        meta = {name: part.meta for name, part in parts.items()}
        meta["rng"] = generator_state(self.rng)
        meta["recent"] = self.recent is not None
        if self.recent is not None:
            arrays |= {f"recent/{name}": value for name, value in zip(Episodes._fields, self.recent)}
        return State(arrays, meta)

    def load(self, state: State) -> None:
        """Restore :meth:`state` into a trainer built with the same settings."""

        def part(name: str) -> State:
            return part_of(state, name)

        self.model.load(part("model"))
        self.buffer.load(part("buffer"))
        if self.counts is not None:
            self.counts.load(part("counts"))
        restore_generator(self.rng, state.meta["rng"])
        if state.meta["recent"]:
            self.recent = Episodes(*(np.array(state.arrays[f"recent/{name}"]) for name in Episodes._fields))
        else:
            self.recent = None
