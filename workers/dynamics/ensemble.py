"""Probabilistic ensemble of dynamics models (thesis section 5.3.3, eq. 19, App. D.2.1).

K MLP members, each predicting a diagonal Gaussian over the state *delta*
(``predict_deltas`` True in Table 13): member k models
N(s' ; s + mu_k(s, a), diag(exp(logvar_k(s, a)))).

All members run as ONE batched computation: every layer holds its weights as a
(K, in, out) tensor and its biases as (K, 1, out), and a layer is a single
``torch.baddbmm`` over a (K, B, in) input. There is no Python loop over
members, so planning cost grows with the batch, not with the number of calls.

Reading of the thesis where it is silent (see also :class:`EnsembleConfig`):

* ``num_layers`` of Tables 13/14 is the number of *hidden* layers of width
  ``size`` (the convention of the PETS-derived frameworks whose parameter names
  the tables use); an output layer of 2 x obs_dim follows.
* Weights use a normal truncated at two standard deviations, std 1/(2 sqrt(in))
  ("truncated_normal", Table 13, as in the PETS code; ``init_std_scale``), biases start at 0.
* Log-variance bounds are soft (D.2.1) and, as the thesis decided, fixed:
  ``learn_logvar_bounds`` can make them learnable (with the PETS regulariser),
  default off.
* Inputs (obs, action) are normalised by mean and std fitted on the training
  data at every training call (``use_input_normalization`` True); outputs are
  not normalised (``use_output_normalization`` False). A warm-started model
  folds the change of normalisation into its first layer (``keep_function``),
  so refitting it does not move what the members predict.
* Warm start: a training call continues from the current weights and Adam
  state by default. The thesis only lists ``epochs`` per training call
  (Table 13) and ``train_epochs_only_with_latest_data`` False, i.e. every call
  trains a fixed number of epochs on all data so far; that budget only makes
  sense for a model that keeps learning between calls, as the lab framework it
  comes from does. ``retrain_from_scratch`` (or ``from_scratch=True`` for one
  call) re-initialises weights and optimiser first.
"""

from __future__ import annotations

import io
import json
import math
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from workers.dynamics.settings import ENSEMBLE_PRESETS, PRESET_SHAPES, EnsembleConfig  # noqa: F401 (re-exported)
from workers.reparameterise import rescale_inputs_of

CHECKPOINT_FORMAT = 2
"""Version of the layout written by :meth:`DynamicsEnsemble.export_state`. 2: the state bounds of the
propagation clamp (EnsembleConfig.state_margin) are part of the weights."""

LOGVAR_AT_BOUND = 0.1
"""A predicted log-variance within this distance of a bound counts as "at the bound" in :class:`TrainStats`."""

ACTIVATIONS = {"silu": F.silu, "relu": F.relu, "tanh": torch.tanh, "elu": F.elu}


class Transitions(NamedTuple):
    """A dataset of environment transitions, as numpy arrays with a leading batch dimension."""

    observations: np.ndarray
    """(n, obs_dim) states s_t."""
    actions: np.ndarray
    """(n, action_dim) actions a_t as the model sees them (normalised to [-1, 1])."""
    next_observations: np.ndarray
    """(n, obs_dim) states s_{t+1}."""

    def __len__(self) -> int:  # a NamedTuple's len would be 3
        return int(self.observations.shape[0])

    @staticmethod
    def concatenate(parts: list[Transitions]) -> Transitions:
        """All transitions of several datasets in one."""
        return Transitions(*(np.concatenate([getattr(p, f) for p in parts]) for f in Transitions._fields))


class TrainStats(NamedTuple):
    """What one training call did; losses are averaged over members, samples and dimensions."""

    train_nll: float
    """Gaussian NLL (see :func:`gaussian_nll`) on the training data after training."""
    train_mse: float
    """Mean squared error of the predicted delta on the training data after training."""
    held_out_nll: float | None
    """The same NLL on the held-out set (None without one)."""
    held_out_mse: float | None
    """The same MSE on the held-out set (None without one)."""
    at_min_logvar: float
    """Fraction of predicted log-variances within LOGVAR_AT_BOUND of min_logvar (held-out set, else training data)."""
    at_max_logvar: float
    """Fraction within LOGVAR_AT_BOUND of max_logvar."""
    epochs: int
    """Epochs run."""
    gradient_steps: int
    """Optimiser steps taken."""
    seconds: float
    """Wall-clock time of the call (including the evaluation of the losses)."""
    weights_version: int
    """Version of the weights after the call."""
    from_scratch: bool
    """Whether the call re-initialised the weights first."""


