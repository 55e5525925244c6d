"""BridgeMaze (thesis section 5.4, App. D.4, Fig. 17b): three bridges over lava, wind on the middle one.

The thesis specifies: a cube on a free joint; a 10-d state (position,
orientation quaternion, linear velocity); a 2-d force along x and y; the goal
platform at x >= 12; lava below z = -1.5; reward eq. 36; a random side wind
(force along y through ``xfrc_applied``, sign and amplitude U(0, f_max)
redrawn every 5 steps) only where -8 <= x <= 8 and -3.6 <= y <= 3.6; a safe
but long upper bridge with walls, a shorter lower bridge without walls, and the
short, windy middle bridge; state coverage on a 50 x 50 grid over
-20 <= x <= 20, -10 <= y <= 15 (App. D.4.1).

Chosen here, because the thesis gives none of it:

* Geometry (workers/tasks/assets/bridge_maze.xml): start platform x in
  [-16, -8], goal platform x in [8, 16], both y in [-7, 11], surface z = 0;
  bridges over x in [-8, 8]: middle y in [-1, 1], lower y in [-6.25, -4.75],
  upper y in [8, 10] between walls. The cube (0.5 m, 1 kg) starts at (-12, 0).
  Rims line every platform edge except where a bridge joins it, so the cube
  reaches the lava only from a bridge (the XML says why). That is the ``wide``
  layout (the default); the ``compact`` one (bridge_maze_compact.xml, option
  ``layout``) moves the side bridges next to the wind region, lower y in
  [-5.5, -4], upper y in [4, 6], platforms y in [-7, 7.5], so that each side
  bridge's entrance is about 6 m from the start, within one plan's reach (Table
  15's 30 steps cover at most 10 m); in the wide layout the upper bridge's
  entrance is 9 m to the side, and a plan sees no progress in heading there.
* Falling: the cube loses the walkway once its centre of mass is over lava
  (the walkway is one plane whose contact is switched off; see the XML for
  why) and drops to the lava plane at z = -2. A fall is z < -1.5 (eq. 36).
* Dynamics: forces of up to 20 N, damping 3 on the free joint, no friction
  between cube and walkway (the XML says why): top speed about 6.7 m/s, a
  stop within about a second without force; env step 0.05 s (25 physics
  steps of 2 ms).
* Wind: redrawn every ``wind_period`` = 5 *environment* steps (0.25 s; at 2 ms
  physics steps, 5 physics steps would be a 10 ms flicker that averages out);
  the region test runs at every physics step. Default f_max = 30 N, which makes
  a straight run over the middle bridge fail often but not always with a
  simple controller (tests/test_bridge_maze.py); it is a constructor option.
* Episode: 200 steps (10 s); at full speed the upper route takes about 110 steps, the middle one 75.
  A fall terminates the episode (gymnasium ``terminated``); with
  ``terminate_on_fall=False`` the episode runs on with reward -1 per step as
  eq. 36 describes.
* Success: the goal line x >= 12 was crossed and the cube never fell.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium.envs.mujoco import MujocoEnv
from gymnasium.spaces import Box
from pydantic import Field

from workers.tasks.base import TaskOptions
from workers.tasks.model_based import ModelBasedTask

if TYPE_CHECKING:
    import torch

ENV_ID = "icemlab/BridgeMaze-v0"
MODEL_PATH = Path(__file__).parent / "assets" / "bridge_maze.xml"
COMPACT_MODEL_PATH = Path(__file__).parent / "assets" / "bridge_maze_compact.xml"

GOAL_X = 12.0
"""s_0* of eq. 36: the goal line."""
LAVA_Z = -1.5
"""Below this height the cube has fallen into the lava (eq. 36)."""
WIND_REGION = ((-8.0, 8.0), (-3.6, 3.6))
"""(x range, y range) where the wind blows (App. D.4)."""
WALKWAY = (
    ((-16.0, -8.0), (-7.0, 11.0)),  # start platform
    ((8.0, 16.0), (-7.0, 11.0)),  # goal platform
    ((-8.0, 8.0), (-1.0, 1.0)),  # middle bridge
    ((-8.0, 8.0), (-6.25, -4.75)),  # lower bridge (no walls)
    ((-8.0, 8.0), (8.0, 10.0)),  # upper bridge (walls)
)
"""Rectangles (x range, y range) of solid ground of the wide layout, as drawn in bridge_maze.xml."""
COMPACT_WALKWAY = (
    ((-16.0, -8.0), (-7.0, 7.5)),  # start platform
    ((8.0, 16.0), (-7.0, 7.5)),  # goal platform
    ((-8.0, 8.0), (-1.0, 1.0)),  # middle bridge
    ((-8.0, 8.0), (-5.5, -4.0)),  # lower bridge (no walls)
    ((-8.0, 8.0), (4.0, 6.0)),  # upper bridge (walls)
)
"""Rectangles of solid ground of the compact layout, as drawn in bridge_maze_compact.xml."""


class Layout(NamedTuple):
    """Where the bridges are: the MuJoCo model and its solid ground (the wind region is the thesis's in both)."""

    xml: Path
    walkway: tuple[tuple[tuple[float, float], tuple[float, float]], ...]


LAYOUTS = {"wide": Layout(MODEL_PATH, WALKWAY), "compact": Layout(COMPACT_MODEL_PATH, COMPACT_WALKWAY)}
"""``wide``: the side bridges far out (the upper one's entrance 9 m to the side of the start); ``compact``: both
side bridges' entrances within one plan's reach of the start (see the XML files)."""
LayoutName = Literal["wide", "compact"]
COVERAGE_RANGE = ((-20.0, 20.0), (-10.0, 15.0))
"""(x range, y range) of the coverage grid (App. D.4.1)."""
COVERAGE_BINS = 50
"""Bins per axis of the coverage grid (App. D.4.1)."""
QUATERNION = slice(3, 7)
"""The orientation quaternion (w, x, y, z) in the 10-d state."""
CUBE_HALF_SIZE = 0.25
"""Half the cube's edge: its centre's height resting on the walkway (z = 0)."""
PROBE_SPEED = 3.3
"""Speed along x of the states that stand for the plane's points in maps of the model: half the top speed."""


@cache
def wall_footprints(xml: Path = MODEL_PATH) -> tuple[tuple[tuple[float, float], tuple[float, float]], ...]:
    """((x0, x1), (y0, y1)) of every wall and rim of the XML (boxes the cube collides with), for maps."""
    model = mujoco.MjModel.from_xml_path(str(xml))
    walls = []
    for geom in range(model.ngeom):
        static = model.geom_bodyid[geom] == 0  # not the cube
        if static and model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_BOX and model.geom_contype[geom] & 1:
            (x, y, _), (dx, dy, _) = model.geom_pos[geom], model.geom_size[geom]
            walls.append(((float(x - dx), float(x + dx)), (float(y - dy), float(y + dy))))
    return tuple(walls)


def on_walkway(x: np.ndarray | float, y: np.ndarray | float, walkway=WALKWAY) -> np.ndarray:
    """Whether points (x, y) lie over solid ground (not lava) of ``walkway`` (a layout's rectangles)."""
    x, y = np.asarray(x), np.asarray(y)
    inside = np.zeros(np.broadcast(x, y).shape, dtype=bool)
    for (x0, x1), (y0, y1) in walkway:
        inside |= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return inside


def in_wind_region(x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
    """Whether points (x, y) lie where the wind blows (App. D.4)."""
    (x0, x1), (y0, y1) = WIND_REGION
    return (np.asarray(x) >= x0) & (np.asarray(x) <= x1) & (np.asarray(y) >= y0) & (np.asarray(y) <= y1)


def bridge_maze_reward(x: np.ndarray, next_x: np.ndarray, next_z: np.ndarray) -> np.ndarray:
    """Eq. 36: progress towards x = 12, 0 beyond it, -1 after a fall (the fall case takes precedence)."""
    progress = np.abs(x - GOAL_X) - np.abs(next_x - GOAL_X)
    return np.where(next_z < LAVA_Z, -1.0, np.where(next_x >= GOAL_X, 0.0, progress))


def coverage_grid(xy: np.ndarray) -> np.ndarray:
    """(50, 50) boolean grid of the cells visited by (n, 2) positions (App. D.4.1); OR grids to accumulate."""
    (x0, x1), (y0, y1) = COVERAGE_RANGE
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    keep = (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
    ix = np.minimum(((xy[keep, 0] - x0) / (x1 - x0) * COVERAGE_BINS).astype(int), COVERAGE_BINS - 1)
    iy = np.minimum(((xy[keep, 1] - y0) / (y1 - y0) * COVERAGE_BINS).astype(int), COVERAGE_BINS - 1)
    grid = np.zeros((COVERAGE_BINS, COVERAGE_BINS), dtype=bool)
    grid[ix, iy] = True
    return grid


def state_coverage(grid: np.ndarray) -> float:
    """Fraction of grid cells visited at least once (App. D.4.1)."""
    return float(np.mean(grid))


class BridgeMazeEnv(MujocoEnv):
    """The BridgeMaze environment; actions are forces in [-1, 1] x 20 N, observations 10-d.

    Args:
        wind_max: f_max, the largest wind force in newtons (amplitude ~ U(0, f_max)).
        wind_period: environment steps between wind redraws.
        terminate_on_fall: end the episode when the cube falls (else -1 per step until the time limit).
        layout: where the bridges are (:data:`LAYOUTS`).
    """

    metadata = {"render_modes": ["human", "rgb_array", "depth_array"], "render_fps": 20}

    def __init__(
        self,
        wind_max: float = 30.0,
        wind_period: int = 5,
        terminate_on_fall: bool = True,
        layout: LayoutName = "wide",
        **kwargs,
    ):
        observation_space = Box(-np.inf, np.inf, shape=(10,), dtype=np.float64)
        self.walkway = LAYOUTS[layout].walkway
        super().__init__(str(LAYOUTS[layout].xml), frame_skip=25, observation_space=observation_space, **kwargs)
        if wind_max < 0 or wind_period < 1:
            raise ValueError("wind_max must be >= 0 and wind_period >= 1")
        self.wind_max, self.wind_period, self.terminate_on_fall = wind_max, wind_period, terminate_on_fall
        self._cube = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "cube")
        self._cube_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "cube")
        self._walkway_bits = int(self.model.geom_contype[self._cube_geom])
        self.wind = 0.0
        self.steps = 0
        self.fell = False
        self.reached_goal = False

    def _get_obs(self) -> np.ndarray:
        # Position (3), orientation quaternion (4), linear velocity (3): the 10-d state of D.4.
        return np.concatenate([self.data.qpos[:7], self.data.qvel[:3]]).copy()

    def _set_walkway_contact(self, on: bool) -> None:
        bits = self._walkway_bits if on else self._walkway_bits & ~1  # bit 1: walkway and walls; bit 2: lava
        self.model.geom_contype[self._cube_geom] = bits
        self.model.geom_conaffinity[self._cube_geom] = bits

    def step(self, action):
        if self.steps % self.wind_period == 0:
            self.wind = float(self.np_random.choice([-1.0, 1.0]) * self.np_random.uniform(0.0, self.wind_max))
        x_before = float(self.data.qpos[0])
        wind_applied = 0.0
        for _ in range(self.frame_skip):
            x, y, z = self.data.qpos[:3]
            if not self.fell and (not on_walkway(x, y, self.walkway) or z < -0.1):
                # Over lava (or already below the surface): the walkway no longer carries the cube.
                self.fell = True
                self._set_walkway_contact(False)
            force = self.wind if in_wind_region(x, y) and z > -0.1 else 0.0
            self.data.xfrc_applied[self._cube, 1] = force
            wind_applied = max(wind_applied, abs(force))
            self.do_simulation(action, 1)
        self.data.xfrc_applied[self._cube] = 0.0
        self.steps += 1
        obs = self._get_obs()
        reward = float(bridge_maze_reward(np.array(x_before), obs[0], obs[2]))
        fallen = bool(obs[2] < LAVA_Z)
        if obs[0] >= GOAL_X and not fallen and not self.fell:
            self.reached_goal = True
        info = {
            "fell": fallen,
            "reached_goal": self.reached_goal,
            "wind": self.wind,
            "wind_applied": wind_applied,
            "x_before": x_before,
        }
        return obs, reward, bool(fallen and self.terminate_on_fall), False, info

    def reset_model(self) -> np.ndarray:
        self._set_walkway_contact(True)
        self.fell = False
        self.reached_goal = False
        self.steps = 0
        self.wind = 0.0
        self.data.xfrc_applied[:] = 0.0
        self.set_state(self.init_qpos.copy(), np.zeros(self.model.nv))
        return self._get_obs()


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=BridgeMazeEnv, max_episode_steps=200)


