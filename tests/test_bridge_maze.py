"""BridgeMaze (thesis App. D.4): falls, the goal, the wind, the reward and the coverage grid."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.tasks.bridge_maze import (
    COVERAGE_BINS,
    LAYOUTS,
    BridgeMaze,
    bridge_maze_reward,
    coverage_grid,
    in_wind_region,
    on_walkway,
    state_coverage,
)

torch.set_num_threads(1)


def waypoint_controller(waypoints, speed: float = 6.0):
    """Track a velocity of ``speed`` m/s towards the next waypoint."""
    waypoints = np.asarray(waypoints, dtype=float)
    state = {"i": 0}

    def act(obs: np.ndarray) -> np.ndarray:
        pos, vel = obs[:2], obs[7:9]
        while state["i"] < len(waypoints) - 1 and np.linalg.norm(waypoints[state["i"]] - pos) < 0.5:
            state["i"] += 1
        offset = waypoints[state["i"]] - pos
        return np.clip(0.5 * (speed * offset / max(np.linalg.norm(offset), 1.0) - vel), -1, 1)

    return act


def run(task: BridgeMaze, policy, seed: int = 0):
    env = task.make_env()
    obs, _ = env.reset(seed=seed)
    observations, rewards, infos = [obs], [], []
    terminated = truncated = False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(task.env_action(policy(obs)))
        observations.append(obs)
        rewards.append(reward)
        infos.append(info)
    env.close()
    return np.array(observations), np.array(rewards), infos, terminated


LOWER = [(-12, -5.5), (-9, -5.5), (9, -5.5), (13, -5.5)]
UPPER = [(-12, 9), (-9, 9), (9, 9), (13, 9)]
MIDDLE = [(-9, 0), (9, 0), (13, 0)]
INTO_LAVA = [(-9, 0), (-4, 0), (-4, 3)]  # onto the middle bridge, then off its side into the gap above it
SIDE_ROUTES = {
    "wide": {"lower": LOWER, "upper": UPPER},
    "compact": {
        "lower": [(-12, -4.75), (-9, -4.75), (9, -4.75), (13, -4.75)],
        "upper": [(-12, 5), (-9, 5), (9, 5), (13, 5)],
    },
}
"""Each layout's routes over its side bridges, along their centre lines."""
GAP_BETWEEN_MIDDLE_AND_UPPER = {"wide": 3.0, "compact": 2.5}
"""A y in the lava gap between the middle and the upper bridge of each layout."""


@pytest.mark.parametrize("bridge", ["lower", "upper"])
@pytest.mark.parametrize("layout", ["wide", "compact"])
def test_goal_is_reachable_by_a_scripted_controller(layout, bridge):
    task = BridgeMaze(layout=layout)
    observations, rewards, infos, terminated = run(task, waypoint_controller(SIDE_ROUTES[layout][bridge]))
    metrics = task.episode_metrics(observations, rewards, infos)
    assert metrics["success"] == 1.0 and metrics["failure"] == 0.0 and not terminated
    assert observations.shape == (task.episode_length + 1, 10)
    # Eq. 36 telescopes to the distance covered towards the goal line, 12 - (-12), less the last
    # stretch: the step that crosses the line earns 0 (the goal case).
    assert 23.0 < metrics["return"] <= 24.0
    assert metrics["windy_steps"] == 0  # neither side bridge is in the wind
    # The cube slides upright: the free joint's quaternion stays close to the identity.
    assert np.abs(observations[:, 3]).min() > 0.98


