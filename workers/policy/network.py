"""The APEX policy (Table 11): a deterministic MLP from observations to normalised actions.

* 3 hidden layers of 128 ReLU units; a linear output layer, clipped to the
  action bounds [-1, 1] when the policy acts. Clipping rather than tanh:
  iCEM's clipped colored-noise samples put many expert actions exactly on
  the bounds, which a tanh output could reach only with unbounded
  pre-activations; the MSE is taken on the unclipped output.
* Inputs are standardised with the mean and standard deviation of the
  training data of the latest training (std floored at ``STD_FLOOR`` so
  that features constant in the data, e.g. a box that never moved, do not
  blow up later; standardised inputs clipped to +-``INPUT_CLIP``).
* Weights are a :class:`PolicyWeights`: a version number and plain numpy
  arrays, evaluated here in numpy (workers need no torch to plan with a
  policy) and stored as pickle-free checkpoint archives
  (workers/checkpoint.py) that :func:`load_policy` reads back.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from workers import checkpoint

FORMAT = "icemlab.apex.policy/1"
"""Format tag of policy checkpoint files."""
STD_FLOOR = 1e-2
"""Smallest input standard deviation used for standardising."""
INPUT_CLIP = 10.0
"""Standardised inputs are clipped to +-INPUT_CLIP."""


class PolicyWeights(NamedTuple):
    """A policy's parameters, versioned: what travels to the workers and into checkpoints."""

    version: int
    """Trainings done so far (0: the random initialisation)."""
    arrays: dict[str, np.ndarray]
    """``w0``, ``b0``, ... per linear layer (w: (in, out)), ``input_mean``, ``input_std``."""
    task: str = ""
    """The task the policy was trained on (checked before rolling it out)."""

    @property
    def layers(self) -> int:
        return sum(1 for key in self.arrays if key.startswith("w"))

    @property
    def obs_dim(self) -> int:
        return int(self.arrays["w0"].shape[0])

    @property
    def action_dim(self) -> int:
        return int(self.arrays[f"w{self.layers - 1}"].shape[1])

    def to_tree(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": self.version, "task": self.task, "arrays": dict(self.arrays)}

    @classmethod
    def from_tree(cls, tree: dict[str, Any]) -> PolicyWeights:
        if tree.get("format") != FORMAT:
            raise checkpoint.CheckpointError(f"not an APEX policy checkpoint (format {tree.get('format')!r})")
        arrays = {k: np.asarray(v) for k, v in tree["arrays"].items()}
        return cls(int(tree["version"]), arrays, str(tree.get("task", "")))

    def to_bytes(self) -> bytes:
        """The weights as a pickle-free ``.npz`` archive (see :func:`load_policy`)."""
        return checkpoint.to_bytes(self.to_tree())

    @classmethod
    def from_bytes(cls, data: bytes) -> PolicyWeights:
        return cls.from_tree(checkpoint.from_bytes(data))


class Policy:
    """A policy evaluated in numpy: ``policy(observations) -> actions`` in [-1, 1].

    Accepts one observation (obs_dim,) or a batch (..., obs_dim).
    """

    def __init__(self, weights: PolicyWeights):
        self.weights = weights
        arrays = weights.arrays
        self.version = weights.version
        self.task = weights.task
        self._layers = [
            (arrays[f"w{i}"].astype(np.float64), arrays[f"b{i}"].astype(np.float64)) for i in range(weights.layers)
        ]
        self._mean = arrays["input_mean"].astype(np.float64)
        self._std = arrays["input_std"].astype(np.float64)

    @property
    def obs_dim(self) -> int:
        return self.weights.obs_dim

    @property
    def action_dim(self) -> int:
        return self.weights.action_dim

    def raw(self, observations: np.ndarray) -> np.ndarray:
        """The network's output before clipping."""
        x = np.asarray(observations, dtype=np.float64)
        if x.shape[-1] != self.obs_dim:
            raise ValueError(f"the policy takes observations of {self.obs_dim} values, got shape {x.shape}")
        h = np.clip((x - self._mean) / self._std, -INPUT_CLIP, INPUT_CLIP)
        for index, (w, b) in enumerate(self._layers):
            h = h @ w + b
            if index < len(self._layers) - 1:
                h = np.maximum(h, 0.0)
        return h

    def __call__(self, observations: np.ndarray) -> np.ndarray:
        return np.clip(self.raw(observations), -1.0, 1.0)


def load_policy(path: str | Path) -> Policy:
    """Read a policy checkpoint written by APEX (``policy/policy_NNNN.npz`` of a trial's run).

    ``from workers.policy import load_policy; pi = load_policy("policy_0007.npz"); action = pi(observation)``
    """
    return Policy(PolicyWeights.from_bytes(Path(path).read_bytes()))


def standardisation(inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) of training inputs, std floored at :data:`STD_FLOOR`."""
    inputs = np.asarray(inputs, dtype=np.float64)
    return inputs.mean(axis=0), np.maximum(inputs.std(axis=0), STD_FLOOR)


def layer_sizes(obs_dim: int, action_dim: int, hidden: Sequence[int]) -> list[int]:
    return [obs_dim, *hidden, action_dim]
