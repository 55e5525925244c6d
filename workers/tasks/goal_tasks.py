"""Goal-reaching tasks of thesis chapter 6 (section 6.6, Fig. 21, App. E.2).

Each :class:`GoalTask` builds a real gymnasium / gymnasium-robotics
environment and says how to read it as a goal-conditioned problem: the
observation vector s, the achieved goal ag(s) (a function of s), the desired
goal g, the sparse success test, and the episode length (App. E.3.1: 50 steps,
100 for Point Maze). :data:`GOAL_TASKS` lists them; they are also in the
service's task registry (workers/tasks/__init__.py), so sweeps name and
validate them like every other task (``icemlab tasks``), and the methods that
need a ground-truth planning model refuse them.

* **Point Maze** (:class:`PointMaze`): gymnasium-robotics' PointMaze on a
  four-room map of our own (:data:`FOUR_ROOMS`): starts in the lower-left
  room, goals in the upper-right room, as in Fig. 20 and Fig. 27; the doors
  sit away from the diagonal, so a ball pushed straight at the goal sticks in
  a corner of the start room (the Euclidean distance has a local optimum; a
  greedy controller reached the goal room in 3 of 20 episodes, against 17 of
  20 on :data:`OPEN_FOUR_ROOMS`, the first map). The env's frame skip is 1 and its speed
  is clipped at 5 (in gymnasium-robotics), so one env step moves the ball at most 0.05;
  an action repeat (default 3) makes the far room reachable in 100 steps.
* **Fetch Reach** (:class:`FetchReach`) and **Fetch Reach with a wall**
  (:class:`FetchReachWall`): a wall across the middle of the table, the
  gripper starts on one half and the goal lies on the table on the other half
  (section 6.6).
* **Fetch Pick&Place** (:class:`FetchPickAndPlace`) with the goal augmented by
  the end-effector position (App. E.2: the gripper's target equals the box's),
  and **with a wall** (:class:`FetchPickAndPlaceWall`): box on one half, goal
  on the other, 50 % of goals in the air, a wall slightly taller than the box
  so the box has to be lifted.

The wall models are generated from gymnasium-robotics' own Fetch XML with
``mujoco.MjSpec`` (mesh and texture directories made absolute) and written to
the system temp directory, as gymnasium-robotics does for its mazes.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar, Literal

import gymnasium as gym
import mujoco
import numpy as np
from pydantic import Field

from workers.tasks.base import TaskOptions, register_robotics_envs
from workers.tasks.maze_distance import MazeDistance


class GoalTaskOptions(TaskOptions):
    """Switches of a goal task; a sweep sets them under ``task_options``."""


class GoalTask(ABC):
    """A goal-conditioned task: env, observation / goal layout, sparse success.

    Args:
        **options: values for the task's :attr:`Options` (validated; unknown keys are errors).
    """

    Options: ClassVar[type[GoalTaskOptions]] = GoalTaskOptions
    name: ClassVar[str]
    """Key used by :data:`GOAL_TASKS` and the thesis-table lookups (workers.distance.config)."""
    description: ClassVar[str] = ""
    episode_length: ClassVar[int] = 50
    """Steps per episode (App. E.3.1)."""
    obs_dim: ClassVar[int]
    goal_dim: ClassVar[int]
    action_dim: ClassVar[int]
    distance_threshold: ClassVar[float] = 0.05
    """Success radius around the goal (per 3-D part for augmented goals)."""

    def __init__(self, **options: Any):
        self.options = self.Options(**options)

    @abstractmethod
    def make_env(self) -> gym.Env:
        """A fresh real environment (dict observations)."""

    # ----------------------------------------------------------- reading
    def split(self, observation: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, ag(s), g) from a goal-env observation dict."""
        obs = np.asarray(observation["observation"], dtype=np.float64)
        return obs, self.achieved_goal(obs), np.asarray(observation["desired_goal"], dtype=np.float64)

    @abstractmethod
    def achieved_goal(self, observations: np.ndarray) -> np.ndarray:
        """ag(s) for observations (..., obs_dim) -> (..., goal_dim)."""

    def goal_distance(self, achieved: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Euclidean distance between achieved and desired goals (..., )."""
        return np.linalg.norm(np.asarray(achieved) - np.asarray(goals), axis=-1)

    def is_success(self, achieved: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Sparse success (..., ) bool."""
        return self.goal_distance(achieved, goals) <= self.distance_threshold

    def sparse_reward(self, achieved: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """0 on success, -1 otherwise (the Sparse+HER reward, section 6.3.1)."""
        return np.where(self.is_success(achieved, goals), 0.0, -1.0)

    def env_action(self, action: np.ndarray) -> np.ndarray:
        """The environment's action for a normalised action in [-1, 1]."""
        return np.asarray(action, dtype=np.float64)

    def evaluation_metrics(self, final_achieved: np.ndarray, goals: np.ndarray) -> dict[str, float]:
        """Extra per-task evaluation figures from final achieved goals (E, goal_dim) and goals."""
        return {}


# ------------------------------------------------------------------ Point Maze
R, G = "r", "g"
FOUR_ROOMS: list[list[Any]] = [
    [1, 1, 1, 1, 1, 1, 1],
    [1, 0, 0, 0, G, G, 1],
    [1, 0, 0, 1, G, G, 1],
    [1, 0, 1, 1, 1, 0, 1],
    [1, R, R, 1, 0, 0, 1],
    [1, R, R, 0, 0, 0, 1],
    [1, 1, 1, 1, 1, 1, 1],
]
"""Four 2 x 2 rooms joined by one-cell doors away from the diagonal; starts ("r") lower left, goals ("g") upper right.

Fig. 20 and 27 show no map; section 6.6 asks for walls that give the
Euclidean distance to the goal local optima. The doors sit on the rooms'
outer sides (left and top of the path through the upper-left room, bottom and
right of the path through the lower-right room), so a ball pushed straight at
the goal from the start room ends in the corner where the start room touches
the central wall block, 3 units from the goal room in a straight line and 6
along the shortest path. In world units (scale 1) the rooms' centres are 3
apart; either shortest path from the start room to the goal room is about 6.
"""

OPEN_FOUR_ROOMS: list[list[Any]] = [
    [1, 1, 1, 1, 1, 1, 1],
    [1, 0, 0, 1, G, G, 1],
    [1, 0, 0, 0, G, G, 1],
    [1, 1, 0, 1, 1, 0, 1],
    [1, R, R, 1, 0, 0, 1],
    [1, R, R, 0, 0, 0, 1],
    [1, 1, 1, 1, 1, 1, 1],
]
"""The first map of this module: the doors next to the central wall block let a ball pushed straight at the goal
slide along the walls into the goal room (a greedy controller got there from the start room in 8 of 8 episodes),
so the Euclidean distance has no local optimum worth the name; kept as ``maze: open_four_rooms``."""

MAZES: dict[str, list[list[Any]]] = {"four_rooms": FOUR_ROOMS, "open_four_rooms": OPEN_FOUR_ROOMS}


class ActionRepeat(gym.Wrapper):
    """Repeat each action ``repeat`` times; the observation and info are the last ones."""

    def __init__(self, env: gym.Env, repeat: int):
        super().__init__(env)
        self.repeat = repeat

    def step(self, action):
        total = 0.0
        for _ in range(self.repeat):
            observation, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            if terminated or truncated:
                break
        return observation, total, terminated, truncated, info


class PointMazeOptions(GoalTaskOptions):
    maze: Literal["four_rooms", "open_four_rooms"] = "four_rooms"
    """The map: four_rooms (doors away from the diagonal: a ball pushed straight at the goal gets stuck) or
    open_four_rooms (doors next to the central block: it slides into the goal room)."""
    action_repeat: int = Field(3, ge=1)
    """Env steps per agent step; PointMaze's ball covers at most 0.05 per env step (speed clip 5, frame skip 1)."""
    resolution: float = Field(0.05, gt=0)
    """Raster cell of the ground-truth shortest-path distance, world units."""


class PointMaze(GoalTask):
    """2-D point mass in a four-room maze (section 6.6 "2D navigation", 100 steps, success radius 0.45)."""

    Options = PointMazeOptions
    options: PointMazeOptions
    name = "point_maze"
    description = "ball in a four-room maze, start lower left, goals upper right (100 steps)"
    episode_length = 100
    obs_dim, goal_dim, action_dim = 4, 2, 2
    distance_threshold = 0.45
    ball_radius = 0.1
    """Radius of PointMaze's ball geom (the clearance of the ground-truth distance)."""

    def __init__(self, **options: Any):
        super().__init__(**options)
        self.maze_map = MAZES[self.options.maze]
        self.maze_distance = MazeDistance(self.maze_map, 1.0, self.options.resolution, self.ball_radius)

    def make_env(self) -> gym.Env:
        register_robotics_envs()
        # continuing_task with reset_target off: the goal stays put and the episode never terminates early,
        # so every episode has exactly episode_length steps (HER and the temporal loss index within it).
        env = gym.make(
            "PointMaze_UMaze-v3",
            maze_map=self.maze_map,
            continuing_task=True,
            reset_target=False,
            max_episode_steps=self.episode_length * self.options.action_repeat,
        )
        # gymnasium-robotics writes the maze's MJCF to a uniquely named file in the temp directory and never
        # removes it; the model is loaded by now, so without this every env (one per worker and trial) leaves one.
        Path(env.unwrapped.tmp_xml_file_path).unlink(missing_ok=True)
        return ActionRepeat(env, self.options.action_repeat) if self.options.action_repeat > 1 else env

    def achieved_goal(self, observations: np.ndarray) -> np.ndarray:
        return np.asarray(observations)[..., :2]

    def evaluation_metrics(self, final_achieved, goals):
        shortest = self.maze_distance.distance(final_achieved, goals)
        return {"maze_distance": float(np.mean(shortest))}


# ----------------------------------------------------------------------- Fetch
TABLE_TOP = 0.4
"""z of the Fetch table's surface (table body at z 0.2, half height 0.2)."""
WALL_Y = 0.75
"""The walls run along x through the middle of the table (its centre is at y 0.75)."""


def fetch_xml_with_wall(base: str, name: str, center: tuple[float, ...], half_size: tuple[float, ...]) -> str:
    """Path of a Fetch model (gymnasium-robotics' ``fetch/<base>``) with a static box wall added.

    The XML is generated with MjSpec from the installed assets; mesh and
    texture directories become absolute so the file loads from the temp
    directory. The file name carries a hash of its content, so concurrent
    processes write identical files.
    """
    register_robotics_envs()
    import gymnasium_robotics

    folder = Path(gymnasium_robotics.__file__).parent / "envs" / "assets" / "fetch"
    spec = mujoco.MjSpec.from_file(str(folder / base))
    spec.meshdir = os.path.normpath(folder / spec.meshdir)
    spec.texturedir = os.path.normpath(folder / spec.texturedir)
    body = spec.worldbody.add_body(name=name, pos=list(center))
    body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half_size), rgba=[0.55, 0.35, 0.25, 1.0])
    xml = spec.to_xml()
    digest = hashlib.sha256(xml.encode()).hexdigest()[:12]
    path = Path(tempfile.gettempdir()) / f"icemlab_{Path(base).stem}_{name}_{digest}.xml"
    if not path.exists():
        partial = path.with_suffix(f".{os.getpid()}.tmp")
        partial.write_text(xml)
        partial.replace(path)
    return str(path)