def gaussian_nll(mean: torch.Tensor, logvar: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean over all elements of 0.5 (logvar + (target - mean)^2 / var).

    Eq. 19 without 0.5 log(2 pi), averaged over the state dimensions where eq. 19 sums them (as the PETS code
    does): the loss is eq. 19 / d, which scales it against weight decay and the gradient-norm limit of Table 13.

    Equal to ``torch.nn.GaussianNLLLoss(full=False, reduction="mean")(mean, target, var)``
    whenever var exceeds that loss's eps (1e-6; our bounded variances do: exp(-10) = 4.5e-5).
    """
    return 0.5 * (logvar + (target - mean).square() * torch.exp(-logvar)).mean()


def soft_bound_logvar(raw: torch.Tensor, min_logvar: torch.Tensor, max_logvar: torch.Tensor) -> torch.Tensor:
    """Softly bound log-variances into [min, max] (D.2.1, after Chua et al. App. A.1).

    The two softplus steps of the PETS code can overshoot max by up to
    log(1 + exp(-(max - min))) (4.5e-5 for Table 14's [-6, 4]); the final clamp
    removes that sliver, so the bound holds exactly.
    """
    logvar = max_logvar - F.softplus(max_logvar - raw)
    logvar = min_logvar + F.softplus(logvar - min_logvar)
    return torch.minimum(torch.maximum(logvar, min_logvar), max_logvar)


class EnsembleMLP(nn.Module):
    """K MLPs evaluated as one batched computation; inputs and outputs carry a leading member dimension."""

    def __init__(self, in_dim: int, out_dim: int, config: EnsembleConfig):
        super().__init__()
        self.config = config
        self.act = ACTIVATIONS[config.activation]
        sizes = [in_dim] + [config.hidden_size] * config.hidden_layers + [2 * out_dim]
        k = config.ensemble_size
        self.weights = nn.ParameterList(nn.Parameter(torch.empty(k, i, o)) for i, o in zip(sizes[:-1], sizes[1:]))
        self.biases = nn.ParameterList(nn.Parameter(torch.zeros(k, 1, o)) for o in sizes[1:])
        bounds = (torch.full((out_dim,), config.min_logvar), torch.full((out_dim,), config.max_logvar))
        if config.learn_logvar_bounds:
            self.min_logvar, self.max_logvar = nn.Parameter(bounds[0]), nn.Parameter(bounds[1])
        else:
            self.register_buffer("min_logvar", bounds[0])
            self.register_buffer("max_logvar", bounds[1])
        self.register_buffer("input_mean", torch.zeros(in_dim))
        self.register_buffer("input_std", torch.ones(in_dim))
        # Where propagated states are clamped (fit to the training data with the normaliser; +-inf: nowhere).
        self.register_buffer("state_low", torch.full((out_dim,), -math.inf))
        self.register_buffer("state_high", torch.full((out_dim,), math.inf))
        self.out_dim = out_dim
        self.layer_sizes = sizes

    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Truncated-normal weights (std init_std_scale / sqrt(fan_in), cut at 2 std) and zero biases (Table 13)."""
        with torch.no_grad():
            for weight in self.weights:
                std = self.config.init_std_scale / math.sqrt(weight.shape[1])
                # Resampling by hand: nn.init.trunc_normal_ takes no generator.
                values = torch.randn(weight.shape, generator=generator)
                while (outside := values.abs() > 2.0).any():
                    values[outside] = torch.randn(int(outside.sum()), generator=generator)
                weight.copy_(values * std)
            for bias in self.biases:
                bias.zero_()
            self.min_logvar.fill_(self.config.min_logvar)
            self.max_logvar.fill_(self.config.max_logvar)

    def forward(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(K, B, in) raw inputs -> (mean delta, bounded logvar), each (K, B, out)."""
        h = (inputs - self.input_mean) / self.input_std
        last = len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(bias, h, weight)
            if i < last:
                h = self.act(h)
        mean, raw_logvar = h.split(self.out_dim, dim=-1)
        return mean, soft_bound_logvar(raw_logvar, self.min_logvar, self.max_logvar)


def epoch_orders(n: int, members: int, epochs: int, bootstrap: bool, generator: torch.Generator):
    """Each epoch's sample indices per member, (members, n).

    Every member sees its data in its own order, so that members differ in more than their initial weights.
    With ``bootstrap`` (PETS), each member's data is one resample with replacement, drawn once for the
    training call and reshuffled every epoch: a fresh resample every epoch would show each member nearly all
    the data over the epochs.
    """
    resample = torch.randint(n, (members, n), generator=generator) if bootstrap else None
    for _ in range(epochs):
        order = torch.rand(members, n, generator=generator).argsort(dim=1)
        yield order if resample is None else resample.gather(1, order)


class DynamicsEnsemble:
    """A probabilistic ensemble dynamics model with its optimiser and a weights version.

    Args:
        obs_dim: state dimensions d_s.
        action_dim: action dimensions d_a.
        config: architecture and training settings.
        seed: seeds the initial weights.
    """

    def __init__(self, obs_dim: int, action_dim: int, config: EnsembleConfig | None = None, seed: int = 0):
        self.config = config or EnsembleConfig()
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.net = EnsembleMLP(obs_dim + action_dim, obs_dim, self.config)
        self.seed = seed
        self.weights_version = 0
        """Counts weight changes: +1 per training call; restored by import_state."""
        self._initialise(seed)

    @property
    def ensemble_size(self) -> int:
        return self.config.ensemble_size

    def _initialise(self, seed: int) -> None:
        self.net.reset_parameters(torch.Generator().manual_seed(seed))
        self.optimizer = self._make_optimizer()

    def _make_optimizer(self) -> torch.optim.Adam:
        net, config = self.net, self.config
        groups = [
            # PETS decays the weight matrices only; biases and bounds are left alone.
            {"params": list(net.weights), "weight_decay": config.weight_decay},
            {"params": list(net.biases), "weight_decay": 0.0},
        ]
        if config.learn_logvar_bounds:
            groups.append({"params": [net.min_logvar, net.max_logvar], "weight_decay": 0.0})
        return torch.optim.Adam(groups, lr=config.lr, eps=config.adam_eps)

    # ------------------------------------------------------------ predicting
    def predict(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(K, B, obs_dim + action_dim) -> (mean delta, logvar), each (K, B, obs_dim); no gradients."""
        with torch.no_grad():
            return self.net(inputs)

    @staticmethod
    def _inputs_targets(data: Transitions) -> tuple[torch.Tensor, torch.Tensor]:
        obs = torch.as_tensor(data.observations, dtype=torch.float32)
        inputs = torch.cat([obs, torch.as_tensor(data.actions, dtype=torch.float32)], dim=-1)
        targets = torch.as_tensor(data.next_observations, dtype=torch.float32) - obs
        return inputs, targets

    def fit_normalizer(self, data: Transitions, keep_function: bool = False) -> None:
        """Fit the input normalisation (use_input_normalization, Table 13) to a dataset.

        With ``keep_function`` the change is folded into every member's first layer: with z = (x - m) / s and
        z' = (x - m') / s', z W + b = z' (diag(s'/s) W) + (b + ((m' - m) / s) W), so each member's output for
        every raw input stays the same; Adam's moments follow the rescale (workers/reparameterise.py).
        """
        inputs, _ = self._inputs_targets(data)
        std = inputs.std(dim=0, unbiased=False)
        # Constant inputs (e.g. a quaternion that never rotates) would divide by (almost) zero.
        threshold = max(self.config.input_std_threshold, 1e-6)
        mean, std = inputs.mean(dim=0), torch.where(std < threshold, torch.ones_like(std), std)
        if keep_function:
            net = self.net
            with torch.no_grad():
                shift = (mean - net.input_mean) / net.input_std
                net.biases[0].add_(torch.einsum("i,kio->ko", shift, net.weights[0]).unsqueeze(1))
            rescale_inputs_of(net.weights[0], (std / net.input_std).view(1, -1, 1), self.optimizer)
        self.net.input_mean.copy_(mean)
        self.net.input_std.copy_(std)
        if self.config.state_margin is not None:
            next_states = torch.as_tensor(data.next_observations, dtype=torch.float32)
            states = torch.cat([inputs[:, : self.obs_dim], next_states])
            low, high = states.min(dim=0).values, states.max(dim=0).values
            margin = self.config.state_margin * (high - low)
            self.net.state_low.copy_(low - margin)
            self.net.state_high.copy_(high + margin)

    def clamp_states(self, states: torch.Tensor) -> torch.Tensor:
        """States clamped into the widened range of the training data (EnsembleConfig.state_margin)."""
        if self.config.state_margin is None:
            return states
        return torch.clamp(states, self.net.state_low, self.net.state_high)

    # ------------------------------------------------------------ training
    def _clip_per_member(self) -> None:
        """Scale each member's gradient to at most grad_norm (members are separate models)."""
        params = [p for p in [*self.net.weights, *self.net.biases] if p.grad is not None]
        squared = torch.stack([p.grad.square().flatten(1).sum(dim=1) for p in params]).sum(dim=0)  # (K,)
        scale = (self.config.grad_norm / (squared.sqrt() + 1e-6)).clamp(max=1.0)
        for p in params:
            p.grad.mul_(scale.view(-1, *([1] * (p.grad.dim() - 1))))

    def evaluate(self, data: Transitions, chunk: int = 8192) -> tuple[float, float, float, float]:
        """(NLL, MSE, fraction at min_logvar, fraction at max_logvar) over a dataset, all members."""
        inputs, targets = self._inputs_targets(data)
        k = self.ensemble_size
        totals = np.zeros(4)
        with torch.no_grad():
            for start in range(0, len(inputs), chunk):
                x, y = inputs[start : start + chunk], targets[start : start + chunk]
                mean, logvar = self.net(x.expand(k, -1, -1))
                weight = len(x) / len(inputs)
                totals += weight * np.array(
                    [
                        gaussian_nll(mean, logvar, y.expand(k, -1, -1)).item(),
                        (mean - y).square().mean().item(),
                        (logvar < self.net.min_logvar + LOGVAR_AT_BOUND).float().mean().item(),
                        (logvar > self.net.max_logvar - LOGVAR_AT_BOUND).float().mean().item(),
                    ]
                )
        return tuple(float(v) for v in totals)  # type: ignore[return-value]

    def train(
        self,
        data: Transitions,
        held_out: Transitions | None = None,
        *,
        from_scratch: bool | None = None,
        epochs: int | None = None,
        seed: int = 0,
    ) -> TrainStats:
        """Train every member on all of ``data`` for the configured epochs (eq. 19); see the module docstring.

        Args:
            data: training transitions.
            held_out: transitions to report held-out losses on (never trained on).
            from_scratch: re-initialise weights and optimiser first; None: the config's retrain_from_scratch.
            epochs: override the configured number of epochs for this call.
            seed: seeds minibatch order; the same weights, data and seed give the same result.
        """
        started = time.perf_counter()
        config = self.config
        if len(data) == 0:
            raise ValueError("cannot train on an empty dataset")
        if from_scratch is None:
            from_scratch = config.retrain_from_scratch
        if from_scratch:
            self._initialise(self.seed + 1_000_003 * (self.weights_version + 1))
        # A model that has trained keeps what it learned when the normalisation moves; a fresh one has nothing to keep.
        self.fit_normalizer(data, keep_function=config.keep_function and self.weights_version > 0 and not from_scratch)
        inputs, targets = self._inputs_targets(data)
        n, k = len(inputs), self.ensemble_size
        generator = torch.Generator().manual_seed(seed)
        batch = min(config.batch_size, n)
        epochs = config.epochs if epochs is None else epochs
        steps = 0
        self.net.train()
        for order in epoch_orders(n, k, epochs, config.bootstrap, generator):
            for start in range(0, n, batch):
                index = order[:, start : start + batch]
                mean, logvar = self.net(inputs[index])
                # Sum over members of each member's mean loss: a member's gradient is what it would be alone.
                loss = k * gaussian_nll(mean, logvar, targets[index])
                if config.learn_logvar_bounds:
                    loss = loss + 0.01 * (self.net.max_logvar.sum() - self.net.min_logvar.sum())
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                if config.grad_norm is not None:
                    self._clip_per_member()
                self.optimizer.step()
                steps += 1
        self.net.eval()
        self.weights_version += 1
        train_nll, train_mse, low, high = self.evaluate(data)
        held_nll = held_mse = None
        if held_out is not None and len(held_out):
            held_nll, held_mse, low, high = self.evaluate(held_out)
        return TrainStats(
            train_nll=train_nll,
            train_mse=train_mse,
            held_out_nll=held_nll,
            held_out_mse=held_mse,
            at_min_logvar=low,
            at_max_logvar=high,
            epochs=epochs,
            gradient_steps=steps,
            seconds=time.perf_counter() - started,
            weights_version=self.weights_version,
            from_scratch=from_scratch,
        )

    # ------------------------------------------------------------ state
    def export_state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Weights, normaliser and Adam state as (numpy arrays, JSON-able metadata); no pickle anywhere."""
        arrays = self._net_arrays()
        optimizer = self.optimizer.state_dict()
        steps: dict[str, float] = {}
        for index, state in optimizer["state"].items():
            for key, value in state.items():
                if key == "step":
                    steps[str(index)] = float(value)
                else:
                    arrays[f"adam.{index}.{key}"] = value.detach().cpu().numpy().copy()
        return arrays, self._meta(steps)

    def import_state(self, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
        """Load what :meth:`export_state` produced (shapes and config must match this ensemble)."""
        if meta.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"checkpoint format {meta.get('format')!r}, expected {CHECKPOINT_FORMAT}")
        if EnsembleConfig(**meta["config"]) != self.config or (meta["obs_dim"], meta["action_dim"]) != (
            self.obs_dim,
            self.action_dim,
        ):
            raise ValueError("checkpoint was written by an ensemble of another shape or config")
        state = {name[4:]: torch.as_tensor(a) for name, a in arrays.items() if name.startswith("net.")}
        self.net.load_state_dict(state)
        self.optimizer = self._make_optimizer()
        saved = self.optimizer.state_dict()
        for index, step in meta["adam_steps"].items():
            saved["state"][int(index)] = {
                "step": torch.tensor(step),
                "exp_avg": torch.as_tensor(arrays[f"adam.{index}.exp_avg"]).clone(),
                "exp_avg_sq": torch.as_tensor(arrays[f"adam.{index}.exp_avg_sq"]).clone(),
            }
        self.optimizer.load_state_dict(saved)
        self.weights_version = int(meta["weights_version"])

    @classmethod
    def from_state(cls, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> DynamicsEnsemble:
        """A new ensemble rebuilt from exported state."""
        model = cls(meta["obs_dim"], meta["action_dim"], EnsembleConfig(**meta["config"]), seed=meta["seed"])
        model.import_state(arrays, meta)
        return model

    def export_weights(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Weights and input normaliser without the optimiser state: what planning needs (a quarter of the bytes).

        :meth:`from_state` rebuilds a model from it (with a fresh optimiser).
        """
        return self._net_arrays(), self._meta({})

    def _net_arrays(self) -> dict[str, np.ndarray]:
        """The network's parameters and buffers (the input normaliser among them) as numpy arrays."""
        return {f"net.{name}": t.detach().cpu().numpy().copy() for name, t in self.net.state_dict().items()}

    def _meta(self, adam_steps: dict[str, float]) -> dict[str, Any]:
        """The JSON-able part of a checkpoint; ``adam_steps`` is empty for weights without optimiser state."""
        return {
            "format": CHECKPOINT_FORMAT,
            "obs_dim": self.obs_dim,
            "action_dim": self.action_dim,
            "config": self.config.model_dump(),
            "seed": self.seed,
            "weights_version": self.weights_version,
            "adam_steps": adam_steps,
        }

    def to_bytes(self, weights_only: bool = False) -> bytes:
        """The bytes of an ``.npz`` checkpoint (see :meth:`save`)."""
        arrays, meta = self.export_weights() if weights_only else self.export_state()
        return npz_bytes(arrays, meta)

    def save(self, path: str | Path, weights_only: bool = False) -> None:
        """Write an ``.npz`` checkpoint; metadata is a JSON string stored as bytes (loads with allow_pickle=False).

        ``weights_only`` leaves the Adam state out. Load either kind with
        ``DynamicsEnsemble.load(path)``.
        """
        Path(path).write_bytes(self.to_bytes(weights_only))

    @classmethod
    def from_bytes(cls, data: bytes) -> DynamicsEnsemble:
        """A model from the bytes of an ``.npz`` checkpoint, without unpickling anything."""
        return cls.from_state(*read_npz(io.BytesIO(data)))

    @classmethod
    def load(cls, path: str | Path) -> DynamicsEnsemble:
        """Read a checkpoint written by :meth:`save` (or an ``mbrl`` run's ``models/*.npz``), without unpickling."""
        return cls.from_state(*read_npz(path))


def npz_bytes(arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> bytes:
    """An ensemble checkpoint archive: the arrays plus the JSON metadata as the uint8 member ``__meta__``."""
    buffer = io.BytesIO()
    np.savez(buffer, __meta__=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
    return buffer.getvalue()


def read_npz(source: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(arrays, metadata) of an ensemble checkpoint archive (a path or a file object); pickles are refused."""
    with np.load(source, allow_pickle=False) as archive:
        if "__meta__" not in archive.files:
            raise ValueError("not an ensemble checkpoint (no __meta__ member)")
        arrays = {name: archive[name] for name in archive.files if name != "__meta__"}
        meta = json.loads(archive["__meta__"].tobytes().decode())
    return arrays, meta
