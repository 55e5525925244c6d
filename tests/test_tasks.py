"""Task definitions: registry, thesis constants, state capture/restore, DAPG rewards."""

from __future__ import annotations

import numpy as np
import pytest

from workers.tasks import GROUND_TRUTH_TASKS, UnknownTaskError, make_task

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


@pytest.mark.parametrize("name", sorted(GROUND_TRUTH_TASKS))
def test_task_matches_its_environment(name, task_bundle):
    task, env, _ = task_bundle(name)
    raw = env.unwrapped
    assert env.action_space.shape == (task.action_dim,)
    assert task.frame_skip == (getattr(raw, "frame_skip", None) or raw.n_substeps)


def test_unknown_task_suggests_the_closest_name():
    with pytest.raises(UnknownTaskError, match="did you mean 'halfcheetah_running'"):
        make_task("halfcheetah_runing")


@pytest.mark.parametrize("name", sorted(GROUND_TRUTH_TASKS))
def test_restore_reproduces_the_following_steps(name, task_bundle):
    """capture -> (other steps) -> restore: the next steps repeat exactly."""
    task, env, _ = task_bundle(name)
    env.reset(seed=5)
    rng = np.random.default_rng(0)
    for _ in range(5):
        task.step_env(env, rng.uniform(-1, 1, task.action_dim))
    state = task.capture(env)
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


def test_door_observation_matches_the_environment(task_bundle):
    door, env, _ = task_bundle("door")
    env.reset(seed=3)
    env.step(np.random.default_rng(0).uniform(-1, 1, door.action_dim))
    raw = env.unwrapped
    rebuilt = door._observation(raw.model, raw.data.qpos, door._env_quantities(env))
    np.testing.assert_array_equal(rebuilt, raw._get_obs())


@pytest.mark.parametrize("name", ["door", "door_sparse"])
def test_door_planning_cost_options(name, task_bundle):
    """velocity_term=qvel plans on -reward; the default swaps in the authors' observation term."""
    from workers.rollout import BatchEvaluator

    _, env, model = task_bundle(name)
    env.reset(seed=4)
    literal, authors = make_task(name, {"velocity_term": "qvel"}), make_task(name)
    state = literal.capture(env)
    actions = np.random.default_rng(1).uniform(-1, 1, (4, 6, literal.action_dim))
    with BatchEvaluator(literal, model, threads=1) as evaluator:
        batch = evaluator.simulate(state, actions)
    np.testing.assert_array_equal(literal.costs(model, batch), -literal.rewards(model, batch))
    q = authors._batch_quantities(model, batch)
    tail = authors._observation(model, authors.qpos(model, batch.states), q)[..., -30:]
    expected = -authors.rewards(model, batch) - 1e-5 * np.sum(q["qvel"] ** 2, -1) + 1e-5 * np.sum(tail**2, -1)
    np.testing.assert_allclose(authors.costs(model, batch), expected, rtol=0, atol=1e-12)
    assert not np.allclose(authors.costs(model, batch), literal.costs(model, batch), rtol=0, atol=1e-9)


def test_halfcheetah_flip_penalty_option(task_bundle):
    from workers.rollout import BatchEvaluator

    _, env, model = task_bundle("halfcheetah_running")
    env.reset(seed=0)
    raw = env.unwrapped
    raw.set_state(raw.data.qpos + np.array([0, 0, 2.5] + [0] * 6), raw.data.qvel)  # on its back
    plain, penalised = make_task("halfcheetah_running", {"flip_penalty": 0}), make_task("halfcheetah_running")
    state = plain.capture(env)
    with BatchEvaluator(plain, model, threads=1) as evaluator:
        batch = evaluator.simulate(state, np.random.default_rng(0).uniform(-1, 1, (3, 5, 6)))
    np.testing.assert_array_equal(plain.costs(model, batch), -plain.rewards(model, batch))
    flipped = np.abs(batch.states[..., 3]) > np.pi / 2  # qpos[2] is the root angle
    assert flipped.any()
    np.testing.assert_array_equal(penalised.costs(model, batch) - plain.costs(model, batch), 10.0 * flipped)


