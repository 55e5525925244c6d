"""Chapter 4 as a method: APEX, adaptive policy extraction from the iCEM expert (Alg. 3).

One round is one APEX iteration:

1. **expert**: n episodes of the guided iCEM_pi expert (workers/policy/expert.py) in the real
   environment, in parallel on the ``relabel`` workers, guided by the current policy;
2. their (observation, action) pairs join the dataset (the latest W x n rollouts);
3. **training** on the ``trainer`` worker (1000 gradient steps; the network carries over unless
   ``policy.reinitialize``);
4. **policy**: n episodes of the trained policy, recording the simulator state of every step;
5. **relabeling** (DAgger): every state the policy visited gets the action of the same guided,
   warm-started expert at the same budget, planned from the recorded simulator state (goals,
   mocap targets and randomised model parameters included) on the ``relabel`` workers, in
   chunks of consecutive states; the relabeled episodes join the dataset;
6. **training** again.

The ``relabel`` role is stateless: every call is a pure function of its arguments (a chunk is
seeded by trial seed, iteration and chunk index), so a lost worker is restarted and its call
retried with the same labels. The ``trainer`` is stateful; its state is part of the
checkpoint, so a lost trainer costs the iteration in flight and the trial resumes from the last
completed one. Every switch of the chapter's ablations and baselines (Fig. 13, 15) is a setting.

Choices where the thesis leaves room (see also workers/policy/*):

* The window (Table 11: the latest W x n rollouts, n from Table 10) counts expert rollouts, and
  the relabeled episodes of the same iterations stay with them: the dataset holds the last W
  iterations' data. App. C.2: "in case of DAgger, the policy gets twice the amount of data as in
  the case of behavioral cloning because in each iteration data from the expert and relabeled
  data from the policy is added"; a window counting both kinds alike would hold the same amount
  for both once full. ``window_counts: episodes`` is that other reading.
* Without DAgger the second training still runs, on the expert data alone, so that every
  variant takes the same number of gradient steps per iteration (App. C.2).
* The first iteration's expert is guided by the randomly initialised policy (Alg. 3 line 1;
  with adaptive weights a weak policy is ignored until the main cost varies among elites).
* Relabeling plans every state as t = 0 of Alg. 2 (warm start from the policy's rollout from that
  state, fresh elites): between two relabeled states the policy acted, not the expert, so the
  expert's shifted plan from the previous state is no prior for the next (``relabel_restart:
  chunk``, the reading before, runs Alg. 2 over each chunk of consecutive states as over an
  episode). Per state the labels of the same state spread less over planner seeds and lie
  closer to the policy (docs/results/apex.md).
"""

from __future__ import annotations

import math
import time
from typing import Any, Literal

import numpy as np
from pydantic import Field

from workers.data import EpisodeBuffer, Trajectory
from workers.methods.base import Artifact, MethodSettings, Program, RoleSpec, RoundReport, TrialSpec
from workers.planning import PlannerConfig
from workers.policy.evaluate import CHAPTER_4_EPISODE_STEPS
from workers.policy.expert import ExpertSettings, ExpertSwitches
from workers.policy.network import PolicyWeights
from workers.policy.training import PolicySettings, PolicyTrainer, TrainReport
from workers.policy.worker import RelabelWorker, states_chunk
from workers.tasks import GroundTruthTask, make_task

