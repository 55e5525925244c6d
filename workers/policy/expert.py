"""iCEM_pi (Alg. 2): iCEM warm-started by the policy, given the policy's own plan, guided towards it.

Every piece is a switch of :class:`ExpertSwitches`, so the ablations of
Fig. 15 and the baselines of Fig. 13 are settings:

* **warm start**: at t = 0 the mean is the policy's closed-loop h-step
  rollout from the current state (in the model: ground truth here);
  afterwards the mean is shift-initialised and its new last action is the
  policy's action at the last predicted state. That state is the end of the
  executed (best) sequence's rollout, as in the authors' iCEM code
  (``compute_new_mean(obs=simulated_paths[best]["observations"][-1])``).
  Without it the mean starts at zero and the shift repeats the last action
  (App. C.2, "w/o warmstarting"): plain iCEM.
* **policy samples**: at the last CEM-iteration the mean and the policy's
  own h-step sequence (that closed-loop rollout, recomputed at every step)
  each replace one random sample, so the budget is unchanged (App. C.2).
* **guidance**: the cost f = J + lambda_1 C_1 (+ lambda_2 C_2) of
  workers/policy/guidance.py, lambda adaptive (eq. 17) or fixed.

sigma is reset to sigma_init at every step (the planner does this).

With adaptive weights the cost that ranks samples changes between
CEM-iterations, so costs of different iterations are not comparable; the
executed action is then the first of the best sequence of the *last*
CEM-iteration (its kept elites included and re-weighed), which is what the
authors' code executes. With a fixed cost the planner's best-ever is
executed; with keep-elites on (iCEM's default) that is the same sequence,
since kept elites carry the best forward.
"""

from __future__ import annotations

import time
from functools import partial
from typing import Literal, NamedTuple

import gymnasium as gym
import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from workers.data import Trajectory, TrajectoryRecorder
from workers.planning import CEMPlanner, PlannerConfig
from workers.planning.icem import CostBatch, PlannerMemory, main_cost
from workers.policy.guidance import ACTION_NORM, GUIDANCE, AuxiliaryTerm, GuidedObjective, LambdaRecord
from workers.policy.network import Policy
from workers.policy.observations import ObservationReader
from workers.rollout import BatchEvaluator
from workers.tasks import GroundTruthTask, SimState
from workers.tasks.base import SimStates


