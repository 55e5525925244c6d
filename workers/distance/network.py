"""The learned dynamical distance d(s, a, g) and its target copy d_old (sections 6.4-6.5, Table 20).

:class:`DistanceFunction` is what a learner needs to compute rewards: the
network and the input normalisation, rebuilt from plain arrays
(:meth:`DistanceFunction.weights` / :meth:`DistanceFunction.from_weights`).
:class:`DistanceModel` is what the distance trainer owns: a DistanceFunction,
the frozen target d_old copied after every temporal phase (Alg. 4 line 10),
and Adam. d_old is a whole DistanceFunction, its input statistics frozen with
its weights: the live statistics move when the next episodes are merged
(Alg. 4 line 4), before the temporal phase that bootstraps from d_old, and a
network read through statistics it was not trained with is not the old
function.

The third argument g is a goal-space vector (an achieved goal ag(s_j) or a
desired goal), which is what lets the same network score (s, a, desired goal)
as a reward. DDL's d(s, g) drops the action.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterator

import numpy as np
import torch
from torch import nn

from workers.distance.buffer import Episodes
from workers.distance.config import DistanceSettings
from workers.distance.normalizer import RunningNormalizer
from workers.distance.state import (
    State,
    load_module_arrays,
    load_optimizer_state,
    module_arrays,
    optimizer_state,
    with_prefix,
)


def mlp(input_dim: int, hidden: tuple[int, ...], output_dim: int) -> nn.Sequential:
    """ReLU MLP with Xavier-uniform weights and zero biases (Table 19, "weight initialization")."""
    layers: list[nn.Module] = []
    width = input_dim
    for size in hidden:
        layers += [nn.Linear(width, size), nn.ReLU()]
        width = size
    layers.append(nn.Linear(width, output_dim))
    for layer in layers:
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    return nn.Sequential(*layers)


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Seed torch's global generator inside the block only (weight initialisation), restoring it after."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


class DistanceFunction:
    """d(s, a, g) (or d(s, g)) with its input normalisation, for inference and training.

    Args:
        obs_dim, action_dim, goal_dim: input sizes; action_dim 0 gives DDL's d(s, g).
        hidden: hidden layer widths.
        clip_obs, clip_normalized: normalisation clips.
        seed: weight initialisation.
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        goal_dim: int,
        hidden: tuple[int, ...],
        clip_obs: float = 200.0,
        clip_normalized: float = 5.0,
        seed: int = 0,
    ):
        self.dims = (obs_dim, action_dim, goal_dim)
        self.hidden = tuple(hidden)
        with seeded(seed):
            self.net = mlp(obs_dim + action_dim + goal_dim, self.hidden, 1)
        self.obs_norm = RunningNormalizer(obs_dim, clip_obs, clip_normalized)
        self.goal_norm = RunningNormalizer(goal_dim, clip_obs, clip_normalized)

    @property
    def uses_action(self) -> bool:
        return self.dims[1] > 0

    def inputs(self, observations: np.ndarray, actions: np.ndarray | None, goals: np.ndarray) -> torch.Tensor:
        """Network input [norm(s); a; norm(g)] (actions are already in [-1, 1])."""
        parts = [self.obs_norm.normalize(observations)]
        if self.uses_action:
            if actions is None:
                raise ValueError("d(s, a, g) needs actions")
            parts.append(np.asarray(actions, dtype=np.float32))
        parts.append(self.goal_norm.normalize(goals))
        return torch.from_numpy(np.concatenate(parts, axis=-1))

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """Distances (B,) from prepared inputs."""
        return self.net(inputs).squeeze(-1)

    def __call__(self, observations: np.ndarray, actions: np.ndarray | None, goals: np.ndarray) -> np.ndarray:
        """Distances (B,) as numpy, without gradients."""
        with torch.no_grad():
            return self.forward(self.inputs(observations, actions, goals)).numpy().astype(np.float64)

    def update_normalizers(self, episodes: Episodes) -> None:
        """Add the episodes' observations and achieved goals (the goals the temporal loss sees)."""
        self.obs_norm.update(episodes.observations)
        self.goal_norm.update(episodes.achieved_goals)

    def weights(self) -> State:
        """Network and normaliser statistics: what a learner loads to compute rewards."""
        obs, goal = self.obs_norm.state(), self.goal_norm.state()
        arrays = {f"net/{k}": v for k, v in module_arrays(self.net).items()}
        arrays |= {f"obs_norm/{k}": v for k, v in obs.arrays.items()}
        arrays |= {f"goal_norm/{k}": v for k, v in goal.arrays.items()}
        meta = {"dims": list(self.dims), "hidden": list(self.hidden), "obs_norm": obs.meta, "goal_norm": goal.meta}
        meta |= {"clip_obs": self.obs_norm.clip_input, "clip_normalized": self.obs_norm.clip_output}
        return State(arrays, meta)

    def load_weights(self, weights: State) -> None:
        """Load what :meth:`weights` exported (same architecture)."""

        def part(prefix: str) -> dict[str, np.ndarray]:
            return with_prefix(weights.arrays, prefix)

        load_module_arrays(self.net, part("net/"))
        self.obs_norm.load(State(part("obs_norm/"), weights.meta["obs_norm"]))
        self.goal_norm.load(State(part("goal_norm/"), weights.meta["goal_norm"]))

    @classmethod
    def from_weights(cls, weights: State) -> DistanceFunction:
        """A DistanceFunction rebuilt from exported weights (on a learner actor)."""
        obs_dim, action_dim, goal_dim = weights.meta["dims"]
        function = cls(
            obs_dim,
            action_dim,
            goal_dim,
            tuple(weights.meta["hidden"]),
            weights.meta["clip_obs"],
            weights.meta["clip_normalized"],
        )
        function.load_weights(weights)
        return function


