"""Goal tasks of chapter 6 (section 6.6, App. E.2): layouts, walls, rooms, reachability."""

from __future__ import annotations

import tempfile
from pathlib import Path

import mujoco
import numpy as np
import pytest

from workers.tasks.goal_tasks import FOUR_ROOMS, GOAL_TASKS, WALL_Y, make_goal_task


@pytest.fixture(scope="module")
def envs():
    cache = {}

    def get(name: str, **options):
        key = (name, tuple(sorted(options.items())))
        if key not in cache:
            task = make_goal_task(name, options)
            cache[key] = (task, task.make_env())
        return cache[key]

    yield get
    for _, env in cache.values():
        env.close()


@pytest.mark.parametrize("name", list(GOAL_TASKS))
def test_task_reads_its_env(name, envs):
    task, env = envs(name)
    observation, _ = env.reset(seed=0)
    obs, achieved, goal = task.split(observation)
    assert obs.shape == (task.obs_dim,) and achieved.shape == goal.shape == (task.goal_dim,)
    for _ in range(3):
        observation, reward, terminated, _, info = env.step(task.env_action(np.full(task.action_dim, 0.5)))
        obs, achieved, goal = task.split(observation)
        assert not terminated
        # ag is a function of the observation; its first 3 (or 2) entries are the env's own achieved goal.
        env_goal_dim = len(observation["achieved_goal"])
        assert np.array_equal(achieved[:env_goal_dim], observation["achieved_goal"])
        assert np.array_equal(goal[:env_goal_dim], observation["desired_goal"])
        if task.goal_dim == env_goal_dim and name != "point_maze":
            assert task.sparse_reward(achieved, goal) == reward  # Fetch's own sparse reward


def test_unknown_task_and_option_are_errors():
    with pytest.raises(ValueError, match="unknown goal task"):
        make_goal_task("fetch_reech")
    with pytest.raises(ValueError):
        make_goal_task("point_maze", {"action_repeat": 0})


def test_augmented_goal_needs_box_and_gripper():
    task = make_goal_task("fetch_pick_place")
    goal = np.array([1.3, 0.7, 0.5, 1.3, 0.7, 0.5])
    assert task.is_success(np.array([1.3, 0.7, 0.5, 1.3, 0.7, 0.53]), goal)
    assert not task.is_success(np.array([1.3, 0.7, 0.5, 1.3, 0.9, 0.5]), goal)  # gripper elsewhere
    assert not task.is_success(np.array([1.3, 0.9, 0.5, 1.3, 0.7, 0.5]), goal)  # box elsewhere
    plain = make_goal_task("fetch_pick_place", {"augment_goal": False})
    assert plain.goal_dim == 3 and plain.is_success(np.array([1.3, 0.7, 0.5]), goal[:3])
    # Box and gripper each 0.04 away: within 0.05 part by part, 0.057 as one 6-D vector.
    both_near = np.array([1.34, 0.7, 0.5, 1.3, 0.74, 0.5])
    assert task.is_success(both_near, goal) and task.goal_distance(both_near, goal) == pytest.approx(0.04)
    joint = make_goal_task("fetch_pick_place", {"success_distance": "joint"})
    assert not joint.is_success(both_near, goal) and joint.goal_distance(both_near, goal) == pytest.approx(0.0566, 1e-3)
    assert joint.is_success(np.array([1.3, 0.7, 0.5, 1.3, 0.7, 0.53]), goal)


def test_reach_wall_starts_on_one_half_and_blocks_the_straight_way(envs):
    task, env = envs("fetch_reach_wall")
    for seed in range(5):
        observation, _ = env.reset(seed=seed)
        _, start, goal = task.split(observation)
        assert start[1] < WALL_Y - 0.1 and goal[1] > WALL_Y + 0.05 and goal[2] == pytest.approx(0.425)
    for _ in range(25):  # straight at the wall, at the start height
        observation, *_ = env.step(np.array([0.0, 1.0, 0.0, 0.0]))
    assert task.split(observation)[1][1] < WALL_Y - 0.01
    wall = mujoco.mj_name2id(env.unwrapped.model, mujoco.mjtObj.mjOBJ_GEOM, "wall0")
    assert env.unwrapped.model.geom_contype[wall] == 1


def test_reach_wall_goal_is_reachable_over_the_wall(envs):
    task, env = envs("fetch_reach_wall")
    observation, _ = env.reset(seed=1)
    _, achieved, goal = task.split(observation)
    for _ in range(task.episode_length):
        direction = goal - achieved
        if achieved[1] < WALL_Y + 0.05:  # up, then across above the wall (its top is at z 0.6)
            direction = np.array([direction[0], 0.3 if achieved[2] > 0.65 else 0.0, 0.7 - achieved[2]])
        observation, *_ = env.step(np.r_[np.clip(direction / 0.05, -1, 1), 0.0])
        _, achieved, _ = task.split(observation)
    assert task.is_success(achieved, goal)


def test_pick_place_wall_splits_box_and_goal(envs):
    task, env = envs("fetch_pick_place_wall")
    in_air = 0
    for seed in range(20):
        observation, _ = env.reset(seed=seed)
        _, achieved, goal = task.split(observation)
        assert achieved[1] < WALL_Y - 0.05 and goal[1] > WALL_Y + 0.05
        in_air += goal[2] > 0.43
    assert 4 <= in_air <= 16  # half of the goals in the air


def test_point_maze_rooms_and_action_repeat(envs):
    """Starts lower left, goals upper right; with the action repeat a simple controller gets there in 100 steps."""
    task, env = envs("point_maze")
    slow_task, slow_env = envs("point_maze", action_repeat=1)
    maze = env.unwrapped.maze
    reached = {}
    for label, (t, e) in {"repeat": (task, env), "no_repeat": (slow_task, slow_env)}.items():
        observation, _ = e.reset(seed=0)
        obs, achieved, goal = t.split(observation)
        row, col = maze.cell_xy_to_rowcol(achieved)
        assert FOUR_ROOMS[row][col] == "r"
        row, col = maze.cell_xy_to_rowcol(goal)
        assert FOUR_ROOMS[row][col] == "g"
        # The shortest path bends through a side room: longer than the straight line.
        assert task.maze_distance.distance(achieved[None], goal)[0] > np.linalg.norm(goal - achieved) + 0.5
        waypoints = [maze.cell_rowcol_to_xy(np.array(c)) for c in [(5, 3), (5, 5), (3, 5)]] + [goal]
        for _ in range(t.episode_length):
            while len(waypoints) > 1 and np.linalg.norm(waypoints[0] - achieved) < 0.3:
                waypoints.pop(0)
            action = np.clip(3 * (waypoints[0] - achieved) - 0.3 * obs[2:], -1, 1)
            observation, *_ = e.step(action)
            obs, achieved, _ = t.split(observation)
        reached[label] = bool(t.is_success(achieved, goal))
    assert reached == {"repeat": True, "no_repeat": False}


def test_point_maze_leaves_no_model_file_behind():
    """gymnasium-robotics writes the maze's MJCF to the temp directory; the task removes it once it is loaded."""
    env = make_goal_task("point_maze", {}).make_env()
    try:
        written = Path(env.unwrapped.tmp_xml_file_path)
        assert written.parent == Path(tempfile.gettempdir())
        assert not written.exists()
        env.reset(seed=0)
        env.step(np.zeros(2))
    finally:
        env.close()
