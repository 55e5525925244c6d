"""Maps of a trained ensemble's one-step Var_A and Var_E over a task's plane (workers/dynamics/uncertainty_map.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.dynamics.costs import reduce_uncertainty
from workers.dynamics.ensemble import DynamicsEnsemble, EnsembleConfig
from workers.dynamics.propagation import petsus_propagate
from workers.dynamics.settings import RazerSettings
from workers.dynamics.uncertainty_map import one_step_uncertainty, uncertainty_map

torch.set_num_threads(1)


def tiny_model(obs_dim: int = 3, action_dim: int = 2) -> DynamicsEnsemble:
    config = EnsembleConfig.preset("small", ensemble_size=5, hidden_layers=2, hidden_size=16)
    return DynamicsEnsemble(obs_dim, action_dim, config, seed=0)


class PlaneTask:
    """A task whose state is (x, y, 0.5) and whose map probe pushes along both axes."""

    def plane_states(self, xy):
        states = np.concatenate([xy, np.full((len(xy), 1), 0.5)], axis=1)
        return states, np.tile([0.3, -0.7], (len(xy), 1))


@pytest.mark.parametrize("terms", ["means_and_variances", "means"])
@pytest.mark.parametrize("reduction, dims", [("sum_sqrt", None), ("sqrt_sum", (0, 2)), ("mean_sqrt", (1,))])
def test_the_map_is_the_first_step_of_the_planners_propagation(terms, reduction, dims):
    """What the map shows at a state is what PETSUS's first step from it adds to eq. 26 and eq. 27."""
    model = tiny_model()
    settings = RazerSettings(epistemic_terms=terms, uncertainty_reduction=reduction, uncertainty_dims=dims)
    rng = np.random.default_rng(0)
    states, actions = rng.normal(size=(4, 3)), rng.uniform(-1, 1, size=(4, 2))
    aleatoric, epistemic = one_step_uncertainty(model, states, actions, settings)
    for i in range(4):
        start = torch.as_tensor(states[i], dtype=torch.float32)
        step = torch.as_tensor(actions[i], dtype=torch.float32).view(1, 1, 2)
        prop = petsus_propagate(model, start, step, 10, "shared", torch.Generator().manual_seed(0), terms)
        expected_a = reduce_uncertainty(prop.var_aleatoric[0, 0], reduction, dims)
        expected_e = reduce_uncertainty(prop.var_epistemic[0, 0], reduction, dims)
        np.testing.assert_allclose(aleatoric[i], expected_a.item(), rtol=1e-5)
        np.testing.assert_allclose(epistemic[i], expected_e.item(), rtol=1e-5)


def test_the_map_puts_each_value_at_its_grid_point():
    model = tiny_model()
    settings = RazerSettings()
    ranges = ((-3.0, 5.0), (1.0, 2.0))
    umap = uncertainty_map(model, PlaneTask(), settings, ranges, bins=7)
    assert umap.aleatoric.shape == umap.epistemic.shape == (7, 7)
    np.testing.assert_allclose(umap.x[[0, -1]], ranges[0])
    np.testing.assert_allclose(umap.y[[0, -1]], ranges[1])
    for i, j in [(0, 6), (6, 0), (2, 5)]:
        states, actions = PlaneTask().plane_states(np.array([[umap.x[i], umap.y[j]]]))
        aleatoric, epistemic = one_step_uncertainty(model, states, actions, settings)
        np.testing.assert_allclose(umap.aleatoric[i, j], aleatoric[0], rtol=1e-5)
        np.testing.assert_allclose(umap.epistemic[i, j], epistemic[0], rtol=1e-5)


def test_a_task_without_a_plane_has_no_map():
    class NoPlane:
        def plane_states(self, xy):
            return None

    assert uncertainty_map(tiny_model(), NoPlane(), RazerSettings(), ((0, 1), (0, 1))) is None


def test_bridge_maze_probes_the_cube_as_it_rests_on_the_walkway():
    """The map's states are the reset state moved to each point and set moving: height and orientation match."""
    from workers.tasks import make_task

    task = make_task("bridge_maze", {})
    env = task.make_env()
    try:
        rest, _ = env.reset(seed=0)
    finally:
        env.close()
    states, actions = task.plane_states(np.array([rest[:2], [3.0, -5.5]]))
    expected = rest.copy()
    expected[7] = states[0, 7]
    np.testing.assert_allclose(states[0], expected, atol=1e-9)
    assert states[0, 7] > 0 and np.all(actions == [[1.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(states[1, :2], [3.0, -5.5])


# ------------------------------------------------------------------ icemlab model
def bridge_maze_checkpoint(path, obs_dim: int = 10, action_dim: int = 2):
    model = tiny_model(obs_dim, action_dim)
    model.weights_version = 7
    model.save(path, weights_only=True)
    return path


def test_icemlab_model_describes_a_checkpoint_and_draws_its_map(tmp_path):
    from helpers import cli

    checkpoint = bridge_maze_checkpoint(tmp_path / "model_v007.npz")
    result = cli("model", str(checkpoint), "--task", "bridge_maze", "--epistemic-terms", "means", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "weights version 7, 5 members x 2 hidden layers of 16" in result.stdout
    assert (tmp_path / "uncertainty_v007.png").read_bytes().startswith(b"\x89PNG")
    assert "uncertainty map: uncertainty_v007.png" in result.stdout


@pytest.mark.parametrize(
    "case, message",
    [
        ("other_task", "task noisy_halfcheetah has a 17-d state and a 6-d action"),
        ("not_a_checkpoint", "is not an ensemble checkpoint"),
        ("missing", "no file"),
        ("ground_truth_task", "is not a task of the mbrl method"),
        ("unknown_task", "bridge_mace"),
        ("dims_outside", "--dims must be distinct dimensions in 0..9, got [3, 10]"),
        ("dims_twice", "--dims must be distinct dimensions in 0..9, got [3, 3]"),
    ],
)
def test_icemlab_model_refuses_what_it_cannot_draw_and_writes_nothing(case, message, tmp_path, capsys):
    from orchestrator.cli import EXIT_BAD_INPUT, main

    checkpoint = bridge_maze_checkpoint(tmp_path / "model.npz")
    (tmp_path / "notes.txt").write_text("not a model")
    args = {
        "other_task": [str(checkpoint), "--task", "noisy_halfcheetah"],
        "not_a_checkpoint": [str(tmp_path / "notes.txt"), "--task", "bridge_maze"],
        "missing": [str(tmp_path / "nowhere.npz"), "--task", "bridge_maze"],
        "ground_truth_task": [str(checkpoint), "--task", "point_reach"],
        "unknown_task": [str(checkpoint), "--task", "bridge_mace"],
        "dims_outside": [str(checkpoint), "--task", "bridge_maze", "--dims", "3", "10"],
        "dims_twice": [str(checkpoint), "--task", "bridge_maze", "--dims", "3", "3"],
    }[case]
    output = tmp_path / "map.png"
    assert main(["model", *args, "--output", str(output)]) == EXIT_BAD_INPUT
    assert message in capsys.readouterr().err
    assert not output.exists()