def test_on_solid_ground_the_cube_neither_bobs_nor_stalls():
    """Random pushes on the start platform: height and vertical velocity stay still (no contact jitter for a
    model to learn as noise, see bridge_maze.xml); full force reaches over 6 m/s and coasting stops in a second."""
    task = BridgeMaze(episode_length=40)
    rng = np.random.default_rng(0)
    pushes = iter(rng.uniform(-0.6, 0.6, (40, 2)))
    observations, _, _, _ = run(task, lambda obs: next(pushes))
    assert np.all(on_walkway(observations[:, 0], observations[:, 1]))
    assert np.abs(observations[:, 2] - 0.25).max() < 2e-3
    assert observations[:, 9].std() < 5e-3
    env = task.make_env()
    obs, _ = env.reset(seed=0)
    for _ in range(30):
        obs, *_ = env.step(np.array([0.0, 1.0]))
    top = obs[8]
    for _ in range(20):
        obs, *_ = env.step(np.zeros(2))
    env.close()
    assert top > 6.0 and abs(obs[8]) < 0.1 * top


def test_a_fall_into_the_lava_ends_the_episode():
    task = BridgeMaze()
    observations, rewards, infos, terminated = run(task, waypoint_controller(INTO_LAVA))
    assert terminated and len(rewards) < 100  # well before the 200-step limit
    assert observations[-1, 2] < -1.5 and infos[-1]["fell"]
    assert rewards[-1] == -1.0
    metrics = task.episode_metrics(observations, rewards, infos)
    assert metrics["failure"] == 1.0 and metrics["success"] == 0.0


@pytest.mark.parametrize("layout", ["wide", "compact"])
def test_the_platform_rims_leave_the_bridges_as_the_only_way_to_the_lava(layout):
    """Driven at speed at the gap between two bridges, the cube stops at the start platform's rim."""
    task = BridgeMaze(episode_length=60, layout=layout)
    gap = GAP_BETWEEN_MIDDLE_AND_UPPER[layout]
    observations, _, infos, terminated = run(task, waypoint_controller([(-12, gap), (-4, gap)]))
    assert not terminated and not any(info["fell"] for info in infos)
    assert np.all(on_walkway(observations[:, 0], observations[:, 1], LAYOUTS[layout].walkway))
    assert -8.6 < observations[-1, 0] < -8.0 and observations[:, 7].max() > 4.0  # hit at speed


def test_a_cube_pushed_into_a_rim_slides_along_it_upright():
    """Pressed into the start platform's rim beside the middle bridge and pushed along it with half the force
    that presses it in, the cube slides (frictionless rims: no stick-slip switch for a model to learn there)
    and stays upright."""
    task = BridgeMaze(episode_length=40)
    env = task.make_env()
    env.reset(seed=0)
    unwrapped = env.unwrapped
    qpos = unwrapped.init_qpos.copy()
    qpos[:2] = (-8.46, -2.0)  # touching start_rim_lower_middle (its face at x = -8.2)
    unwrapped.set_state(qpos, np.zeros(unwrapped.model.nv))
    for _ in range(20):
        obs, *_ = env.step(task.env_action(np.array([1.0, -0.5])))
    env.close()
    assert obs[0] < -8.2 and obs[1] < -3.0  # held at the rim, slid over a metre along it
    assert abs(obs[3]) > 0.99


def test_without_termination_the_fall_costs_minus_one_per_step():
    task = BridgeMaze(episode_length=100, terminate_on_fall=False)
    observations, rewards, _, terminated = run(task, waypoint_controller(INTO_LAVA))
    assert not terminated and len(rewards) == 100
    fallen = observations[1:, 2] < -1.5
    assert fallen[-1] and np.all(rewards[fallen] == -1.0)


@pytest.mark.parametrize("layout", ["wide", "compact"])
def test_wind_only_acts_on_the_middle_bridge(layout):
    task = BridgeMaze(wind_max=30.0, layout=layout)
    for route in (MIDDLE, *SIDE_ROUTES[layout].values()):
        observations, _, infos, _ = run(task, waypoint_controller(route), seed=1)
        before = observations[:-1]
        windy = np.array([info["wind_applied"] > 0 for info in infos])
        inside = in_wind_region(before[:, 0], before[:, 1]) | in_wind_region(observations[1:, 0], observations[1:, 1])
        assert not np.any(windy & ~inside)
        if route is MIDDLE:
            assert windy.sum() > 5
        else:
            assert windy.sum() == 0