TABLE_10_ROLLOUTS: dict[str, int] = {
    "halfcheetah_running": 1,
    "humanoid_standup": 1,
    "door": 10,
    "door_sparse": 10,
    "fetch_pick_place_sparse": 25,
}
"""Rollouts per iteration n (Table 10); other tasks default to 1."""
TABLE_11_WINDOW: dict[str, int] = {
    "halfcheetah_running": 50,
    "humanoid_standup": 100,
    "fetch_pick_place_sparse": 150,
    "door": 100,
    "door_sparse": 100,
}
"""W of Table 11: the policy trains on the latest W x n rollouts; other tasks default to 50."""
TABLE_9: dict[tuple[str, int], dict[str, float]] = {
    ("halfcheetah_running", 45): {"expert": 5556, "policy": 4847, "icem": 3488},
    ("halfcheetah_running", 100): {"expert": 7202, "policy": 5596, "icem": 5235.9},
    ("halfcheetah_running", 300): {"expert": 9310, "policy": 6218, "icem": 7632.54},
    ("humanoid_standup", 45): {"expert": 149.0e3, "policy": 73.5e3, "icem": 146.3e3},
    ("humanoid_standup", 100): {"expert": 173.7e3, "policy": 80.5e3, "icem": 182.2e3},
    ("humanoid_standup", 300): {"expert": 207.3e3, "policy": 88.7e3, "icem": 202.4e3},
    ("fetch_pick_place_sparse", 45): {"expert": 0.893, "icem": 0.67},  # the policy's 0.0311 is a misprint
    ("fetch_pick_place_sparse", 100): {"expert": 0.947, "policy": 0.770, "icem": 0.81},
    ("door_sparse", 45): {"expert": 1.0, "policy": 0.99, "icem": 1.0},
}
"""Table 9: APEX expert and policy (returns, success rates for Fetch and Door) and plain iCEM, by budget."""

# CPUs: the phases of an iteration run one after another, so only one kind of actor computes at a
# time. The relabel workers hold the trial's CPUs; the runner only coordinates and reserves none; the
# trainer reserves none either and trains in the first relabel worker's bundle, with that worker's
# threads, while the relabel workers wait. On two cores one relabel worker thus plans with two threads
# (with reservations of their own, the runner and trainer would leave it one).
SUMMARY_ITERATIONS = 5
"""The summary averages the last this many iterations (the issue's 'mean of the last 5 iterations')."""


class ApexSettings(MethodSettings, ExpertSwitches):
    """APEX (thesis chapter 4, Alg. 3): distil the guided iCEM_pi expert into a policy, with DAgger."""

    # The expert's switches and weights (warm_start ... epsilon) are inherited from ExpertSwitches, declared
    # once for the sweep file and for what the expert and relabeling workers are told.

    planner: PlannerConfig = PlannerConfig()
    """The expert's planner (iCEM; budget 45, 100 or 300 in Table 9; horizon 30)."""
    iterations: int = Field(10, ge=1)
    """APEX iterations (rounds) of the trial; the thesis does not give how many it ran."""
    rollouts: int | None = Field(None, ge=1)
    """Rollouts per iteration n: expert episodes and policy episodes each (default: Table 10 for the task)."""
    window: int | None = Field(None, ge=1)
    """W: the policy trains on the latest W x n rollouts (default: Table 11); see ``window_counts``."""
    window_counts: Literal["iterations", "episodes"] = "iterations"
    """What the window's W x n rollouts count: ``iterations``, the expert rollouts, with the relabeled episodes
    of the same iterations kept beside them (DAgger holds twice BC's data, App. C.2); ``episodes``, expert and
    relabeled episodes alike."""
    episode_steps: int | None = Field(None, ge=1)
    """Steps per episode (default: the task's; Humanoid standup 500 as in section 4.4)."""
    policy: PolicySettings = PolicySettings()
    """The policy network and its training (Table 11)."""
    dagger: bool = True
    """Relabel the states the policy visits with the expert and train on them too (Alg. 3 lines 9-12)."""
    relabel_chunk: int = Field(100, ge=1)
    """Consecutive states per relabeling call (the unit of work spread over the relabel workers; see
    ``relabel_restart`` for where Alg. 2 starts afresh)."""
    evaluation_episodes: int = Field(0, ge=0)
    """Extra policy episodes after each iteration's last training, from the same seeds every time (the thesis
    gives no evaluation protocol for Table 9). Timed apart from Table 12's phases (``seconds/evaluation``)."""
    evaluate_every: int = Field(1, ge=1)
    """Evaluate every this many iterations (and after the last). The summary averages the evaluations among the
    last 5 iterations: with 2, three of them; with 5, the last one alone."""

    def expert_settings(self) -> ExpertSettings:
        """What the expert and relabeling workers are told."""
        return ExpertSettings(planner=self.planner, **self.switches())