class BridgeMazeOptions(TaskOptions):
    """Options of BridgeMaze (the thesis gives none of these values; see workers/tasks/bridge_maze.py)."""

    wind_max: float = Field(30.0, ge=0)
    """f_max: the largest side-wind force on the middle bridge, in newtons (amplitude ~ U(0, f_max))."""
    wind_period: int = Field(5, ge=1)
    """Environment steps between wind redraws (App. D.4: every 5 steps)."""
    episode_length: int = Field(200, ge=1)
    """Environment steps per episode."""
    terminate_on_fall: bool = True
    """End the episode when the cube falls into the lava (else -1 per step until the time limit, eq. 36)."""
    layout: LayoutName = "wide"
    """Where the bridges are: ``wide`` (the upper bridge's entrance 9 m to the side of the start, beyond a plan's
    reach) or ``compact`` (both side bridges' entrances about 6 m from the start); see workers/tasks/assets/."""
    unit_quaternion: bool = True
    """Rescale the orientation quaternion of every state the model predicts during planning to unit length (w >= 0).
    The cube rarely tips, so w stays within about 0.001 of 1 in the data while the smallest noise the model may
    predict (Table 13's log-variance floor -10: std 0.0067) is several times that: sampled particles leave the
    data within a step or two and the rollouts diverge (docs/results/razer.md). False: the raw predictions."""