def test_wind_pushes_sideways_and_is_redrawn_every_period():
    """On the middle bridge, holding still, the cube drifts along y; the draw changes every 5 steps."""
    task = BridgeMaze(wind_max=30.0, episode_length=40, terminate_on_fall=False)
    env = task.make_env()
    env.reset(seed=3)
    raw = env.unwrapped
    raw.set_state(np.array([0.0, 0.0, 0.25, 1, 0, 0, 0]), np.zeros(6))
    winds, ys = [], []
    for _ in range(20):
        obs, *_, info = env.step(np.zeros(2))
        winds.append(info["wind"])
        ys.append(obs[1])
    winds = np.array(winds)
    assert all(len(set(winds[i : i + 5])) == 1 for i in range(0, 20, 5))
    assert len(set(winds)) == 4
    assert np.abs(np.array(ys)).max() > 0.05  # the force moves the cube
    calm = BridgeMaze(wind_max=0.0).make_env()
    calm.reset(seed=3)
    calm.unwrapped.set_state(np.array([0.0, 0.0, 0.25, 1, 0, 0, 0]), np.zeros(6))
    for _ in range(20):
        obs, *_ = calm.step(np.zeros(2))
    assert abs(obs[1]) < 1e-6
    env.close()
    calm.close()


def test_the_middle_bridge_is_risky_but_crossable():
    """The wind is tuned so a straight run sometimes succeeds and sometimes falls (section 5.4.2)."""
    task = BridgeMaze(wind_max=30.0)
    successes = [task.episode_metrics(*run(task, waypoint_controller(MIDDLE), seed=s)[:3])["success"] for s in range(8)]
    assert 0 < sum(successes) < 8


def test_planning_cost_is_minus_eq_36():
    task = BridgeMaze()
    rng = np.random.default_rng(0)
    obs, next_obs = rng.uniform(-16, 16, (500, 10)), rng.uniform(-16, 16, (500, 10))
    next_obs[:, 2] = rng.uniform(-3, 1, 500)
    expected = -bridge_maze_reward(obs[:, 0], next_obs[:, 0], next_obs[:, 2])
    cost = task.planning_cost(torch.as_tensor(obs), torch.zeros(500, 2), torch.as_tensor(next_obs))
    np.testing.assert_allclose(cost.numpy(), expected)
    # The three cases of eq. 36, the fall taking precedence over the goal.
    assert bridge_maze_reward(np.array(0.0), np.array(1.0), np.array(0.25)) == 1.0
    assert bridge_maze_reward(np.array(11.5), np.array(12.5), np.array(0.25)) == 0.0
    assert bridge_maze_reward(np.array(11.5), np.array(12.5), np.array(-2.0)) == -1.0


def test_walkway_geometry():
    assert on_walkway(-12, 0) and on_walkway(0, 0) and on_walkway(0, -5.5) and on_walkway(0, 9) and on_walkway(12, 0)
    assert not on_walkway(0, 3) and not on_walkway(0, -3) and not on_walkway(0, 6) and not on_walkway(18, 0)
    assert in_wind_region(0, 3) and not in_wind_region(0, -5.5) and not in_wind_region(9, 0)
    compact = LAYOUTS["compact"].walkway
    assert all(on_walkway(0, y, compact) for y in (-4.75, 0, 5)) and on_walkway(-12, 7, compact)
    assert not any(on_walkway(0, y, compact) for y in (-3, 2.5, 9)) and not on_walkway(-12, 9, compact)
    # Both side bridges lie outside the wind region of App. D.4 in both layouts.
    for layout in LAYOUTS.values():
        for (x0, x1), (y0, y1) in layout.walkway[3:]:
            assert not in_wind_region(0, y0) and not in_wind_region(0, y1)