def _fetch_env_classes():
    """The wall environments, defined lazily so importing this module does not import gymnasium_robotics."""
    register_robotics_envs()
    from gymnasium_robotics.envs.fetch import MujocoFetchEnv

    reach_qpos = {"robot0:slide0": 0.4049, "robot0:slide1": 0.48, "robot0:slide2": 0.0}
    pick_qpos = reach_qpos | {"robot0:slide0": 0.405, "object0:joint": [1.25, 0.53, 0.4, 1.0, 0.0, 0.0, 0.0]}

    class FetchReachWallEnv(MujocoFetchEnv):
        """FetchReach-v4 with a wall across the table; start on the near half, goals on the table beyond it."""

        wall_center = (1.3, WALL_Y, TABLE_TOP + 0.1)
        wall_half_size = (0.3, 0.01, 0.1)
        start = np.array([1.34, 0.60, 0.50])
        goal_low = np.array([1.19, 0.85, TABLE_TOP + 0.025])
        goal_high = np.array([1.49, 1.00, TABLE_TOP + 0.025])

        def __init__(self, reward_type: str = "sparse", **kwargs):
            path = fetch_xml_with_wall("reach.xml", "wall0", self.wall_center, self.wall_half_size)
            MujocoFetchEnv.__init__(
                self,
                model_path=path,
                has_object=False,
                block_gripper=True,
                n_substeps=20,
                gripper_extra_height=0.2,
                target_in_the_air=True,
                target_offset=0.0,
                obj_range=0.15,
                target_range=0.15,
                distance_threshold=0.05,
                initial_qpos=reach_qpos,
                reward_type=reward_type,
                **kwargs,
            )

        def _env_setup(self, initial_qpos):
            super()._env_setup(initial_qpos)
            # Drive the gripper to the start on the near half, with the wall's contacts off (the default start
            # is inside it); the env's resets return to the joint configuration reached here.
            wall = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "wall0")
            contype, conaffinity = self.model.geom_contype[wall], self.model.geom_conaffinity[wall]
            self.model.geom_contype[wall] = self.model.geom_conaffinity[wall] = 0
            for _ in range(100):
                self._utils.reset_mocap2body_xpos(self.model, self.data)
                error = self.start - self._utils.get_site_xpos(self.model, self.data, "robot0:grip")
                self.data.mocap_pos[0] += np.clip(error, -0.02, 0.02)
                mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
            self.model.geom_contype[wall], self.model.geom_conaffinity[wall] = contype, conaffinity
            self.data.qvel[:] = 0.0
            mujoco.mj_forward(self.model, self.data)
            self.initial_gripper_xpos = self._utils.get_site_xpos(self.model, self.data, "robot0:grip").copy()

        def _sample_goal(self):
            return self.np_random.uniform(self.goal_low, self.goal_high)

    class FetchPickAndPlaceWallEnv(MujocoFetchEnv):
        """FetchPickAndPlace-v4 with a wall across the table, box on the near half, goal on the far half."""

        wall_center = (1.3, WALL_Y, TABLE_TOP + 0.03)
        wall_half_size = (0.3, 0.01, 0.03)
        object_low, object_high = np.array([1.19, 0.55]), np.array([1.49, 0.69])
        goal_low, goal_high = np.array([1.19, 0.81]), np.array([1.49, 0.95])

        def __init__(self, reward_type: str = "sparse", **kwargs):
            path = fetch_xml_with_wall("pick_and_place.xml", "wall0", self.wall_center, self.wall_half_size)
            MujocoFetchEnv.__init__(
                self,
                model_path=path,
                has_object=True,
                block_gripper=False,
                n_substeps=20,
                gripper_extra_height=0.2,
                target_in_the_air=True,
                target_offset=0.0,
                obj_range=0.15,
                target_range=0.15,
                distance_threshold=0.05,
                initial_qpos=pick_qpos,
                reward_type=reward_type,
                **kwargs,
            )

        def _reset_sim(self):
            super()._reset_sim()
            object_qpos = self._utils.get_joint_qpos(self.model, self.data, "object0:joint").copy()
            object_qpos[:2] = self.np_random.uniform(self.object_low, self.object_high)
            self._utils.set_joint_qpos(self.model, self.data, "object0:joint", object_qpos)
            mujoco.mj_forward(self.model, self.data)
            return True

        def _sample_goal(self):
            goal = np.empty(3)
            goal[:2] = self.np_random.uniform(self.goal_low, self.goal_high)
            goal[2] = self.height_offset
            if self.np_random.uniform() < 0.5:  # half of the goals in the air, as in FetchPickAndPlace
                goal[2] += self.np_random.uniform(0, 0.45)
            return goal

    return FetchReachWallEnv, FetchPickAndPlaceWallEnv