class DistanceModel:
    """The trainer's side: d_theta, the frozen d_old (network and input statistics) and Adam (Table 20).

    Args:
        settings: network and loss settings.
        obs_dim, action_dim, goal_dim: sizes; the action is dropped for ``conditioning: state``.
        seed: weight initialisation.
    """

    def __init__(self, settings: DistanceSettings, obs_dim: int, action_dim: int, goal_dim: int, seed: int = 0):
        self.settings = settings
        uses_action = settings.conditioning == "state_action"
        self.function = DistanceFunction(
            obs_dim,
            action_dim if uses_action else 0,
            goal_dim,
            settings.hidden,
            settings.clip_obs,
            settings.clip_normalized,
            seed,
        )
        self.target = copy.deepcopy(self.function)
        for parameter in self.target.net.parameters():
            parameter.requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.function.net.parameters(), lr=settings.learning_rate)

    def predict_target(self, observations: np.ndarray, actions: np.ndarray | None, goals: np.ndarray) -> np.ndarray:
        """d_old for a batch, as numpy (the losses' bootstrapped terms)."""
        return self.target(observations, actions, goals)

    def fit(
        self,
        observations: np.ndarray,
        actions: np.ndarray | None,
        goals: np.ndarray,
        targets: np.ndarray,
        mask: np.ndarray | None = None,
    ) -> tuple[float, np.ndarray]:
        """One Adam step on the squared error to fixed targets; returns (loss, predictions before the step).

        With a mask, only the masked samples contribute and the loss is their
        mean (Alg. 4 line 20: samples that fail the count test are left out).
        """
        inputs = self.function.inputs(observations, actions, goals)
        prediction = self.function.forward(inputs)
        error = (prediction - torch.as_tensor(targets, dtype=torch.float32)) ** 2
        if mask is not None:
            weights = torch.as_tensor(mask, dtype=torch.float32)
            if weights.sum() == 0:
                return 0.0, prediction.detach().numpy().astype(np.float64)
            loss = (error * weights).sum() / weights.sum()
        else:
            loss = error.mean()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return float(loss.detach()), prediction.detach().numpy().astype(np.float64)

    def copy_target(self) -> None:
        """d_old <- d_theta, with the input statistics of this moment (Alg. 4 line 10)."""
        self.target.load_weights(self.function.weights())

    def state(self) -> State:
        weights = self.function.weights()
        optimizer = optimizer_state(self.optimizer)
        arrays = {f"function/{k}": v for k, v in weights.arrays.items()}
        target = self.target.weights()
        arrays |= {f"target/{k}": v for k, v in target.arrays.items()}
        arrays |= {f"optimizer/{k}": v for k, v in optimizer.arrays.items()}
        return State(arrays, {"function": weights.meta, "target": target.meta, "optimizer": optimizer.meta})

    def load(self, state: State) -> None:
        def part(prefix: str) -> dict[str, np.ndarray]:
            return with_prefix(state.arrays, prefix)

        self.function.load_weights(State(part("function/"), state.meta["function"]))
        if "target" in state.meta:
            self.target.load_weights(State(part("target/"), state.meta["target"]))
        else:
            # A checkpoint from before d_old kept its own statistics holds the target network alone;
            # it was read through the live statistics, which are the best guess of the ones it saw.
            self.target.load_weights(self.function.weights())
            load_module_arrays(self.target.net, part("target/"))
        load_optimizer_state(self.optimizer, State(part("optimizer/"), state.meta["optimizer"]))