def derived_seed(trial_seed: int, iteration: int, kind: str, index: int) -> int:
    """Seed of one unit of work: expert or policy episode, relabeling chunk, evaluation episode."""
    code = {"expert": 1, "policy": 2, "relabel": 3, "evaluation": 4}[kind]
    if kind == "evaluation":
        iteration = 0  # the same evaluation episodes at every iteration
    return int(np.random.SeedSequence([trial_seed, iteration, code, index]).generate_state(1)[0] % 2**31)


def lambda_statistics(values: np.ndarray, prefix: str) -> dict[str, float]:
    """Mean, median, max and fraction of zeros of lambda over a phase's CEM-iterations."""
    if len(values) == 0:
        return {}
    return {
        f"{prefix}_mean": float(np.mean(values)),
        f"{prefix}_median": float(np.median(values)),
        f"{prefix}_max": float(np.max(values)),
        f"{prefix}_zero_fraction": float(np.mean(values == 0)),
    }


def _replaced(trajectory: Trajectory, **changes: Any) -> Trajectory:
    # Trajectory defines __len__ (its steps), which breaks NamedTuple._replace.
    return Trajectory(**{**trajectory._asdict(), **changes})


def _without_states(trajectory: Trajectory) -> Trajectory:
    return _replaced(trajectory, sim_states=None)