REACH_WALL_ID = "icemlab/FetchReachWall-v0"
PICK_WALL_ID = "icemlab/FetchPickAndPlaceWall-v0"


def _make_reach_wall(**kwargs) -> gym.Env:
    return _fetch_env_classes()[0](**kwargs)


def _make_pick_wall(**kwargs) -> gym.Env:
    return _fetch_env_classes()[1](**kwargs)


for _id, _entry in ((REACH_WALL_ID, _make_reach_wall), (PICK_WALL_ID, _make_pick_wall)):
    if _id not in gym.registry:
        gym.register(_id, entry_point=_entry, max_episode_steps=50)


class FetchTask(GoalTask):
    """A Fetch task (50 steps, 4-D actions, success radius 0.05)."""

    env_id: ClassVar[str]
    action_dim = 4

    def make_env(self) -> gym.Env:
        register_robotics_envs()
        return gym.make(self.env_id, max_episode_steps=self.episode_length)


class FetchReach(FetchTask):
    """FetchReach-v4: move the gripper to a goal in the air; ag = gripper position (obs[0:3])."""

    name = "fetch_reach"
    description = "Fetch gripper to a point (50 steps)"
    env_id = "FetchReach-v4"
    obs_dim, goal_dim = 10, 3

    def achieved_goal(self, observations):
        return np.asarray(observations)[..., 0:3]


