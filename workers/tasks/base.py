"""Common machinery of the ground-truth MuJoCo tasks (thesis section 3.3.1).

A task couples two things:

* the *real environment* (a gymnasium / gymnasium-robotics env) that executes
  the chosen action at every MPC step, and
* a *planning model*: the environment's own MuJoCo model plus a few frame
  sensors. mujoco.rollout records sensor values after every physics step, and a
  frame sensor reads exactly the array the environment's reward reads
  (``data.site_xpos``, ``data.xpos``, ``data.xquat``). Those arrays are computed
  in the forward pass *before* integration, so after ``mj_step`` they describe
  the state one substep earlier; the environments' rewards read them in that
  stale form, and so do the sensors. This is what lets a vectorised reward over
  a whole batch reproduce the real environment's per-step reward.

Everything the planner needs to restart the simulation where the real
environment is lives in a :class:`SimState`: the full physics state, the
solver warm start, mocap targets, the stale frame values, per-episode model
parameters that resets randomise (Adroit), and the goal (Fetch).
"""

from __future__ import annotations

import contextlib
import io
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, NamedTuple

import gymnasium as gym
import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict

from workers.tasks.mujoco_compat import route_warnings_to_logging

FULL_PHYSICS = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
route_warnings_to_logging()  # every process that builds a task: no MUJOCO_LOG.TXT in the user's directory


class Frame(NamedTuple):
    """A frame quantity a task's reward reads from derived simulator data."""

    kind: Literal["pos", "quat"]
    """``pos``: world position (3 values); ``quat``: world orientation (4 values)."""
    objtype: Literal["site", "xbody"]
    """``site``: a site frame; ``xbody``: a body's regular frame (``data.xpos``)."""
    name: str
    """Name of the site or body in the MuJoCo model."""

    @property
    def size(self) -> int:
        return 3 if self.kind == "pos" else 4


@dataclass
class SimState:
    """An exact snapshot of a real environment, sufficient to plan from it."""

    physics: np.ndarray
    """mjSTATE_FULLPHYSICS vector: time, qpos, qvel, act, history, plugin state."""
    warmstart: np.ndarray
    """qacc_warmstart of the constraint solver (results differ in the last bits without it)."""
    mocap_pos: np.ndarray
    """(nmocap, 3) mocap positions; not part of the physics state."""
    mocap_quat: np.ndarray
    """(nmocap, 4) mocap orientations."""
    frames: np.ndarray
    """Current values of the task's frames, as the environment's next step reads them."""
    model_params: dict[str, np.ndarray] = field(default_factory=dict)
    """Model fields the environment randomises per episode (e.g. Adroit body_pos)."""
    goal: np.ndarray | None = None
    """Goal kept by the environment in Python (Fetch), else None."""

    def to_tree(self) -> dict[str, Any]:
        """The state as checkpoint leaves (see workers.checkpoint)."""
        return _state_tree(self)

    @classmethod
    def from_tree(cls, tree: dict[str, Any]) -> SimState:
        return _state_from_tree(cls, tree)


@dataclass
class SimStates:
    """The simulator states of one episode, stacked: what relabeling needs to plan from any visited state.

    Per-step fields are (T, ...) arrays; ``model_params`` and ``goal`` are
    fixed within an episode and stored once.
    """

    physics: np.ndarray
    warmstart: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    frames: np.ndarray
    model_params: dict[str, np.ndarray] = field(default_factory=dict)
    goal: np.ndarray | None = None

    @classmethod
    def stack(cls, states: list[SimState]) -> SimStates:
        if not states:
            raise ValueError("no states to stack")
        fields = {name: np.stack([getattr(s, name) for s in states]) for name in PER_STEP_FIELDS}
        return cls(**fields, model_params=dict(states[0].model_params), goal=states[0].goal)

    def __len__(self) -> int:
        return len(self.physics)

    def __getitem__(self, index: int) -> SimState:
        return SimState(
            **{name: getattr(self, name)[index] for name in PER_STEP_FIELDS},
            model_params=self.model_params,
            goal=self.goal,
        )

    def to_tree(self) -> dict[str, Any]:
        return _state_tree(self)

    @classmethod
    def from_tree(cls, tree: dict[str, Any]) -> SimStates:
        return _state_from_tree(cls, tree)


