"""Task definitions: registry, thesis constants, state capture/restore, DAPG rewards."""

from __future__ import annotations

import numpy as np
import pytest

from workers.tasks import TASKS, UnknownTaskError, make_task

# Table 6 (colored-noise beta) and Table 7 (episode length).
THESIS = {
    "halfcheetah_running": (0.25, 1000),
    "humanoid_standup": (2.0, 1000),
    "door": (2.5, 200),
    "door_sparse": (2.5, 200),
    "fetch_pick_place_sparse": (3.0, 50),
    "relocate": (3.5, 200),
}


@pytest.mark.parametrize("name", sorted(THESIS))
def test_thesis_constants(name):
    task = make_task(name)
    assert (task.colored_noise_beta, task.episode_length) == THESIS[name]


@pytest.mark.parametrize("name", sorted(TASKS))
def test_task_matches_its_environment(name, task_bundle):
    task, env, _ = task_bundle(name)
    raw = env.unwrapped
    assert env.action_space.shape == (task.action_dim,)
    assert task.frame_skip == (getattr(raw, "frame_skip", None) or raw.n_substeps)


def test_unknown_task_suggests_the_closest_name():
    with pytest.raises(UnknownTaskError, match="did you mean 'halfcheetah_running'"):
        make_task("halfcheetah_runing")


@pytest.mark.parametrize("name", sorted(TASKS))
def test_restore_reproduces_the_following_steps(name, task_bundle):
    """capture -> (other steps) -> restore: the next steps repeat exactly."""
    task, env, _ = task_bundle(name)
    env.reset(seed=5)
    rng = np.random.default_rng(0)
    for _ in range(5):
        task.step_env(env, rng.uniform(-1, 1, task.action_dim))
    state = task.capture(env, time_step=5)
    actions = rng.uniform(-1, 1, (6, task.action_dim))
    first = [task.step_env(env, a).reward for a in actions]
    env.reset(seed=99)  # somewhere else entirely, other goal and model randomisation
    for _ in range(3):
        task.step_env(env, rng.uniform(-1, 1, task.action_dim))
    task.restore(env, state)
    again = [task.step_env(env, a).reward for a in actions]
    np.testing.assert_allclose(again, first, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["door", "relocate"])
def test_dapg_reward_differs_from_gymnasium_robotics_only_in_the_palm_sign(name, task_bundle):
    """gymnasium-robotics 1.4.2 adds +0.1 ||palm - x|| where DAPG subtracts it (see adroit.py)."""
    task, env, _ = task_bundle(name)
    env.reset(seed=1)
    raw = env.unwrapped
    rng = np.random.default_rng(0)
    for _ in range(10):
        action = rng.uniform(-1, 1, task.action_dim)
        _, gym_reward, *_ = env.step(action)
        q = task._env_quantities(env)
        other = q["handle"] if name == "door" else q["ball"]
        palm_term = 0.1 * np.linalg.norm(q["palm"] - other)
        assert task._reward(q) == pytest.approx(gym_reward - 2 * palm_term, abs=1e-12)
    assert raw is env.unwrapped


def test_door_sparse_is_door_without_the_palm_term(task_bundle):
    door, env, _ = task_bundle("door")
    sparse = make_task("door_sparse")
    env.reset(seed=2)
    env.step(np.zeros(door.action_dim))
    q = door._env_quantities(env)
    palm_term = -0.1 * np.linalg.norm(q["palm"] - q["handle"])
    assert door._reward(q) == pytest.approx(sparse._reward(q) + palm_term)


def test_dapg_success_needs_more_than_25_goal_steps():
    door = make_task("door")
    assert door.episode_success([True] * 25 + [False] * 175) is False
    assert door.episode_success([True] * 26 + [False] * 174) is True


def test_fetch_success_is_the_final_step():
    fetch = make_task("fetch_pick_place_sparse")
    assert fetch.episode_success([True] * 49 + [False]) is False
    assert fetch.episode_success([False] * 49 + [True]) is True