class ExpertSwitches(BaseModel):
    """The switches and weights of the APEX expert (iCEM_pi with the guided cost); a sweep's ``base`` sets them
    through ``ApexSettings``, which adds them to the method's own fields."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    warm_start: bool = True
    """iCEM_pi warm start: the mean from the policy's rollout at t = 0, the shifted mean's last action from the
    policy afterwards (off: plain iCEM initialisation, App. C.2)."""
    policy_samples: bool = True
    """Put the policy's own h-step sequence among the last CEM-iteration's samples (replacing one)."""
    guidance: bool = True
    """Add the guidance cost lambda_1 sum_t ||a_t - pi(s_t)||^2 (eq. 15)."""
    adaptive_lambda: bool = True
    """lambda by eq. 17 at every CEM-iteration; off: the fixed values (iCEM_pi-GPS, APEX lambda-fixed)."""
    c: float = Field(0.025, ge=0)
    """c_1 of eq. 17 for the guidance term (Table 10: 0.025)."""
    fixed_lambda: float = Field(1.0, ge=0)
    """lambda_1 when not adaptive. The thesis tuned it per task (App. C.2) and does not give it: 1.0 is ours,
    untuned, so the fixed-lambda ablation and iCEM_pi-GPS run with a weight the thesis did not use."""
    action_norm: bool = False
    """Add the action-norm cost lambda_2 sum_t ||a_t|| (eq. 16 writes lambda_2 ||a|| of the sequence; we read it
    as the sum of the steps' norms, which weighs every step alike; the two rank sequences differently)."""
    c_action_norm: float = Field(0.025, ge=0)
    """c_2 of eq. 17 for the action-norm term."""
    fixed_lambda_action_norm: float = Field(0.01, ge=0)
    """lambda_2 when not adaptive (not given in the thesis)."""
    epsilon: float = Field(1e-6, gt=0)
    """eps of eq. 17 (not given in the thesis)."""
    relabel_restart: Literal["state", "chunk"] = "state"
    """Where DAgger relabeling starts Alg. 2 afresh (t = 0: the mean from the policy's rollout, no elites kept):
    at every relabeled ``state``, or only at the first state of each chunk of consecutive states (``chunk``:
    later states inherit the previous state's shifted plan and elites)."""

    @property
    def uses_policy(self) -> bool:
        """Whether the expert consults the policy at all (else it is plain iCEM)."""
        return self.warm_start or self.policy_samples or self.guidance

    def switches(self) -> dict[str, object]:
        """The values of the fields declared here (also when called on a subclass with more fields)."""
        return {name: getattr(self, name) for name in ExpertSwitches.model_fields}


class ExpertSettings(ExpertSwitches):
    """What expert and relabeling workers are told: the switches and a resolved planner."""

    planner: PlannerConfig
    """A resolved planner config (budget, horizon, iCEM switches)."""


class StepInfo(NamedTuple):
    """What the expert did at one state."""

    action: np.ndarray
    """(d,) the action (label) in [-1, 1]."""
    plan: np.ndarray
    """(h, d) the sequence whose first action it is."""
    lambdas: np.ndarray
    """(iterations,) lambda_1 at each CEM-iteration (empty without guidance)."""
    best_cost: float
    trajectories: int
    records: list[LambdaRecord] = []
    """The weights and the main cost's range over the preliminary elites at each CEM-iteration."""


class ICemPi:
    """iCEM_pi planning from simulator states of one task.

    Args:
        task / model / evaluator: the task, its planning model and a batch evaluator on it.
        reader: observations of simulated batches (guidance).
        scratch_env: a real environment of the task for the policy's closed-loop rollouts.
        settings: switches and planner.
        seed: the planner's random seed.
    """

    def __init__(
        self,
        task: GroundTruthTask,
        model: mujoco.MjModel,
        evaluator: BatchEvaluator,
        reader: ObservationReader,
        scratch_env: gym.Env,
        settings: ExpertSettings,
        seed: int,
    ):
        self.task, self.model, self.evaluator, self.reader = task, model, evaluator, reader
        self.scratch = scratch_env
        self.settings = settings
        terms = []
        if settings.guidance:
            terms.append(AuxiliaryTerm(GUIDANCE, settings.adaptive_lambda, settings.c, settings.fixed_lambda))
        if settings.action_norm:
            terms.append(
                AuxiliaryTerm(
                    ACTION_NORM, settings.adaptive_lambda, settings.c_action_norm, settings.fixed_lambda_action_norm
                )
            )
        self.objective = GuidedObjective(settings.planner.elites, terms, settings.epsilon) if terms else None
        self.planner = CEMPlanner(settings.planner, task.action_dim, seed, self.objective or main_cost)
        self.horizon = settings.planner.horizon
        self.t = 0
        self._final: dict[bytes, np.ndarray] = {}

    def reset(self, seed: int) -> None:
        """Start a new sequence of states (an episode, a relabeling chunk): the next step is t = 0."""
        self.planner.reset(seed)
        self.t = 0

    # ------------------------------------------------------------ policy
    def policy_rollout(self, state: SimState, observation: np.ndarray, policy: Policy) -> np.ndarray:
        """(h, d) the policy's closed-loop actions from ``state``, rolled out in the (ground-truth) model."""
        raw = self.scratch.unwrapped
        self.task.restore(self.scratch, state)
        actions = np.empty((self.horizon, self.task.action_dim))
        current = np.asarray(observation, dtype=np.float64)
        for t in range(self.horizon):
            actions[t] = policy(current)
            if t + 1 < self.horizon:
                outcome = self.task.step_env(raw, actions[t])
                current = self.task.observe(outcome.observation)
        return actions

    # ------------------------------------------------------------- costs
    def _costs(self, state: SimState, observation: np.ndarray, policy: Policy | None, actions: np.ndarray) -> CostBatch:
        settings = self.settings
        guided = settings.guidance and policy is not None
        batch = self.evaluator.simulate(state, actions, keep_substeps=guided and self.reader.needs_substeps)
        main = self.task.costs(self.model, batch).sum(axis=1)
        components: dict[str, np.ndarray] = {}
        if guided:
            observations = self.reader.read(self.model, state, batch)
            n = len(actions)
            start = np.broadcast_to(np.asarray(observation, dtype=np.float64), (n, 1, observations.shape[-1]))
            inputs = np.concatenate([start, observations[:, :-1]], axis=1)  # s_0 .. s_{h-1}
            components[GUIDANCE] = np.square(actions - policy(inputs)).sum(axis=(1, 2))
            for i in range(n):
                self._final[actions[i].tobytes()] = observations[i, -1]
        if settings.action_norm:
            components[ACTION_NORM] = np.linalg.norm(actions, axis=2).sum(axis=1)
        return CostBatch(main, "mean", components)

    def final_observation(self, state: SimState, plan: np.ndarray) -> np.ndarray:
        """Observation after the last step of ``plan`` simulated from ``state``."""
        cached = self._final.get(np.ascontiguousarray(plan).tobytes())
        if cached is not None:
            return cached
        batch = self.evaluator.simulate(state, plan[None], keep_substeps=self.reader.needs_substeps)
        return self.reader.read(self.model, state, batch)[0, -1]

    # -------------------------------------------------------------- plan
    def act(self, state: SimState, observation: np.ndarray, policy: Policy | None) -> StepInfo:
        """Plan from ``state`` (whose observation is ``observation``); the planner's memory moves one step on."""
        settings = self.settings
        consult = policy is not None
        sequence = None
        # The policy's own sequence is a sample at every step, but seeds the mean only at t = 0.
        if consult and (settings.policy_samples or (settings.warm_start and self.t == 0)):
            sequence = self.policy_rollout(state, observation, policy)
        if self.t == 0 and consult and settings.warm_start:
            self.planner.memory = self.planner.initial_memory(sequence)
        self._final = {}
        first_record = len(self.objective.records) if self.objective else 0
        proposals = sequence[None] if sequence is not None and settings.policy_samples else None
        result = self.planner.plan(partial(self._costs, state, observation, policy), proposals=proposals)
        plan, action = result.plan, result.action
        if self.objective is not None and self.objective.adaptive and settings.planner.best_action:
            plan = self.planner.memory.elites[0].copy()  # best of the last CEM-iteration under its lambda
            action = plan[0].copy()
        if consult and settings.warm_start:
            mean = self.planner.memory.mean.copy()
            mean[-1] = policy(self.final_observation(state, plan))
            self.planner.memory = PlannerMemory(mean, self.planner.memory.elites)
        self.t += 1
        records: list[LambdaRecord] = []
        if self.objective is not None:
            records = self.objective.records[first_record:]
            self.objective.records.clear()  # memory stays flat over long episodes
        lambdas = np.array([r.lambdas[GUIDANCE] for r in records if GUIDANCE in r.lambdas])
        return StepInfo(action, plan, lambdas, result.best_cost, result.trajectories, records)


# ------------------------------------------------------------------ episodes
class ExpertEpisode(NamedTuple):
    """An episode of the expert in the real environment."""

    trajectory: Trajectory
    lambdas: np.ndarray
    """lambda_1 of every CEM-iteration of every step."""
    trajectories: int
    """Action sequences evaluated (the budget spent)."""
    seconds: float
    cpu_seconds: float
    """CPU seconds of the process (all threads) during the episode."""


class PolicyEpisode(NamedTuple):
    """An episode of the policy in the real environment, with the simulator state of every step."""

    trajectory: Trajectory
    seconds: float
    cpu_seconds: float


class RelabeledChunk(NamedTuple):
    """Expert actions for a run of consecutive states."""

    actions: np.ndarray
    """(m, d) the expert's action at each state."""
    lambdas: np.ndarray
    trajectories: int
    seconds: float
    cpu_seconds: float


def _success(task: GroundTruthTask, flags: list[bool | None]) -> bool | None:
    achieved = [f for f in flags if f is not None]
    return task.episode_success(achieved) if task.has_success else None


def run_expert_episode(
    task: GroundTruthTask, env: gym.Env, expert: ICemPi, policy: Policy | None, seed: int, steps: int
) -> ExpertEpisode:
    """An episode of ``expert`` from ``env.reset(seed=seed)`` (planner seeded with ``seed``)."""
    started, cpu = time.perf_counter(), time.process_time()
    observation, _ = env.reset(seed=seed)
    expert.reset(seed)
    current = task.observe(observation)
    recorder = TrajectoryRecorder(current, task.goals(observation))
    lambdas, flags, spent = [], [], 0
    for _ in range(steps):
        info = expert.act(task.capture(env), current, policy)
        outcome = task.step_env(env, info.action)
        current = task.observe(outcome.observation)
        recorder.add(info.action, outcome.reward, current, goals=task.goals(outcome.observation))
        lambdas.append(info.lambdas)
        flags.append(outcome.goal_achieved)
        spent += info.trajectories
    trajectory = recorder.finish(_success(task, flags))
    return ExpertEpisode(
        trajectory,
        np.concatenate(lambdas) if lambdas else np.zeros(0),
        spent,
        time.perf_counter() - started,
        time.process_time() - cpu,
    )


def run_policy_episode(task: GroundTruthTask, env: gym.Env, policy: Policy, seed: int, steps: int) -> PolicyEpisode:
    """An episode of the policy from ``env.reset(seed=seed)``, recording the simulator state before each step."""
    started, cpu = time.perf_counter(), time.process_time()
    observation, _ = env.reset(seed=seed)
    current = task.observe(observation)
    recorder = TrajectoryRecorder(current, task.goals(observation))
    flags = []
    for _ in range(steps):
        state = task.capture(env)
        action = policy(current)
        outcome = task.step_env(env, action)
        current = task.observe(outcome.observation)
        recorder.add(action, outcome.reward, current, state=state, goals=task.goals(outcome.observation))
        flags.append(outcome.goal_achieved)
    return PolicyEpisode(
        recorder.finish(_success(task, flags)), time.perf_counter() - started, time.process_time() - cpu
    )


def relabel_seed(chunk_seed: int, index: int) -> int:
    """Planner seed of the ``index``-th state of a chunk relabeled state by state."""
    return int(np.random.SeedSequence([chunk_seed, index]).generate_state(1)[0])


def relabel_states(
    expert: ICemPi, states: SimStates, observations: np.ndarray, policy: Policy | None, seed: int
) -> RelabeledChunk:
    """The expert's action at each of a run of consecutive states.

    The states were visited by the policy, so the action taken between two of them is the policy's, not the
    expert's. With ``relabel_restart: state`` each state is therefore a query without prior information and is
    planned as t = 0 of Alg. 2 (section 4.3.1: "at time t = 0 where no prior information exists, the mean is
    initialized from rolling out the trajectory with the policy"); with ``chunk`` Alg. 2 runs over the chunk
    as over an episode, t = 0 at its first state only.
    """
    started, cpu = time.perf_counter(), time.process_time()
    each_state = expert.settings.relabel_restart == "state"
    if not each_state:
        expert.reset(seed)
    actions = np.empty((len(states), expert.task.action_dim))
    lambdas, spent = [], 0
    for k in range(len(states)):
        if each_state:
            expert.reset(relabel_seed(seed, k))
        info = expert.act(states[k], observations[k], policy)
        actions[k] = info.action
        lambdas.append(info.lambdas)
        spent += info.trajectories
    return RelabeledChunk(
        actions,
        np.concatenate(lambdas) if lambdas else np.zeros(0),
        spent,
        time.perf_counter() - started,
        time.process_time() - cpu,
    )