def test_the_compact_layout_moves_the_maze_and_keeps_the_physics():
    """The two XML files differ in where the platforms, bridges, walls and rims are, nothing else."""
    import mujoco

    wide, compact = (mujoco.MjModel.from_xml_path(str(layout.xml)) for layout in LAYOUTS.values())
    assert wide.opt.timestep == compact.opt.timestep
    for field in ("body_mass", "body_inertia", "dof_damping", "actuator_gear", "actuator_ctrlrange", "body_pos"):
        np.testing.assert_array_equal(getattr(wide, field), getattr(compact, field), err_msg=field)
    names = [[m.geom(i).name for i in range(m.ngeom)] for m in (wide, compact)]
    assert names[0] == names[1]
    for field in ("geom_friction", "geom_condim", "geom_contype", "geom_conaffinity", "geom_type"):
        np.testing.assert_array_equal(getattr(wide, field), getattr(compact, field), err_msg=field)
    moved = {names[0][i] for i in range(wide.ngeom) if not np.allclose(wide.geom_pos[i], compact.geom_pos[i])}
    assert "cube" not in moved and "walkway" not in moved and {"bridge_lower", "bridge_upper"} <= moved


@pytest.mark.parametrize("layout, rim", [("wide", ((-8.2, -8.0), (1.0, 8.0))), ("compact", ((-8.2, -8.0), (1.0, 4.0)))])
def test_the_maps_walls_are_the_xmls_walls_and_rims(layout, rim):
    task = BridgeMaze(layout=layout)
    walls = task.map_walls
    assert len(walls) == 16  # two walls along the upper bridge, 3 outer and 4 inner rims per platform
    assert rim in [tuple(tuple(round(v, 6) for v in r) for r in w) for w in walls]  # between middle and upper
    assert task.map_rectangles == LAYOUTS[layout].walkway


def test_coverage_grid():
    grid = coverage_grid(np.array([[-20.0, -10.0], [20.0, 15.0], [0.0, 0.0], [0.1, 0.1], [30.0, 0.0]]))
    assert grid.shape == (COVERAGE_BINS, COVERAGE_BINS)
    assert grid[0, 0] and grid[-1, -1] and grid.sum() == 3  # (0, 0) and (0.1, 0.1) share a cell; x = 30 is outside
    assert state_coverage(grid) == pytest.approx(3 / 2500)


def test_success_needs_the_goal_without_a_fall():
    task = BridgeMaze()
    observations = np.zeros((4, 10))
    observations[:, 0] = [-12.0, 0.0, 12.5, 7.0]
    observations[:, 2] = [0.25, 0.25, 0.25, 0.25]
    assert task.episode_metrics(observations, np.zeros(3), [{}] * 3)["success"] == 1.0
    observations[3, 2] = -1.6  # went back and fell into the lava after reaching the goal
    metrics = task.episode_metrics(observations, np.zeros(3), [{}] * 3)
    assert metrics["success"] == 0.0 and metrics["failure"] == 1.0


@pytest.mark.parametrize("unit_quaternion", [True, False])
def test_predicted_states_get_a_unit_quaternion_with_w_non_negative(unit_quaternion):
    task = BridgeMaze(unit_quaternion=unit_quaternion)
    states = torch.randn(4, 6, 10)
    states[0, 0, 3:7] = torch.tensor([-0.9, 0.1, 0.0, 0.2])  # w < 0: the same rotation as its negative
    projected = task.project_states(states)
    if not unit_quaternion:
        assert torch.equal(projected, states)
        return
    quaternion = projected[..., 3:7]
    torch.testing.assert_close(quaternion.norm(dim=-1), torch.ones(4, 6))
    assert (quaternion[..., 0] >= 0).all()
    # The same rotation: parallel to the input, up to the sign that makes w >= 0.
    raw = states[..., 3:7]
    cosine = (quaternion * raw).sum(-1) / raw.norm(dim=-1)
    torch.testing.assert_close(cosine.abs(), torch.ones(4, 6))
    torch.testing.assert_close(projected[0, 0, 3:7], torch.tensor([0.9, -0.1, 0.0, -0.2]) / 0.86**0.5)
    # Position and velocity are left alone.
    assert torch.equal(projected[..., :3], states[..., :3]) and torch.equal(projected[..., 7:], states[..., 7:])