class BridgeMaze(ModelBasedTask):
    """BridgeMaze as a chapter-5 task (see the module docstring for every choice).

    Options (:class:`BridgeMazeOptions`): wind_max, wind_period, episode_length, terminate_on_fall, layout.
    """

    Options = BridgeMazeOptions
    name = "bridge_maze"
    observation_dim = 10
    action_dim = 2
    ensemble_preset = "bridge_maze"
    colored_noise_beta = 2.0  # Table 15
    has_success = True
    coverage_range = COVERAGE_RANGE
    plane_probe = f"one step moving along +x at {PROBE_SPEED} m/s, pushed on at full force"
    description = "cube over three bridges above lava, wind on the middle one (RAZER, App. D.4)"

    @property
    def map_rectangles(self) -> tuple:
        return LAYOUTS[self.options.layout].walkway

    @property
    def map_walls(self) -> tuple:  # read from the XML when a map is drawn, not at import
        return wall_footprints(LAYOUTS[self.options.layout].xml)

    def __init__(self, **options: Any):
        super().__init__(**options)
        self.wind_max, self.wind_period = self.options.wind_max, self.options.wind_period
        self.episode_length = self.options.episode_length
        self.terminate_on_fall = self.options.terminate_on_fall

    def project_states(self, states: torch.Tensor) -> torch.Tensor:
        """The quaternion (dims 3-6) rescaled to unit length with w >= 0 (``unit_quaternion``), the rest unchanged."""
        import torch

        if not self.options.unit_quaternion:
            return states
        quaternion = states[..., QUATERNION]
        sign = torch.where(quaternion[..., :1] < 0, -1.0, 1.0)
        unit = sign * quaternion / quaternion.norm(dim=-1, keepdim=True).clamp(min=1e-6)
        return torch.cat([states[..., : QUATERNION.start], unit, states[..., QUATERNION.stop :]], dim=-1)

    def make_env(self) -> gym.Env:
        return gym.make(
            ENV_ID,
            max_episode_steps=self.episode_length,
            wind_max=self.wind_max,
            wind_period=self.wind_period,
            terminate_on_fall=self.terminate_on_fall,
            layout=self.options.layout,
        )

    def planning_cost(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """c = -r of eq. 36 (App. D.4)."""
        import torch

        x, next_x, next_z = obs[:, 0], next_obs[:, 0], next_obs[:, 2]
        progress = (x - GOAL_X).abs() - (next_x - GOAL_X).abs()
        reward = torch.where(next_z < LAVA_Z, -1.0, torch.where(next_x >= GOAL_X, 0.0, progress))
        return -reward

    def episode_metrics(
        self, observations: np.ndarray, rewards: np.ndarray, infos: list[dict[str, Any]]
    ) -> dict[str, float]:
        """return, success (goal crossed, never fell), failure and falls (fell), max_x, steps, coverage."""
        observations = np.asarray(observations)
        fell = bool(np.any(observations[:, 2] < LAVA_Z))
        reached = bool(np.any((observations[:, 0] >= GOAL_X) & (observations[:, 2] >= LAVA_Z)))
        return {
            "return": float(np.sum(rewards)),
            "success": float(reached and not fell),
            "failure": float(fell),
            "falls": float(fell),
            "max_x": float(observations[:, 0].max()),
            "steps": float(len(rewards)),
            "coverage": state_coverage(coverage_grid(observations[:, :2])),
            "windy_steps": float(sum(info.get("wind_applied", 0.0) > 0 for info in infos)),
        }

    def coverage_grid(self, observations: np.ndarray) -> np.ndarray:
        """The 50 x 50 grid of App. D.4.1 over the visited (x, y)."""
        return coverage_grid(np.asarray(observations)[:, :2])

    def visited_xy(self, observations: np.ndarray) -> np.ndarray:
        """The cube's (x, y): the plane of Fig. 37b/c."""
        return np.asarray(observations)[:, :2]

    def plane_states(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cube upright on the walkway's height at each (x, y), moving towards the goal at half its top speed
        and pushed on at full force: a state a plan passes through on its way over a bridge."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        states = np.zeros((len(xy), self.observation_dim))
        states[:, :2] = xy
        states[:, 2] = CUBE_HALF_SIZE
        states[:, 3] = 1.0  # identity quaternion (w, x, y, z)
        states[:, 7] = PROBE_SPEED
        actions = np.zeros((len(xy), self.action_dim))
        actions[:, 0] = 1.0
        return states, actions