PER_STEP_FIELDS = ("physics", "warmstart", "mocap_pos", "mocap_quat", "frames")
"""The fields of a simulator state that change every step (the others are fixed within an episode)."""


def _state_tree(state: SimState | SimStates) -> dict[str, Any]:
    tree: dict[str, Any] = {name: getattr(state, name) for name in PER_STEP_FIELDS}
    tree["model_params"] = dict(state.model_params)
    if state.goal is not None:
        tree["goal"] = state.goal
    return tree


def _state_from_tree(cls, tree: dict[str, Any]):
    return cls(
        **{name: np.asarray(tree[name]) for name in PER_STEP_FIELDS},
        model_params={k: np.asarray(v) for k, v in (tree.get("model_params") or {}).items()},
        goal=None if tree.get("goal") is None else np.asarray(tree["goal"]),
    )


class RolloutBatch(NamedTuple):
    """A batch of simulated action sequences, as the batch evaluator hands it to a reward.

    N sequences, horizon h, d action dimensions; "after step t" means after the
    last physics substep of environment step t.
    """

    start: np.ndarray
    """(nstate,) physics state the sequences start from."""
    states: np.ndarray
    """(N, h, nstate) physics state after every environment step."""
    frames: np.ndarray
    """(N, h, nframes) task frames after every environment step, stale as the env reads them."""
    actions: np.ndarray
    """(N, h, d) normalised actions in [-1, 1]."""
    goal: np.ndarray | None
    """The task goal (Fetch), else None."""
    before_last_substep: np.ndarray | None
    """(N, h, nstate) state before the last physics substep of every step, when requested."""


class StepOutcome(NamedTuple):
    """One step of the real environment, seen through the task's definitions."""

    reward: float
    """The task's reward for this step (the figure summed into the reported return)."""
    goal_achieved: bool | None
    """Whether the task's goal condition holds after this step (None: task has none)."""
    observation: Any
    """The environment's observation after the step."""


def register_robotics_envs() -> None:
    """Register gymnasium-robotics' environment ids.

    Importing gymnasium_robotics 1.4.2 prints a notice that its Adroit *reward
    functions* changed in 1.2.1; the Adroit tasks compute DAPG's rewards
    themselves (see workers/tasks/adroit.py), so the notice is not shown.
    """
    from workers.tasks.mujoco_compat import patch_joint_helpers

    with contextlib.redirect_stderr(io.StringIO()):
        import gymnasium_robotics
    patch_joint_helpers()  # before any environment is built (MuJoCo >= 3.12; see the module)
    gym.register_envs(gymnasium_robotics)


def copy_model_parameters(dst: mujoco.MjModel, src: mujoco.MjModel) -> None:
    """Copy every numeric model array that both models share, except sensors.

    The planning model is compiled from the environment's XML with different
    sensors; anything the environment changed after loading (Fetch's weld
    data, Adroit's actuator gains) is carried over here.
    """
    for name in dir(src):
        if name.startswith(("_", "sensor", "name", "names", "paths", "text", "tuple")):
            continue
        value = getattr(src, name)
        if not isinstance(value, np.ndarray):
            continue
        target = getattr(dst, name, None)
        if isinstance(target, np.ndarray) and target.shape == value.shape and target.flags.writeable:
            np.copyto(target, value)


