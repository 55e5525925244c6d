"""Chapter 3 as a method: MPC episodes of a CEM-family planner on MuJoCo ground truth.

A trial runs ``episodes`` episodes, each with its own seed. A round is a
segment of ``round_steps`` environment steps of an episode: the trial's state
is checkpointed after every segment (environment, planner memory and random
state, the episode's records), so a lost process costs at most one segment and
the resumed episode is the same, step for step, as an uninterrupted one.

With ``ensemble`` set, the planner plans on P noisy ground-truth rollouts per
sequence with RAZER's cost (thesis App. D.4, Noisy-FetchPickAndPlace, Fig.
19b; workers/dynamics/ground_truth.py): ``aleatoric_weight`` 0 is PETS.
"""

from __future__ import annotations

import io
import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from workers.dynamics.settings import UncertaintyDims, UncertaintyReduction
from workers.methods.base import Artifact, MethodSettings, Program, RoleSpec, RoundReport, TrialSpec, located_error
from workers.mpc import MpcEpisode
from workers.planning import CEMPlanner, PlannerConfig
from workers.simulation import SimulationPool
from workers.tasks import GroundTruthTask, make_task


class GroundTruthEnsembleSettings(BaseModel):
    """Plan on an ensemble of noisy ground-truth simulators with RAZER's cost (App. D.4); w_A = 0 is PETS."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    particles: int = Field(5, ge=1)
    """P, noisy rollouts per action sequence, each with its own draws of the task's noise (not in the thesis)."""
    aleatoric_weight: float = Field(0.0, ge=0)
    """w_A of the aleatoric penalty (eq. 26) on the particles' spread; 0: PETS, the mean particle cost."""
    uncertainty_reduction: UncertaintyReduction = "sum_sqrt"
    """How the per-dimension standard deviations combine (workers/dynamics/costs.py)."""
    uncertainty_dims: UncertaintyDims | None = None
    """Observation dimensions whose spread is Var_A; None: the task's own (the box position on
    noisy_fetch_pick_place)."""


class MpcSettings(MethodSettings):
    """MPC episodes with a planner of the CEM family (thesis chapter 3)."""

    planner: PlannerConfig = PlannerConfig()
    """The planner: budget, horizon and the switches of the CEM family (see PlannerConfig)."""
    episodes: int = Field(1, ge=1)
    """MPC episodes per trial (each with its own seed derived from the trial seed)."""
    max_steps: int | None = Field(None, ge=1)
    """Cut episodes to this many steps (smoke runs); default: the task's episode length."""
    planner_seed_offset: int = Field(0, ge=0)
    """Seed the planner's noise with the episode's seed plus this offset; the environment's reset keeps the
    episode's seed. 0: one integer seeds both. Replaying the same start states with another offset tells a
    hard start (fails again) from the planner's sampling (succeeds)."""
    round_steps: int = Field(100, ge=1)
    """Environment steps per round: the trial is checkpointed this often, and a lost process repeats at most
    this many steps. Results do not depend on it."""
    ensemble: GroundTruthEnsembleSettings | None = None
    """Plan on P noisy ground-truth particles per sequence with RAZER's cost (tasks with a noise process:
    noisy_fetch_pick_place); None: one noise-free rollout per sequence."""


def episode_seed(trial_seed: int, episode: int) -> int:
    """Seed of episode ``episode`` of a trial: the trial seed first, then derived ones."""
    if episode == 0:
        return trial_seed
    return int(np.random.SeedSequence([trial_seed, episode]).generate_state(1)[0] % 2**31)