class ApexProgram(Program):
    """APEX iterations on one task (chapter 4, Table 9, Fig. 13-16)."""

    name = "apex"
    Settings = ApexSettings
    description = "APEX: distil the guided iCEM_pi expert into a policy with DAgger relabeling (chapter 4)"
    metrics = {
        "policy_return": "final_policy_return",
        "expert_return": "final_expert_return",
        "policy_success": "final_policy_success",
        "expert_success": "final_expert_success",
        "evaluation_return": "final_evaluation_return",
        "evaluation_success": "final_evaluation_success",
    }
    """Sweep metric -> summary key: each figure averaged over the last SUMMARY_ITERATIONS iterations."""
    label_paths = {"budget": ("planner.budget",)}
    curves = (
        "expert_return", "policy_return", "evaluation_return", "expert_success", "policy_success", "evaluation_success",
    )  # fmt: skip
    curve_step = "APEX iteration"
    """Per-iteration metrics reports draw against the iteration (Fig. 14; used by the core's reports)."""
    role_names = ("relabel", "trainer")

    settings: ApexSettings

    # ---------------------------------------------------------- declaration
    @classmethod
    def resolve(cls, settings: ApexSettings, task: GroundTruthTask) -> ApexSettings:
        name = task.name
        return settings.model_copy(
            update={
                "planner": settings.planner.resolved(task.colored_noise_beta),
                "rollouts": settings.rollouts or TABLE_10_ROLLOUTS.get(name, 1),
                "window": settings.window or TABLE_11_WINDOW.get(name, 50),
                "episode_steps": settings.episode_steps or CHAPTER_4_EPISODE_STEPS.get(name, task.episode_length),
            }
        )

    @classmethod
    def roles_for(cls, trial: TrialSpec, unit_cpus: int, counts) -> list[RoleSpec]:
        settings = trial.settings
        relabel = {"task_name": trial.task, "task_options": settings.task_options, "threads": unit_cpus}
        # The trainer borrows the first relabel worker's CPUs (see the note on CPUs above).
        trainer = {"seed": trial.seed, "settings": settings.policy, "task": trial.task, "cpus": unit_cpus}
        return [
            RoleSpec("relabel", RelabelWorker, counts.get("relabel", 1), unit_cpus, relabel),
            RoleSpec("trainer", PolicyTrainer, 1, 0, trainer, stateful=True),
        ]

    @classmethod
    def runner_cpus(cls, trial: TrialSpec, unit_cpus: int) -> float:  # type: ignore[override]
        return 0.0  # it coordinates the phases and computes during none of them

    @classmethod
    def labels(cls, trial: TrialSpec) -> dict[str, str]:
        return {"budget": str(trial.settings.planner.budget)}

    @classmethod
    def planned_rounds(cls, trial: TrialSpec) -> int:
        return trial.settings.iterations

    # ------------------------------------------------------------------ run
    def __init__(self, trial: TrialSpec, roles, cpus: int):
        super().__init__(trial, roles, cpus)
        settings = trial.settings
        if settings.rollouts is None or settings.window is None or settings.episode_steps is None:
            raise ValueError("ApexProgram needs resolved settings (ApexProgram.resolve)")
        self.settings = settings
        self.task = make_task(trial.task, settings.task_options)
        env = self.task.make_env()
        try:
            self.obs_dim = len(self.task.reset(env, trial.seed))
        finally:
            env.close()
        self.n = settings.rollouts
        self.steps = settings.episode_steps
        self.buffer = EpisodeBuffer(self.window_capacity(settings))
        self.weights: PolicyWeights | None = None
        self.history: dict[str, list[float]] = {}

    @staticmethod
    def window_capacity(settings: ApexSettings) -> int:
        """Episodes the dataset holds: W x n, doubled for the relabeled episodes when counting iterations."""
        per_iteration = 2 if settings.dagger and settings.window_counts == "iterations" else 1
        return settings.window * settings.rollouts * per_iteration

    def _dataset(self) -> dict[str, np.ndarray]:
        transitions = self.buffer.transitions()
        return {"observations": transitions.observations, "actions": transitions.actions}

    def _train(self, label: str, fraction: float, cpu: list[float]) -> TrainReport:
        """Train on the current window (one ``share`` of the dataset); the trainer's CPU time joins ``cpu``."""
        self.set_progress(fraction, label)
        trainer = self.roles["trainer"]
        report = trainer.submit(0, "train", trainer.share(self._dataset())).result()
        cpu.append(report.cpu_seconds)
        return report

    def run_round(self, index: int) -> RoundReport:
        settings, trial = self.settings, self.trial
        relabel, trainer = self.roles["relabel"], self.roles["trainer"]
        expert_settings = settings.expert_settings()
        label = f"it {index + 1}/{settings.iterations}"
        started = time.perf_counter()
        cpu: list[float] = []
        metrics: dict[str, float] = {}
        if self.weights is None:
            self.weights = trainer.submit(0, "initialize", self.obs_dim, self.task.action_dim).result()

        # 1-2. Expert episodes, guided by the current policy.
        self.set_progress(0.0, f"{label} expert")
        phase = time.perf_counter()
        shared = relabel.share(self.weights if expert_settings.uses_policy else None)
        calls = [
            (derived_seed(trial.seed, index, "expert", k), self.steps, shared, expert_settings) for k in range(self.n)
        ]
        experts = relabel.map("expert_episode", calls)
        metrics["seconds/expert"] = time.perf_counter() - phase
        cpu += [e.cpu_seconds for e in experts]
        self.buffer.add([_without_states(e.trajectory) for e in experts])
        metrics |= self._episode_metrics("expert", [e.trajectory for e in experts])
        metrics |= lambda_statistics(np.concatenate([e.lambdas for e in experts]), "lambda/expert")
        metrics["expert_trajectories_per_step"] = float(np.mean([e.trajectories / self.steps for e in experts]))
        metrics["weights_version/expert"] = float(self.weights.version)

        # 3. Training on the expert data.
        phase = time.perf_counter()
        first = self._train(f"{label} training", 0.35, cpu)
        seconds_training = time.perf_counter() - phase
        metrics |= {"loss/first_training": first.loss, "loss/first_training_first_batch": first.first_loss}

        # 4. Policy episodes, recording the simulator states.
        self.set_progress(0.45, f"{label} policy")
        phase = time.perf_counter()
        shared = relabel.share(first.weights)
        calls = [(derived_seed(trial.seed, index, "policy", k), self.steps, shared) for k in range(self.n)]
        rollouts = relabel.map("policy_episode", calls)
        metrics["seconds/policy"] = time.perf_counter() - phase
        cpu += [r.cpu_seconds for r in rollouts]
        metrics |= self._episode_metrics("policy", [r.trajectory for r in rollouts])
        metrics["weights_version/policy"] = float(first.weights.version)

        # 5. DAgger: relabel every visited state with the same expert.
        phase = time.perf_counter()
        if settings.dagger:
            relabeled, lambdas, chunk_cpu = self._relabel(index, rollouts, shared, expert_settings, label)
            cpu += chunk_cpu
            self.buffer.add(relabeled)
            metrics |= lambda_statistics(lambdas, "lambda/relabel")
            metrics["dataset/relabeled_steps"] = float(sum(len(t) for t in relabeled))
            metrics["weights_version/relabel"] = float(first.weights.version)
        metrics["seconds/relabel"] = time.perf_counter() - phase

        # 6. Training on expert and relabeled data.
        phase = time.perf_counter()
        second = self._train(f"{label} training", 0.9, cpu)
        seconds_training += time.perf_counter() - phase
        metrics |= {"loss/second_training": second.loss, "loss/second_training_first_batch": second.first_loss}
        self.weights = second.weights
        metrics["weights_version"] = float(second.weights.version)
        metrics["dataset/steps"] = float(second.samples)
        metrics["dataset/rollouts"] = float(len(self.buffer))

        metrics["seconds/training"] = seconds_training
        metrics["seconds/dagger"] = metrics["seconds/policy"] + metrics["seconds/relabel"]
        # Table 12's Total: expert, DAgger and training; an evaluation is the product's own and timed apart.
        metrics["seconds/iteration"] = time.perf_counter() - started
        metrics["core_minutes"] = float(sum(cpu)) / 60.0

        # Optional evaluation of the final policy of the iteration.
        last = index + 1 >= settings.iterations
        if settings.evaluation_episodes and ((index + 1) % settings.evaluate_every == 0 or last):
            self.set_progress(0.95, f"{label} evaluation")
            phase = time.perf_counter()
            shared = relabel.share(self.weights)
            calls = [
                (derived_seed(trial.seed, index, "evaluation", k), self.steps, shared)
                for k in range(settings.evaluation_episodes)
            ]
            evaluations = relabel.map("policy_episode", calls)
            metrics |= self._episode_metrics("evaluation", [e.trajectory for e in evaluations])
            metrics["seconds/evaluation"] = time.perf_counter() - phase
            metrics["core_minutes/evaluation"] = float(sum(e.cpu_seconds for e in evaluations)) / 60.0
        for key in (
            "expert_return", "expert_success", "policy_return", "policy_success", "evaluation_return",
            "evaluation_success",
        ):  # fmt: skip
            self.history.setdefault(key, [])
            self.history[key].append(metrics.get(key, math.nan))
        artifacts = [
            Artifact(f"policy/policy_{index:04d}.npz", self.weights.to_bytes()),
            Artifact("apex_curves.png", self._curves_png()),
        ]
        done = last
        return RoundReport(
            index, metrics, step=index, artifacts=artifacts, done=done, summary=self._summary() if done else {}
        )

    def _relabel(self, index: int, rollouts, shared, expert_settings: ExpertSettings, label: str):
        chunk = self.settings.relabel_chunk
        calls, spans = [], []
        for episode, rollout in enumerate(rollouts):
            trajectory = rollout.trajectory
            states = trajectory.sim_states
            for start in range(0, len(trajectory), chunk):
                stop = min(start + chunk, len(trajectory))
                tree = states_chunk(states, start, stop)
                seed = derived_seed(self.trial.seed, index, "relabel", len(calls))
                calls.append((tree, trajectory.observations[start:stop], shared, seed, expert_settings))
                spans.append((episode, start, stop))
        self.set_progress(0.5, f"{label} relabel ({len(calls)} chunks)")
        chunks = self.roles["relabel"].map("relabel", calls)
        relabeled = []
        for episode, rollout in enumerate(rollouts):
            parts = [c.actions for c, (e, _, _) in zip(chunks, spans) if e == episode]
            trajectory = _without_states(rollout.trajectory)
            relabeled.append(_replaced(trajectory, actions=np.concatenate(parts)))
        lambdas = np.concatenate([c.lambdas for c in chunks]) if chunks else np.zeros(0)
        return relabeled, lambdas, [c.cpu_seconds for c in chunks]

    def _episode_metrics(self, prefix: str, trajectories: list[Trajectory]) -> dict[str, float]:
        metrics = {f"{prefix}_return": float(np.mean([t.episode_return for t in trajectories]))}
        if self.task.has_success:
            metrics[f"{prefix}_success"] = float(np.mean([bool(t.success) for t in trajectories]))
        return metrics

    def _summary(self) -> dict[str, float]:
        # A success figure is logged with the episodes behind it, so that reports count it as a rate of episodes
        # (a Wilson interval and a binomial test) rather than a mean over seeds.
        episodes_per_iteration = {"expert": self.n, "policy": self.n, "evaluation": self.settings.evaluation_episodes}
        summary = {}
        for key, values in self.history.items():
            tail = np.array(values[-SUMMARY_ITERATIONS:], dtype=float)
            tail = tail[np.isfinite(tail)]
            if len(tail):
                summary[f"final_{key}"] = float(tail.mean())
                if key.endswith("_success"):
                    kind = key.removesuffix("_success")
                    # Evaluations start from the same seeds every time (derived_seed): averaged over several
                    # iterations they are still that many distinct episodes, not that many times each.
                    times = 1 if kind == "evaluation" else len(tail)
                    summary[f"final_{key}_episodes"] = float(times * episodes_per_iteration[kind])
        summary["final_weights_version"] = float(self.weights.version if self.weights else 0)
        return summary

    def _curves_png(self) -> bytes:
        """Fig. 14 style: expert (dashed) and policy (solid) per iteration so far."""
        from workers import plots

        figure, axis = plots.plt.subplots(figsize=(6, 3.6))
        metric = "success" if self.task.has_success else "return"
        iterations = np.arange(len(self.history.get(f"expert_{metric}", [])))
        for key, style, name in ((f"expert_{metric}", "--", "expert"), (f"policy_{metric}", "-", "policy")):
            axis.plot(iterations, self.history.get(key, []), style, marker="o", markersize=3, label=name)
        if any(np.isfinite(self.history.get(f"evaluation_{metric}", [math.nan]))):
            axis.plot(
                iterations, self.history[f"evaluation_{metric}"], ":", marker="s", markersize=3, label="evaluation"
            )
        published = TABLE_9.get((self.trial.task, self.settings.planner.budget or 0), {})
        for key, style in (("expert", "--"), ("policy", "-")):
            if key in published:
                axis.axhline(published[key], linestyle=style, color="gray", alpha=0.5, linewidth=1)
        axis.set_xlabel("APEX iteration")
        axis.set_ylabel(metric)
        axis.set_title(
            f"{self.trial.task} budget {self.settings.planner.budget} seed {self.trial.seed} (gray: Table 9)"
        )
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
        figure.tight_layout()
        return plots.to_png(figure)

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        trainer_state = self.roles["trainer"].submit(0, "state_dict").result()
        history = {key: np.array(values, dtype=float) for key, values in self.history.items()}
        state: dict[str, Any] = {"buffer": self.buffer.to_tree(), "trainer": trainer_state, "history": history}
        if self.weights is not None:
            state["weights"] = self.weights.to_tree()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.buffer = EpisodeBuffer.from_tree(state["buffer"])
        self.history = {key: [float(v) for v in np.atleast_1d(values)] for key, values in state["history"].items()}
        self.weights = PolicyWeights.from_tree(state["weights"]) if "weights" in state else None
        self.roles["trainer"].submit(0, "load_state_dict", state["trainer"]).result()