class TaskOptions(BaseModel):
    """Switches of a task's planning cost; a sweep sets them under ``task_options``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)


class GroundTruthTask(ABC):
    """A thesis task with MuJoCo ground-truth dynamics (chapter 3).

    Args:
        **options: values for the task's :attr:`Options` (validated; unknown keys are errors).
    """

    Options: ClassVar[type[TaskOptions]] = TaskOptions
    """The task's options model."""

    name: ClassVar[str]
    """Registry name used in sweeps, e.g. ``halfcheetah_running``."""
    env_id: ClassVar[str]
    """gymnasium id of the real environment."""
    env_kwargs: ClassVar[dict[str, Any]] = {}
    """Extra keyword arguments for ``gym.make``."""
    episode_length: ClassVar[int]
    """Environment steps per episode (thesis Table 7)."""
    frame_skip: ClassVar[int]
    """Physics steps per environment step (the environment's frame_skip / n_substeps)."""
    action_dim: ClassVar[int]
    """Dimensions d of the action space."""
    colored_noise_beta: ClassVar[float]
    """Colored-noise exponent beta of iCEM for this task (thesis Table 6)."""
    frames: ClassVar[tuple[Frame, ...]] = ()
    """Derived frame quantities the reward or the controls read."""
    per_episode_model_fields: ClassVar[tuple[str, ...]] = ()
    """MjModel fields the environment's reset randomises."""
    feedback_control: ClassVar[bool] = False
    """True when the controls of a step depend on the simulated state (Fetch mocap)."""
    has_success: ClassVar[bool] = False
    """Whether the task defines a success criterion."""
    description: ClassVar[str] = ""
    """One line for ``icemlab tasks`` and error messages."""
    batch_observations: ClassVar[bool] = False
    """Whether :meth:`observations` computes the observations of simulated batches in numpy (else callers
    replay each step's last physics substep in a real environment: workers/policy/observations.py)."""
    observation_dim: ClassVar[int | None] = None
    """Length of :meth:`observe`'s vector where it is known without an environment (settings validate
    observation dimensions against it), else None."""
    noise_dim: ClassVar[int] = 0
    """Standard-normal draws per environment step that the task's noise process takes (:meth:`noisy_actions`);
    0: the dynamics are deterministic."""
    uncertainty_dims: ClassVar[tuple[int, ...] | None] = None
    """Observation dimensions whose spread over noisy particles is the aleatoric uncertainty by default
    (workers/dynamics/ground_truth.py); None: all."""

    def __init__(self, **options: Any):
        self.options = self.Options(**options)

    # ----------------------------------------------------------------- envs
    def make_env(self) -> gym.Env:
        """The real environment, with the task's episode length as time limit."""
        register_robotics_envs()
        return gym.make(self.env_id, max_episode_steps=self.episode_length, **self.env_kwargs)

    def build_planning_model(self, env: gym.Env) -> mujoco.MjModel:
        """The environment's model with the task's frame sensors (and no others)."""
        raw = env.unwrapped
        spec = mujoco.MjSpec.from_file(raw.fullpath)
        for sensor in list(spec.sensors):
            spec.delete(sensor)
        for frame in self.frames:
            spec.add_sensor(
                type=mujoco.mjtSensor.mjSENS_FRAMEPOS if frame.kind == "pos" else mujoco.mjtSensor.mjSENS_FRAMEQUAT,
                objtype=mujoco.mjtObj.mjOBJ_SITE if frame.objtype == "site" else mujoco.mjtObj.mjOBJ_XBODY,
                objname=frame.name,
            )
        model = spec.compile()
        copy_model_parameters(model, raw.model)
        return model

    # ------------------------------------------------------------ states
    def capture(self, env: gym.Env) -> SimState:
        """Snapshot the real environment (see :class:`SimState`)."""
        raw = env.unwrapped
        model, data = raw.model, raw.data
        physics = np.empty(mujoco.mj_stateSize(model, FULL_PHYSICS))
        mujoco.mj_getState(model, data, physics, FULL_PHYSICS)
        return SimState(
            physics=physics,
            warmstart=data.qacc_warmstart.copy(),
            mocap_pos=data.mocap_pos.copy(),
            mocap_quat=data.mocap_quat.copy(),
            frames=self.read_frames(model, data),
            model_params={f: getattr(model, f).copy() for f in self.per_episode_model_fields},
            goal=self._goal(env),
        )

    def restore(self, env: gym.Env, state: SimState) -> None:
        """Put the real environment back into a captured state.

        Derived quantities are recomputed by ``mj_forward``; the frames the next
        step reads are then overwritten with their captured (stale) values so the
        next step is the same as it was from the original state.
        """
        raw = env.unwrapped
        model, data = raw.model, raw.data
        for name, value in state.model_params.items():
            np.copyto(getattr(model, name), value)
        mujoco.mj_resetData(model, data)
        mujoco.mj_setState(model, data, state.physics, FULL_PHYSICS)
        data.mocap_pos[:] = state.mocap_pos
        data.mocap_quat[:] = state.mocap_quat
        mujoco.mj_forward(model, data)
        data.qacc_warmstart[:] = state.warmstart
        self._write_frames(model, data, state.frames)
        if state.goal is not None:
            raw.goal = state.goal.copy()

    def load_into(self, model: mujoco.MjModel, state: SimState) -> None:
        """Copy the state's per-episode model parameters into a planning model."""
        for name, value in state.model_params.items():
            np.copyto(getattr(model, name), value)

    def _goal(self, env: gym.Env) -> np.ndarray | None:
        return None

    def _frame_arrays(self, model: mujoco.MjModel, data: mujoco.MjData):
        for frame in self.frames:
            if frame.objtype == "site":
                index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, frame.name)
                if frame.kind != "pos":
                    raise ValueError("site frames support positions only")
                yield data.site_xpos[index]
            else:
                index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, frame.name)
                yield data.xpos[index] if frame.kind == "pos" else data.xquat[index]

    def read_frames(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """Current frame values of an MjData, laid out like the planning sensors."""
        arrays = list(self._frame_arrays(model, data))
        return np.concatenate(arrays) if arrays else np.zeros(0)

    def _write_frames(self, model: mujoco.MjModel, data: mujoco.MjData, values: np.ndarray) -> None:
        offset = 0
        for frame, array in zip(self.frames, self._frame_arrays(model, data)):
            array[:] = values[offset : offset + frame.size]
            offset += frame.size

    def frame_slice(self, name: str, kind: str = "pos") -> slice:
        """Columns of a frame in the sensordata / ``frames`` arrays."""
        offset = 0
        for frame in self.frames:
            if frame.name == name and frame.kind == kind:
                return slice(offset, offset + frame.size)
            offset += frame.size
        raise KeyError(f"task {self.name} has no {kind} frame {name!r}")

    # -------------------------------------------------------- observations
    def reset(self, env: gym.Env, seed: int) -> np.ndarray:
        """Reset the real environment with ``seed``; return the observation vector (:meth:`observe`)."""
        observation, _info = env.reset(seed=seed)
        return self.observe(observation)

    def observe(self, observation: Any) -> np.ndarray:
        """The environment's observation as one flat vector: what a policy or a learned model sees.

        Goal-conditioned environments (dict observations) give the observation
        followed by the desired goal, the policy input of APEX on Fetch (Table 11).
        """
        if isinstance(observation, dict):
            return np.concatenate([np.ravel(observation["observation"]), np.ravel(observation["desired_goal"])])
        return np.asarray(observation, dtype=np.float64).ravel()

    def observations(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        """(N, h, obs_dim) the observation vector (:meth:`observe`) after every step of a simulated batch,
        equal to what the real environment reports after the same steps (tasks with :attr:`batch_observations`).

        Environments read some derived quantities (site positions, Jacobians) as the forward pass left them
        before the last substep's integration; the task's frames record exactly those values.
        """
        raise NotImplementedError(f"{self.name} has no vectorised observations; replay them in an environment")

    def goals(self, observation: Any) -> tuple[np.ndarray, np.ndarray] | None:
        """(achieved goal, desired goal) of a goal-conditioned observation, else None (for HER)."""
        if isinstance(observation, dict):
            return np.asarray(observation["achieved_goal"]).copy(), np.asarray(observation["desired_goal"]).copy()
        return None

    # ---------------------------------------------------------- controls
    def env_action(self, action: np.ndarray) -> np.ndarray:
        """Map a normalised action in [-1, 1] to the environment's action space."""
        return np.asarray(action, dtype=np.float64)

    @abstractmethod
    def controls(self, model: mujoco.MjModel, state: SimState, actions: np.ndarray) -> np.ndarray:
        """Open-loop control vectors for a batch of normalised action sequences.

        ``actions`` is (N, h, d); returns (N, h, ncontrol) laid out per
        :meth:`control_spec`, one vector per environment step (held over its
        physics substeps). Feedback tasks override :meth:`feedback_controls`.
        """

    def feedback_controls(
        self,
        model: mujoco.MjModel,
        state: SimState,
        actions_t: np.ndarray,
        physics: np.ndarray,
        frames: np.ndarray,
    ) -> np.ndarray:
        """Controls of one environment step from the simulated state (feedback tasks).

        ``actions_t`` (N, d); ``physics`` (N, nstate) state at the start of the
        step; ``frames`` (N, nframes) stale frames at the start of the step.
        """
        raise NotImplementedError(f"{self.name} has open-loop controls")

    def control_spec(self, model: mujoco.MjModel) -> int:
        """mjtState bits of the control vectors (ctrl, plus mocap when the model has any)."""
        spec = int(mujoco.mjtState.mjSTATE_CTRL)
        if model.nmocap:
            spec |= int(mujoco.mjtState.mjSTATE_MOCAP_POS) | int(mujoco.mjtState.mjSTATE_MOCAP_QUAT)
        return spec

    def _with_mocap(self, state: SimState, ctrl: np.ndarray) -> np.ndarray:
        """Append the (constant) mocap targets of the state to control vectors."""
        if state.mocap_pos.size == 0:
            return ctrl
        mocap = np.concatenate([state.mocap_pos.ravel(), state.mocap_quat.ravel()])
        return np.concatenate([ctrl, np.broadcast_to(mocap, ctrl.shape[:-1] + mocap.shape)], axis=-1)

    # ----------------------------------------------------------- rewards
    @abstractmethod
    def rewards(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        """(N, h) per-step rewards of the batch, equal to the real environment's."""

    def costs(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        """(N, h) per-step planning costs: the negative reward unless a task shapes it."""
        return -self.rewards(model, batch)

    def episode_success(self, goal_achieved: list[bool]) -> bool | None:
        """Success of a whole episode from its per-step goal flags."""
        return None

    def episode_metrics(self, observations: np.ndarray) -> dict[str, float]:
        """The task's own figures of a finished episode from its (T + 1, obs) observations (e.g. box drops)."""
        return {}

    # ------------------------------------------------------------ noise
    def noisy_actions(self, actions_t: np.ndarray, frames: np.ndarray, draws_t: np.ndarray) -> np.ndarray:
        """The actions a step applies under the task's noise process (tasks with :attr:`noise_dim` > 0).

        ``actions_t`` (N, d) chosen actions; ``frames`` (N, nframes) stale frames at the start of the step;
        ``draws_t`` (N, noise_dim) standard-normal draws. The real environment and the planner's simulators
        call this same function, each with draws of its own.
        """
        raise NotImplementedError(f"{self.name} has deterministic dynamics")

    # -------------------------------------------------------- real steps
    def step_env(self, env: gym.Env, action: np.ndarray) -> StepOutcome:
        """Execute a normalised action in the real environment."""
        observation, reward, _terminated, _truncated, _info = env.step(self.env_action(action))
        return StepOutcome(float(reward), None, observation)

    @property
    def needs_substeps(self) -> bool:
        """Whether rewards need the state before the last physics substep."""
        return False

    # ----------------------------------------------------------- helpers
    @staticmethod
    def qpos(model: mujoco.MjModel, physics: np.ndarray) -> np.ndarray:
        """qpos columns of FULLPHYSICS state arrays (time comes first)."""
        return physics[..., 1 : 1 + model.nq]

    @staticmethod
    def qvel(model: mujoco.MjModel, physics: np.ndarray) -> np.ndarray:
        """qvel columns of FULLPHYSICS state arrays."""
        return physics[..., 1 + model.nq : 1 + model.nq + model.nv]