def test_relocate_planning_cost_leaves_out_the_palm_to_target_term_by_default(task_bundle):
    """The authors' cost omits -0.5 ||palm - target|| while the ball is up; the option puts it back."""
    from workers.rollout import BatchEvaluator
    from workers.tasks.adroit import Relocate

    task, env, model = task_bundle("relocate")
    env.reset(seed=3)
    state = task.capture(env)
    actions = np.random.default_rng(0).uniform(-1, 1, (4, 5, task.action_dim))
    with BatchEvaluator(task, model, threads=1) as evaluator:
        batch = evaluator.simulate(state, actions)
    q = task._batch_quantities(model, batch)
    q["ball"] = q["ball"].copy()
    q["ball"][..., 2] = 0.1  # pretend the ball is lifted everywhere
    lifted_batch = batch._replace(frames=batch.frames.copy())
    lifted_batch.frames[..., task.frame_slice("Object")] = q["ball"]
    palm_target = 0.5 * np.linalg.norm(q["palm"] - q["target"], axis=-1)
    default, with_term = Relocate(), Relocate(palm_target_term=True)
    np.testing.assert_allclose(with_term.costs(model, lifted_batch), -task.rewards(model, lifted_batch))
    np.testing.assert_allclose(default.costs(model, lifted_batch) + palm_target, with_term.costs(model, lifted_batch))


@pytest.mark.parametrize("name", ["relocate", "door"])
def test_contact_margin_max_halves_the_margins_of_the_environment_and_the_planning_model(name):
    plain, old_rule = make_task(name), make_task(name, {"contact_margin": "max"})
    plain_env, old_env = plain.make_env(), old_rule.make_env()
    np.testing.assert_array_equal(old_env.unwrapped.model.geom_margin, 0.5 * plain_env.unwrapped.model.geom_margin)
    planning_model = old_rule.build_planning_model(old_env)
    np.testing.assert_array_equal(planning_model.geom_margin, old_env.unwrapped.model.geom_margin)


def test_contact_margin_max_rests_the_ball_half_a_millimetre_lower_in_env_and_rollouts():
    """With MuJoCo 2's rule the ball-table contact keeps 0.5 mm stand-off instead of 1 mm; rollouts agree."""
    from workers.rollout import BatchEvaluator

    resting = {}
    for rule in ("sum", "max"):
        task = make_task("relocate", {"contact_margin": rule})
        env = task.make_env()
        env.reset(seed=0)
        model = task.build_planning_model(env)
        state = task.capture(env)
        for _ in range(10):
            task.step_env(env, np.zeros(task.action_dim))
        with BatchEvaluator(task, model, threads=1) as evaluator:
            batch = evaluator.simulate(state, np.zeros((1, 10, task.action_dim)))
        ball_in_rollout = batch.frames[0, -1, task.frame_slice("Object")][2]
        ball_in_env = env.unwrapped.data.xpos[env.unwrapped.model.body("Object").id][2]
        assert ball_in_rollout == pytest.approx(ball_in_env, abs=1e-9)
        resting[rule] = ball_in_env
    assert resting["sum"] - resting["max"] == pytest.approx(5e-4, abs=1e-4)


def test_relocate_counts_a_ball_falling_in_the_simulator_as_free_flight():
    import mujoco

    from workers.tasks.adroit import STEP_SECONDS

    task = make_task("relocate")
    env = task.make_env()
    env.reset(seed=0)
    raw = env.unwrapped
    assert raw.model.opt.timestep * raw.frame_skip == pytest.approx(STEP_SECONDS)
    raw.data.qpos[raw.model.joint("OBJTz").qposadr[0]] += 0.3  # 0.3 m up: about 0.25 s of fall
    mujoco.mj_forward(raw.model, raw.data)
    observations = [task.observe(raw._get_obs())]
    for _ in range(12):
        observations.append(task.observe(task.step_env(env, np.zeros(task.action_dim)).observation))
    metrics = task.episode_metrics(np.array(observations))
    assert metrics["ball_flight_steps"] == 11  # every step pair of the fall
    assert metrics["ball_off_table"] == 0.0


def test_relocate_flight_metrics_tell_a_batted_ball_from_a_resting_or_lost_one():
    from workers.tasks.adroit import STEP_SECONDS

    task = make_task("relocate")
    t = np.arange(40) * STEP_SECONDS
    observations = np.zeros((40, 39))
    observations[:, -3:] = [0.3, 0.2, -0.2]  # at rest on the table, away from the target
    assert task.episode_metrics(observations) == {"ball_flight_steps": 0, "goal_flight_steps": 0, "ball_off_table": 0}
    # Batted up through the target: a parabola whose middle passes within 0.1 of it.
    observations[:, -3:] = np.stack([0.5 * (t - 0.2), 0 * t, 1.5 * (t - 0.2) - 4.905 * (t - 0.2) ** 2], axis=1)
    metrics = task.episode_metrics(observations)
    near = np.linalg.norm(observations[1:-1, -3:], axis=1) < 0.1
    assert metrics["ball_flight_steps"] == 38 and metrics["goal_flight_steps"] == near.sum() > 0
    observations[-1, -3:] = [0.4, 1.6, -1.2]  # ends on the floor
    assert task.episode_metrics(observations)["ball_off_table"] == 1.0


