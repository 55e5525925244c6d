"""Policy training (Table 11) and the stateful trainer worker of APEX.

MSE to the expert's actions plus l1 (1e-6) and l2 (1e-5) penalties on the
weight matrices, Adam (lr 5e-4), batches of 1024 drawn with replacement,
1000 gradient steps per training. By default the network and the optimiser
are never reset: every training continues from the last one, as Alg. 3
initialises theta once, before its loop. The input
standardisation follows the current dataset; when it moves, the first layer
is rescaled and shifted with it, so the carried-over network computes the
same function of the raw observation as before (``keep_function``).
``reinitialize: true`` starts every training from a fresh network and
optimiser instead, a departure from Alg. 3 that measured better on
HalfCheetah (docs/results/apex.md measures both).
"""

from __future__ import annotations

import os
import time
from typing import Any, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from workers.checkpoint import arrays_to_tensors, tensors_to_arrays
from workers.policy.network import PolicyWeights, layer_sizes, standardisation
from workers.reparameterise import rescale_inputs_of


class PolicySettings(BaseModel):
    """The policy network and its training (thesis Table 11)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    hidden: list[int] = Field([128, 128, 128], min_length=1)
    """Units of each hidden ReLU layer (Table 11: 3 layers of 128)."""
    learning_rate: float = Field(5e-4, gt=0)
    """Adam learning rate."""
    l1: float = Field(1e-6, ge=0)
    """Weight of the l1 penalty on the weight matrices."""
    l2: float = Field(1e-5, ge=0)
    """Weight of the l2 penalty on the weight matrices."""
    batch_size: int = Field(1024, ge=1)
    """Samples per gradient step, drawn with replacement from the dataset."""
    gradient_steps: int = Field(1000, ge=1)
    """Gradient steps per training (Table 11 'iterations'); APEX trains twice per iteration."""
    keep_function: bool = True
    """When a carried-over network's input standardisation is refitted to the current dataset, rescale and shift
    its first layer so that it computes the same function of the raw observation; False: the old weights meet
    inputs standardised differently from those they were fitted on (the reading before)."""
    reinitialize: bool = False
    """Start every training from a freshly initialised network and optimiser (seeded by the trainer's seed and
    the training's index) instead of continuing from the last one. Alg. 3 initialises the weights once, before its
    loop, and every training updates them: False is that reading."""


class TrainReport(NamedTuple):
    """One training of the policy."""

    weights: PolicyWeights
    """The weights after it (version incremented)."""
    loss: float
    """MSE of the trained policy (unclipped output) over the whole dataset."""
    first_loss: float
    """MSE of the first batch, before its gradient step."""
    last_loss: float
    """Mean MSE of the last 10% of the batches."""
    samples: int
    """Dataset size (state-action pairs)."""
    seconds: float
    """Wall-clock seconds of the training."""
    cpu_seconds: float
    """CPU seconds of the trainer's process during the training (all its threads)."""
    threads: int
    """torch threads used."""


class PolicyTrainer:
    """Trains the policy network; stateful (network, optimiser, sampling generator, version).

    Args:
        seed: initialises the network and the batch sampling.
        settings: network and training settings.
        task: the task's name, stamped into the weights.
        cpus: CPUs this worker holds; torch uses that many threads (at least one).
        obs_dim / action_dim: the policy's input and output sizes; without them the network is built by
            :meth:`initialize`.
    """

    def __init__(
        self,
        seed: int,
        settings: PolicySettings | None = None,
        task: str = "",
        cpus: float = 1,
        obs_dim: int | None = None,
        action_dim: int | None = None,
    ):
        import torch

        self.seed = seed
        self.threads = max(1, int(cpus))
        torch.set_num_threads(self.threads)
        self.settings = PolicySettings.model_validate(settings if settings is not None else {})
        self.task = task
        self.model = None
        if obs_dim is not None and action_dim is not None:
            self.initialize(obs_dim, action_dim)

    def initialize(self, obs_dim: int, action_dim: int) -> PolicyWeights:
        """Build the randomly initialised network (once); return its weights (version 0 until trained)."""
        import torch

        if self.model is not None:
            if (self.obs_dim, self.action_dim) != (obs_dim, action_dim):
                raise ValueError(f"the policy is {self.obs_dim} -> {self.action_dim}, not {obs_dim} -> {action_dim}")
            return self.weights()
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self._build_network(self.seed)
        sampling_seed = int(np.random.SeedSequence([self.seed, 1]).generate_state(1)[0])
        self.generator = torch.Generator().manual_seed(sampling_seed)
        self.mean = np.zeros(obs_dim)
        self.std = np.ones(obs_dim)
        self.version = 0
        return self.weights()

    def _build_network(self, seed: int) -> None:
        """A randomly initialised network (``seed``) and a fresh optimiser for it."""
        import torch

        sizes = layer_sizes(self.obs_dim, self.action_dim, self.settings.hidden)
        torch.manual_seed(seed)
        layers: list[Any] = []
        for index, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            layers.append(torch.nn.Linear(n_in, n_out))
            if index < len(sizes) - 2:
                layers.append(torch.nn.ReLU())
        self.model = torch.nn.Sequential(*layers)
        self.linears = [layer for layer in self.model if isinstance(layer, torch.nn.Linear)]
        self.optimiser = torch.optim.Adam(self.model.parameters(), lr=self.settings.learning_rate)

    # ------------------------------------------------------------ weights
    def weights(self) -> PolicyWeights:
        """The current weights as numpy arrays (w: (in, out))."""
        arrays: dict[str, np.ndarray] = {}
        for index, layer in enumerate(self.linears):
            arrays[f"w{index}"] = layer.weight.detach().numpy().T.copy()
            arrays[f"b{index}"] = layer.bias.detach().numpy().copy()
        # Kept in float64 as trained: inputs far from zero with a small spread lose their standardisation in float32.
        arrays["input_mean"] = self.mean.astype(np.float64)
        arrays["input_std"] = self.std.astype(np.float64)
        return PolicyWeights(self.version, arrays, self.task)

    # ----------------------------------------------------------- training
    def _restandardise_first_layer(self, mean: np.ndarray, std: np.ndarray) -> None:
        """Fold a change of input standardisation into the first layer: with z = (x - m) / s and z' = (x - m') / s',
        W z + b = (W diag(s'/s)) z' + (b + W (m' - m) / s), so the network's output for every raw x is unchanged
        (up to the clipping of standardised inputs at +-INPUT_CLIP); Adam's moments follow the rescale
        (workers/reparameterise.py)."""
        import torch

        first = self.linears[0]
        with torch.no_grad():
            shift = torch.as_tensor((mean - self.mean) / self.std, dtype=first.weight.dtype)
            first.bias.add_(first.weight @ shift)
        rescale_inputs_of(first.weight, torch.as_tensor(std / self.std, dtype=first.weight.dtype), self.optimiser)

    def _inputs(self, observations: np.ndarray):
        import torch

        from workers.policy.network import INPUT_CLIP

        standardised = np.clip((observations - self.mean) / self.std, -INPUT_CLIP, INPUT_CLIP)
        return torch.as_tensor(standardised, dtype=torch.float32)

    def train(self, dataset: dict[str, np.ndarray], steps: int | None = None) -> TrainReport:
        """Fit the policy to ``dataset`` ({observations (M, obs_dim), actions (M, d)}) for ``steps`` steps."""
        import torch

        torch.set_num_threads(self.threads)
        started, cpu_started = time.perf_counter(), time.process_time()
        observations = np.asarray(dataset["observations"], dtype=np.float64)
        if self.model is None:
            self.initialize(observations.shape[1], np.shape(dataset["actions"])[1])
        targets = torch.as_tensor(np.asarray(dataset["actions"]), dtype=torch.float32)
        if len(observations) == 0:
            raise ValueError("cannot train the policy on an empty dataset")
        settings = self.settings
        if settings.reinitialize and self.version > 0:
            self._build_network(int(np.random.SeedSequence([self.seed, 2, self.version]).generate_state(1)[0]))
        mean, std = standardisation(observations)
        # A trained network is carried over; a fresh one (first training, or reinitialize) has nothing to keep.
        if settings.keep_function and self.version > 0 and not settings.reinitialize:
            self._restandardise_first_layer(mean, std)
        self.mean, self.std = mean, std
        inputs = self._inputs(observations)
        steps = settings.gradient_steps if steps is None else steps
        losses = np.empty(steps)
        for step in range(steps):
            index = torch.randint(0, len(inputs), (settings.batch_size,), generator=self.generator)
            mse = torch.mean((self.model(inputs[index]) - targets[index]) ** 2)
            penalty = 0.0
            for layer in self.linears:
                penalty = penalty + settings.l1 * layer.weight.abs().sum() + settings.l2 * (layer.weight**2).sum()
            self.optimiser.zero_grad()
            (mse + penalty).backward()
            self.optimiser.step()
            losses[step] = float(mse.detach())
        with torch.no_grad():
            loss = float(torch.mean((self.model(inputs) - targets) ** 2))
        self.version += 1
        tail = max(1, steps // 10)
        return TrainReport(
            weights=self.weights(),
            loss=loss,
            first_loss=float(losses[0]) if steps else loss,
            last_loss=float(losses[-tail:].mean()) if steps else loss,
            samples=len(inputs),
            seconds=time.perf_counter() - started,
            cpu_seconds=time.process_time() - cpu_started,
            threads=torch.get_num_threads(),
        )

    # -------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        if self.model is None:
            return {}
        return {
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "model": tensors_to_arrays(self.model.state_dict()),
            "optimiser": tensors_to_arrays(self.optimiser.state_dict()),
            "generator": self.generator.get_state().numpy().copy(),
            "mean": self.mean.copy(),
            "std": self.std.copy(),
            "version": self.version,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        import torch

        if not state:
            # The state of a trainer that never trained (a checkpoint from before round 0): forget any training
            # since, so that a round re-run after a restore starts from the same random initialisation.
            self.model = None
            return
        self.initialize(int(state["obs_dim"]), int(state["action_dim"]))
        self.model.load_state_dict(arrays_to_tensors(state["model"]))
        self.optimiser.load_state_dict(arrays_to_tensors(state["optimiser"]))
        self.generator.set_state(torch.from_numpy(np.array(state["generator"], dtype=np.uint8)))
        self.mean = np.array(state["mean"])
        self.std = np.array(state["std"])
        self.version = int(state["version"])

    def pid(self) -> int:
        """Process id (fault-injection tests)."""
        return os.getpid()
