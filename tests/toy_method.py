"""A small learning method for the service tests: collect on point_reach, fit a tiny torch model, repeat.

Registered through ``ICEMLAB_PLUGINS=toy_method`` (with tests/ on the path),
as a method kept outside icemlab would be. A round collects one episode of
random actions, sends the whole dataset to a stateful ``trainer`` role (one
``share`` per round), which fits a linear dynamics model for a few steps and
returns versioned weights. Its state (dataset, weights, optimiser, RNG) is
checkpointed, so a restarted trial continues exactly.
"""

from __future__ import annotations

import os
import time
from typing import Any, NamedTuple

import numpy as np
from pydantic import Field

from workers.checkpoint import arrays_to_tensors, restore_rng, rng_state, tensors_to_arrays
from workers.data import EpisodeBuffer, TrajectoryRecorder
from workers.methods import MethodSettings, Program, RoleSpec, TrialSpec, register
from workers.tasks import make_task


class ToySettings(MethodSettings):
    """Settings of the toy method."""

    rounds: int = Field(4, ge=1)
    """Rounds of collect-and-fit."""
    steps: int = Field(10, ge=1)
    """Environment steps per collected episode."""
    train_seconds: float = Field(0.0, ge=0)
    """Extra seconds every training call sleeps (gives fault tests time to kill the trainer mid-call)."""
    step_seconds: float = Field(0.0, ge=0)
    """Seconds every collected step sleeps (gives fault tests time to act while the trainer is idle)."""
    pause_file: str | None = None
    """Collecting waits while this file exists (a fault test holds the round there while a worker restarts)."""
    fail_on_round: int | None = None
    """Raise in this round (a deterministic code error)."""
    fail_until_file: str | None = None
    """With fail_on_round: raise only while this file does not exist (a fault the test then clears)."""


class Weights(NamedTuple):
    version: int
    arrays: dict[str, np.ndarray]


class ToyTrainer:
    """Fits next_obs - obs ~ W [obs, action] + b by a few Adam steps; stateful across calls."""

    def __init__(self, seed: int, cpus: int = 1, train_seconds: float = 0.0):
        import torch

        torch.set_num_threads(max(1, int(cpus)))
        torch.manual_seed(seed)
        self.model = torch.nn.Linear(8, 6, dtype=torch.float64)
        self.optimiser = torch.optim.Adam(self.model.parameters(), lr=1e-2)
        self.version = 0
        self.train_seconds = train_seconds

    def train(self, dataset: dict[str, np.ndarray]) -> tuple[Weights, float]:
        import torch

        time.sleep(self.train_seconds)
        inputs = torch.from_numpy(np.concatenate([dataset["observations"], dataset["actions"]], axis=1))
        targets = torch.from_numpy(dataset["next_observations"] - dataset["observations"])
        for _ in range(20):
            self.optimiser.zero_grad()
            loss = torch.mean((self.model(inputs) - targets) ** 2)
            loss.backward()
            self.optimiser.step()
        self.version += 1
        arrays = {k: v.detach().numpy().copy() for k, v in self.model.state_dict().items()}
        return Weights(self.version, arrays), float(loss.detach())

    def state_dict(self) -> dict[str, Any]:
        return {
            "model": tensors_to_arrays(self.model.state_dict()),
            "optimiser": tensors_to_arrays(self.optimiser.state_dict()),
            "version": self.version,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(arrays_to_tensors(state["model"]))
        self.optimiser.load_state_dict(arrays_to_tensors(state["optimiser"]))
        self.version = int(state["version"])

    def pid(self) -> int:
        return os.getpid()


@register
class ToyProgram(Program):
    """Collect, fit, repeat."""

    name = "toy"
    Settings = ToySettings
    description = "test method: collect random episodes on point_reach and fit a linear model"
    metrics = {"loss": "final_loss"}
    role_names = ("trainer",)

    @classmethod
    def planned_rounds(cls, trial: TrialSpec) -> int:
        return trial.settings.rounds

    @classmethod
    def roles_for(cls, trial: TrialSpec, unit_cpus: int, counts) -> list[RoleSpec]:
        kwargs = {"seed": trial.seed, "cpus": 1, "train_seconds": trial.settings.train_seconds}
        return [RoleSpec("trainer", ToyTrainer, 1, 1, kwargs, stateful=True)]

    @classmethod
    def runner_cpus(cls, trial: TrialSpec, unit_cpus: int) -> int:
        return 1

    def __init__(self, trial: TrialSpec, roles, cpus: int):
        super().__init__(trial, roles, cpus)
        self.task = make_task(trial.task)
        self.env = self.task.make_env()
        self.rng = np.random.default_rng(trial.seed)
        self.buffer = EpisodeBuffer()
        self.weights: Weights | None = None

    def run_round(self, index: int):
        from workers.methods import RoundReport

        settings = self.trial.settings
        if index == settings.fail_on_round and not (
            settings.fail_until_file and os.path.exists(settings.fail_until_file)
        ):
            raise ValueError(f"toy method fails on round {index} as configured")
        observation, _ = self.env.reset(seed=int(self.rng.integers(2**31)))
        recorder = TrajectoryRecorder(self.task.observe(observation))
        for t in range(self.trial.settings.steps):
            action = self.rng.uniform(-1, 1, self.task.action_dim)
            outcome = self.task.step_env(self.env, action)
            recorder.add(action, outcome.reward, self.task.observe(outcome.observation))
            time.sleep(self.trial.settings.step_seconds)
            while settings.pause_file and os.path.exists(settings.pause_file):
                time.sleep(0.05)
            self.set_progress((t + 1) / self.trial.settings.steps, f"step {t + 1}")
        self.buffer.add(recorder.finish())
        transitions = self.buffer.transitions()
        dataset = {k: getattr(transitions, k) for k in ("observations", "actions", "next_observations")}
        trainer = self.roles["trainer"]
        self.weights, loss = trainer.submit(0, "train", trainer.share(dataset)).result()
        done = index + 1 >= self.trial.settings.rounds
        metrics = {
            "loss": loss,
            "weights_version": float(self.weights.version),
            "dataset_steps": float(self.buffer.steps),
        }
        return RoundReport(index, metrics, step=index, done=done, summary={"final_loss": loss} if done else {})

    def state_dict(self) -> dict[str, Any]:
        trainer_state = self.roles["trainer"].submit(0, "state_dict").result()
        return {"buffer": self.buffer.to_tree(), "rng": rng_state(self.rng), "trainer": trainer_state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.buffer = EpisodeBuffer.from_tree(state["buffer"])
        self.rng = restore_rng(state["rng"])
        self.roles["trainer"].submit(0, "load_state_dict", state["trainer"]).result()

    def close(self) -> None:
        self.env.close()