class FetchReachWall(FetchReach):
    """Fetch Reach with a wall (section 6.6): the gripper must go over a wall to a goal on the table."""

    name = "fetch_reach_wall"
    description = "Fetch gripper over a wall to a point on the table (50 steps)"
    env_id = REACH_WALL_ID


class FetchPickAndPlaceOptions(GoalTaskOptions):
    augment_goal: bool = True
    """Goal = (box target, gripper target = box target), ag = (box, gripper) (App. E.2); False: box only."""
    success_distance: Literal["parts", "joint"] = "parts"
    """The augmented goal's distance, which success (<= 0.05), the sparse reward and the reported goal distances
    use; the thesis gives no rule. "parts": the larger of the box's and the gripper's distances, so each must be
    within 0.05 ("the goal is to have both box and gripper at the target state", section 6.6.1). "joint": the
    distance of the whole 6-D goal vector, as a HER reward over the augmented goal would take it (stricter:
    sqrt(d_box^2 + d_gripper^2) <= 0.05)."""


class FetchPickAndPlace(FetchTask):
    """FetchPickAndPlace-v4; by default with the end-effector goal augmentation of App. E.2.

    With augmentation, success needs both the box and the gripper within 0.05
    of the target ("the goal is to have both box and gripper at the target
    state", section 6.6.1; option ``success_distance`` takes the 6-D distance
    instead); the env's own success (box only) is reported separately by the
    loop.
    """

    Options = FetchPickAndPlaceOptions
    options: FetchPickAndPlaceOptions
    name = "fetch_pick_place"
    description = "Fetch puts a box on a target, goal augmented with the gripper (50 steps)"
    env_id = "FetchPickAndPlace-v4"
    obs_dim = 25

    @property
    def goal_dim(self) -> int:  # type: ignore[override]
        return 6 if self.options.augment_goal else 3

    def achieved_goal(self, observations):
        observations = np.asarray(observations)
        box = observations[..., 3:6]
        if not self.options.augment_goal or self.options.success_distance == "joint":
            return box
        return np.concatenate([box, observations[..., 0:3]], axis=-1)

    def split(self, observation):
        obs, achieved, goal = super().split(observation)
        if self.options.augment_goal:
            goal = np.concatenate([goal, goal], axis=-1)
        return obs, achieved, goal

    def goal_distance(self, achieved, goals):
        if not self.options.augment_goal or self.options.success_distance == "joint":
            return super().goal_distance(achieved, goals)
        # Per 3-D part; the larger of the box's and the gripper's distances decides success.
        achieved, goals = np.broadcast_arrays(np.asarray(achieved), np.asarray(goals))
        parts = achieved.shape[-1] // 3
        shape = achieved.shape[:-1] + (parts, 3)
        return np.linalg.norm(achieved.reshape(shape) - goals.reshape(shape), axis=-1).max(axis=-1)


class FetchPickAndPlaceWall(FetchPickAndPlace):
    """Fetch Pick&Place with a wall (section 6.6): the box has to be lifted over the wall."""

    name = "fetch_pick_place_wall"
    description = "Fetch lifts a box over a wall to a target, goal augmented (50 steps)"
    env_id = PICK_WALL_ID


GOAL_TASKS: dict[str, type[GoalTask]] = {
    task.name: task for task in (PointMaze, FetchReach, FetchReachWall, FetchPickAndPlace, FetchPickAndPlaceWall)
}


def make_goal_task(name: str, options: dict[str, Any] | None = None) -> GoalTask:
    """The goal task called ``name`` with its options."""
    try:
        task_class = GOAL_TASKS[name]
    except KeyError:
        raise ValueError(f"unknown goal task {name!r}; known: {', '.join(GOAL_TASKS)}") from None
    return task_class(**(options or {}))