class MpcProgram(Program):
    """MPC episodes of one task (the chapter 3 experiments, Table 3)."""

    name = "mpc"
    Settings = MpcSettings
    description = "MPC episodes with iCEM or a CEM baseline on MuJoCo ground truth (chapter 3)"
    metrics = {"episode_return": "mean_return", "success": "success_rate", "box_drops": "mean_box_drops"}
    label_paths = {"algorithm": ("algorithm", "planner.algorithm"), "budget": ("planner.budget",)}
    curves = ("step/return",)
    independent_episodes = True  # each episode plans on ground truth from its own seed; nothing carries over
    curve_step = "environment step"
    # An episode's start state and the seeds of its noise and planner are functions of (trial seed, episode
    # index) alone (episode_seed), so a variant and its baseline meet the same layouts.
    paired_episodes = True
    role_names = ("simulation",)

    settings: MpcSettings

    @classmethod
    def resolve(cls, settings: MpcSettings, task: GroundTruthTask) -> MpcSettings:
        if settings.ensemble is not None:
            cls._check_ensemble(settings.ensemble, task)
        return settings.model_copy(update={"planner": settings.planner.resolved(task.colored_noise_beta)})

    @staticmethod
    def _check_ensemble(ensemble: GroundTruthEnsembleSettings, task: GroundTruthTask) -> None:
        """Refuse ensemble settings that the task cannot honour, at the setting's location."""
        if not task.noise_dim:
            raise located_error(
                ("ensemble",),
                f"{task.name} has deterministic dynamics: every particle would be the same rollout; an ensemble "
                "of noisy ground-truth simulators needs a task with a noise process (noisy_fetch_pick_place)",
            )
        if not task.batch_observations or task.observation_dim is None:
            raise located_error(("ensemble",), f"{task.name} computes no observations of simulated batches")
        dims = ensemble.uncertainty_dims or ()
        outside = [d for d in dims if d >= task.observation_dim]
        if outside:
            raise located_error(
                ("ensemble", "uncertainty_dims"),
                f"dimension {outside[0]} is outside {task.name}'s {task.observation_dim}-d observation "
                f"(0 to {task.observation_dim - 1})",
                list(dims),
            )

    @classmethod
    def roles_for(cls, trial: TrialSpec, unit_cpus: int, counts) -> list[RoleSpec]:
        # The runner simulates with a co-located worker; further workers are the role's actors.
        remote = max(0, counts.get("simulation", 1) - 1)
        kwargs = {
            "task_name": trial.task,
            "threads": unit_cpus,
            "task_options": trial.settings.task_options,
            "ensemble": cls._ensemble(trial.settings),
        }
        from workers.simulation import SimulationWorker

        return [RoleSpec("simulation", SimulationWorker, remote, unit_cpus, kwargs)] if remote else []

    @classmethod
    def work(cls, trial: TrialSpec) -> float:
        """Environment steps of the whole trial."""
        from workers.tasks import TASKS

        return float(trial.settings.episodes * (trial.settings.max_steps or TASKS[trial.task].episode_length))

    @classmethod
    def calibrate(cls, trial: TrialSpec, cpus: int, steps: int = 4) -> float:
        """Core-seconds per environment step: a few MPC steps of the trial's planner, the first left out."""
        import time

        task = make_task(trial.task, trial.settings.task_options)
        env = task.make_env()
        pool = SimulationPool(trial.task, cpus, None, trial.settings.task_options, cls._ensemble(trial.settings))
        try:
            planner = CEMPlanner(trial.settings.planner, task.action_dim, seed=trial.seed)
            episode = MpcEpisode(task, env, planner, pool, trial.seed, steps)
            episode.run(1)  # warms the thread pool and the caches
            started = time.perf_counter()
            episode.run()
            return (time.perf_counter() - started) / (steps - 1) * cpus
        finally:
            pool.close()
            env.close()

    @staticmethod
    def _ensemble(settings: MpcSettings) -> dict[str, Any] | None:
        return None if settings.ensemble is None else settings.ensemble.model_dump()

    @classmethod
    def labels(cls, trial: TrialSpec) -> dict[str, str]:
        """Algorithm and budget name the trial; horizon and particles are tagged too because the cost of a step
        grows with each, so a sweep's time estimate only reuses past runs that simulated as much per step."""
        planner, ensemble = trial.settings.planner, trial.settings.ensemble
        labels = {"algorithm": planner.algorithm, "budget": str(planner.budget), "horizon": str(planner.horizon)}
        return labels | ({"particles": str(ensemble.particles)} if ensemble is not None else {})

    @classmethod
    def label_text(cls, labels) -> list[str]:
        return [labels["algorithm"], f"b{labels['budget']}"]

    def __init__(self, trial: TrialSpec, roles, cpus: int):
        super().__init__(trial, roles, cpus)
        self.settings = trial.settings
        self.task = make_task(trial.task, self.settings.task_options)
        self.env = self.task.make_env()
        self.steps = self.settings.max_steps or self.task.episode_length
        self.segments = math.ceil(self.steps / self.settings.round_steps)
        ensemble = self._ensemble(self.settings)
        self.pool = SimulationPool(
            trial.task, cpus, roles.get("simulation"), self.settings.task_options, ensemble, trial.seed
        )
        self.planner = CEMPlanner(self.settings.planner, self.task.action_dim, seed=trial.seed)
        self.episode: MpcEpisode | None = None
        self.episode_index = 0
        self.episode_seconds = 0.0
        self.restarts_at_episode_start = 0
        self.finished: list[dict[str, float]] = []

    @classmethod
    def planned_rounds(cls, trial: TrialSpec) -> int:
        from workers.tasks import TASKS

        settings = trial.settings
        steps = settings.max_steps or TASKS[trial.task].episode_length
        return settings.episodes * math.ceil(steps / settings.round_steps)

    def _start_episode(self) -> MpcEpisode:
        seed = episode_seed(self.trial.seed, self.episode_index)
        self.restarts_at_episode_start = self.pool.restarts
        self.episode_seconds = 0.0
        planner_seed = seed + self.settings.planner_seed_offset
        return MpcEpisode(self.task, self.env, self.planner, self.pool, seed, self.steps, planner_seed=planner_seed)

    def run_round(self, index: int) -> RoundReport:
        import time

        episode_index, segment = divmod(index, self.segments)
        if episode_index != self.episode_index or self.episode is None:
            self.episode_index = episode_index
            self.episode = self._start_episode()
        episode = self.episode
        start = episode.t
        until = min(self.steps, (segment + 1) * self.settings.round_steps)
        label = f"ep {episode_index + 1}/{self.settings.episodes} step"

        def on_step(record) -> None:
            done = record.step + 1 - start
            self.set_progress(done / max(until - start, 1), f"{label} {record.step + 1}/{self.steps}")

        started = time.perf_counter()
        records = episode.run(until, on_step)
        self.episode_seconds += time.perf_counter() - started

        rewards = np.array([r.reward for r in episode.records])
        offset = episode_index * self.steps
        series = {
            "step/reward": [r.reward for r in records],
            "step/return": list(np.cumsum(rewards)[start:until]),
            "step/planning_seconds": [r.planning_seconds for r in records],
            "step/trajectories": [r.trajectories for r in records],
            "step/best_cost": [r.best_cost for r in records],
        }
        metrics: dict[str, float] = {}
        artifacts: list[Artifact] = []
        if episode.done:
            metrics, artifacts = self._finish_episode(episode)
        done = episode.done and episode_index + 1 >= self.settings.episodes
        summary = self._summary() if done else {}
        return RoundReport(
            index=index,
            metrics=metrics,
            step=episode_index,
            series=series,
            series_start=offset + start,
            artifacts=artifacts,
            done=done,
            summary=summary,
        )

    def _finish_episode(self, episode: MpcEpisode) -> tuple[dict[str, float], list[Artifact]]:
        from workers import plots

        result = episode.result()
        metrics = {
            "episode_return": result.episode_return,
            "planning_seconds_per_step": float(result.planning_seconds.mean()),
            "simulated_steps_per_second": result.simulated_steps_per_second,
            "physics_steps_per_second": result.physics_steps_per_second,
            "episode_seconds": self.episode_seconds,
            "simulation_worker_restarts": float(self.pool.check_restarts() - self.restarts_at_episode_start),
        }
        if result.success is not None:
            metrics["success"] = float(result.success)
            metrics["goal_steps"] = float(result.goal_steps)
        metrics |= {f"cost/{name}": value for name, value in result.components.items()}
        trajectory = episode.trajectory()
        task_metrics = self.task.episode_metrics(trajectory.observations)
        metrics |= task_metrics
        self.finished.append(
            {
                "episode_return": result.episode_return,
                "success": float(result.success) if result.success is not None else math.nan,
                "planning_seconds": float(result.planning_seconds.mean()),
                **task_metrics,
            }
        )
        name = f"episodes/episode_{self.episode_index:03d}"
        words = "/".join(self.label_text(self.labels(self.trial)))
        title = f"{self.trial.task}/{words}/s{self.trial.seed} episode {self.episode_index}"
        title += f" (return {result.episode_return:.1f})"
        figure = plots.episode_png(title, result.rewards, result.planning_seconds)
        data = io.BytesIO()
        np.savez_compressed(data, **{k: v for k, v in trajectory.to_tree().items() if isinstance(v, np.ndarray)})
        return metrics, [Artifact(f"{name}.png", figure), Artifact(f"{name}.npz", data.getvalue())]

    def _summary(self) -> dict[str, float]:
        summary = {
            "mean_return": float(np.mean([e["episode_return"] for e in self.finished])),
            "mean_planning_seconds_per_step": float(np.mean([e["planning_seconds"] for e in self.finished])),
        }
        successes = [e["success"] for e in self.finished if not math.isnan(e["success"])]
        if successes:
            summary["success_rate"] = float(np.mean(successes))
        # The task's own figures (e.g. box_drops: mean_box_drops is the drop rate).
        for key in sorted(self.finished[0].keys() - {"episode_return", "success", "planning_seconds"}):
            summary[f"mean_{key}"] = float(np.mean([e[key] for e in self.finished]))
        return summary

    # ------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        keys = self.finished[0] if self.finished else ("episode_return", "success", "planning_seconds")
        finished = {key: np.array([e[key] for e in self.finished]) for key in keys}
        state: dict[str, Any] = {"episode_index": self.episode_index, "finished": finished}
        if self.episode is not None and not self.episode.done:
            # Mid-episode: the next round continues this episode where it stopped.
            state["episode"] = self.episode.state_dict()
            state["episode_seconds"] = self.episode_seconds
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        finished = state["finished"]
        self.finished = [
            {key: float(finished[key][i]) for key in finished} for i in range(len(finished["episode_return"]))
        ]
        self.episode_index = int(state["episode_index"])
        self.episode = None
        if "episode" in state:
            self.episode = self._start_episode()
            self.episode.load_state_dict(state["episode"])
            self.episode_seconds = float(state["episode_seconds"])

    def close(self) -> None:
        self.pool.close()
        self.env.close()