# ------------------------------------------------ MuJoCo >= 3.12 compatibility
BALL_AND_FRIENDS = """
<mujoco>
  <worldbody>
    <body name="free"><freejoint name="free"/><geom size="0.1"/></body>
    <body name="ball" pos="1 0 0"><joint name="ball" type="ball"/><geom size="0.1"/>
      <body name="arm" pos="0 0 0.3"><joint name="hinge" type="hinge"/><joint name="slide" type="slide"/>
        <geom size="0.1"/></body></body>
  </worldbody>
</mujoco>
"""


def _original_mujoco_utils():
    """A fresh copy of gymnasium-robotics' mujoco_utils module, untouched by the patch."""
    import importlib.util

    import gymnasium_robotics.utils.mujoco_utils as patched

    spec = importlib.util.spec_from_file_location("original_mujoco_utils", patched.__file__)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# (joint, kind) -> (slice start, width) in BALL_AND_FRIENDS, as gymnasium-robotics 1.4.2 reads them; its
# get_joint_qvel reads 4 values of a ball joint (3 degrees of freedom), set_joint_qvel writes 3.
JOINT_SLICES = {("free", "qpos"): (0, 7), ("ball", "qpos"): (7, 4), ("hinge", "qpos"): (11, 1),
                ("slide", "qpos"): (12, 1), ("free", "qvel"): (0, 6), ("ball", "qvel"): (6, 4),
                ("hinge", "qvel"): (9, 1), ("slide", "qvel"): (10, 1)}  # fmt: skip


def test_joint_helpers_replacing_gymnasium_robotics_ones_behave_like_them():
    """The replacements work on every MuJoCo and, where the originals still run (MuJoCo < 3.12), read and
    write exactly what they do."""
    import mujoco

    from workers.tasks import mujoco_compat

    original = _original_mujoco_utils() if tuple(map(int, mujoco.__version__.split(".")[:2])) < (3, 12) else None
    model = mujoco.MjModel.from_xml_string(BALL_AND_FRIENDS)
    rng = np.random.default_rng(0)
    for (joint, kind), (start, width) in JOINT_SLICES.items():
        data = mujoco.MjData(model)
        setattr(data, kind, rng.normal(size=getattr(data, kind).shape))
        np.testing.assert_array_equal(
            getattr(mujoco_compat, f"get_joint_{kind}")(model, data, joint), getattr(data, kind)[start : start + width]
        )
        written = rng.normal(size=3 if (joint, kind) == ("ball", "qvel") else width)
        expected = getattr(data, kind).copy()
        expected[start : start + len(written)] = written
        getattr(mujoco_compat, f"set_joint_{kind}")(model, data, joint, written)
        np.testing.assert_array_equal(getattr(data, kind), expected)
        if original is not None:
            reference = mujoco.MjData(model)
            setattr(reference, kind, getattr(data, kind))
            np.testing.assert_array_equal(getattr(original, f"get_joint_{kind}")(model, reference, joint),
                                          getattr(mujoco_compat, f"get_joint_{kind}")(model, data, joint))  # fmt: skip
            getattr(original, f"set_joint_{kind}")(model, reference, joint, written)
            np.testing.assert_array_equal(getattr(reference, kind), getattr(data, kind))
    with pytest.raises(AssertionError, match="incorrect shape"):
        mujoco_compat.set_joint_qpos(model, mujoco.MjData(model), "free", np.zeros(3))


def test_robotics_environments_are_built_with_the_replaced_joint_helpers():
    import gymnasium_robotics.utils.mujoco_utils as utils

    from workers.tasks import mujoco_compat
    from workers.tasks.base import register_robotics_envs

    register_robotics_envs()
    for name, function in mujoco_compat.REPLACEMENTS.items():
        assert getattr(utils, name) is function
    env = make_task("fetch_pick_place_sparse").make_env()
    env.reset(seed=0)  # places the object through set_joint_qpos
    env.close()


def test_mujoco_warnings_go_to_logging_once_and_leave_no_file(tmp_path, monkeypatch, caplog):
    """HalfCheetah's model uses the deprecated settotalmass: MuJoCo's own handler would append the warning to a
    MUJOCO_LOG.TXT in the working directory of every run."""
    import logging

    import mujoco

    from workers.tasks.mujoco_compat import route_warnings_to_logging

    monkeypatch.chdir(tmp_path)
    route_warnings_to_logging()  # a fresh record of what was logged, for this test
    xml = (
        '<mujoco><compiler settotalmass="2"/>'
        '<worldbody><body><freejoint/><geom size="0.1"/></body></worldbody></mujoco>'
    )
    with caplog.at_level(logging.WARNING, logger="mujoco"):
        for _ in range(2):
            mujoco.MjModel.from_xml_string(xml)
    assert len([record for record in caplog.records if "settotalmass" in record.getMessage()]) == 1
    assert list(tmp_path.iterdir()) == []
