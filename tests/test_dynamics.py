"""Probabilistic ensembles, PETSUS and RAZER's costs against their definitions (thesis chapter 5, App. D)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from workers.dynamics.benchmark import measure_ensemble_throughput
from workers.dynamics.costs import (
    RazerSettings,
    SafetyBox,
    box_violation_probability,
    moment_matched_violation,
)
from workers.dynamics.ensemble import (
    DynamicsEnsemble,
    EnsembleConfig,
    Transitions,
    epoch_orders,
    gaussian_nll,
    soft_bound_logvar,
)
from workers.dynamics.evaluator import EnsembleEvaluator
from workers.dynamics.propagation import petsus_propagate

torch.set_num_threads(1)

TINY = dict(ensemble_size=5, hidden_layers=2, hidden_size=16, epochs=2, batch_size=64)


def tiny_model(obs_dim: int = 3, action_dim: int = 2, seed: int = 0, **overrides) -> DynamicsEnsemble:
    return DynamicsEnsemble(obs_dim, action_dim, EnsembleConfig.preset("small", **(TINY | overrides)), seed=seed)


def make_identical(model: DynamicsEnsemble) -> DynamicsEnsemble:
    """Every member becomes a copy of member 0."""
    with torch.no_grad():
        for p in [*model.net.weights, *model.net.biases]:
            p.copy_(p[:1].expand_as(p))
    return model


def make_deterministic(model: DynamicsEnsemble) -> DynamicsEnsemble:
    """Variance bounds so low that sampling noise vanishes (std about exp(-30))."""
    model.net.min_logvar.fill_(-62.0)
    model.net.max_logvar.fill_(-60.0)
    return model


def toy_data(n: int, noise: float, seed: int = 0) -> Transitions:
    rng = np.random.default_rng(seed)
    obs = rng.uniform(-2, 2, size=(n, 3))
    act = rng.uniform(-1, 1, size=(n, 2))
    delta = 0.3 * np.sin(obs) + 0.2 * act[:, [0, 1, 0]]
    return Transitions(obs, act, obs + delta + noise * rng.normal(size=(n, 3)))


# ------------------------------------------------------------------ model
def test_nll_equals_torch_gaussian_nll_loss():
    """Eq. 19 loss = torch.nn.GaussianNLLLoss(full=False, reduction='mean') (no 0.5 log 2 pi)."""
    generator = torch.Generator().manual_seed(0)
    mean, target = torch.randn(5, 64, 3, generator=generator), torch.randn(5, 64, 3, generator=generator)
    logvar = soft_bound_logvar(3 * torch.randn(5, 64, 3, generator=generator), torch.tensor(-10.0), torch.tensor(4.0))
    reference = torch.nn.GaussianNLLLoss(full=False, reduction="mean")(mean, target, logvar.exp())
    assert gaussian_nll(mean, logvar, target).item() == pytest.approx(reference.item(), rel=1e-6)
    full = torch.nn.GaussianNLLLoss(full=True, reduction="mean")(mean, target, logvar.exp())
    assert (full - gaussian_nll(mean, logvar, target)).item() == pytest.approx(0.5 * math.log(2 * math.pi), rel=1e-5)


@pytest.mark.parametrize("low, high", [(-10.0, 4.0), (-6.0, 4.0), (-1.0, 0.5)])
def test_soft_bounds_are_never_exceeded(low, high):
    raw = torch.tensor([-math.inf, -1e30, -1e6, low - 1, low, 0.5 * (low + high), high, high + 1, 1e6, 1e30, math.inf])
    logvar = soft_bound_logvar(raw, torch.tensor(low), torch.tensor(high))
    assert torch.all(logvar >= low) and torch.all(logvar <= high)
    # Soft, not hard: a raw value at a bound is pulled inside by softplus(0) = log 2, and the map stays monotone.
    at_edges = soft_bound_logvar(torch.tensor([low, high]), torch.tensor(low), torch.tensor(high))
    margin = min(0.5, 0.1 * (high - low))
    assert at_edges[0] > low + margin and at_edges[1] < high - margin
    assert torch.all(logvar[1:] >= logvar[:-1])


def test_model_variance_bounds_hold_for_extreme_inputs():
    model = tiny_model(min_logvar=-6.0, max_logvar=4.0)
    with torch.no_grad():
        model.net.weights[-1].mul_(1e4)  # push the raw log-variances far outside the bounds
    inputs = torch.cat([torch.zeros(1, 4, 5), 1e6 * torch.randn(4, 4, 5, generator=torch.Generator().manual_seed(1))])
    _, logvar = model.predict(inputs)
    assert torch.isfinite(logvar).all()
    assert logvar.min() >= -6.0 and logvar.max() <= 4.0
    assert logvar.max() == 4.0 or logvar.min() == -6.0  # the inputs really did saturate


def test_members_are_one_batched_computation_matching_separate_mlps():
    """Member k of the batched net equals an MLP built from slice k of every (K, in, out) weight."""
    model = tiny_model()
    x = torch.randn(5, 7, 5, generator=torch.Generator().manual_seed(2))
    mean, logvar = model.predict(x)
    net = model.net
    for k in range(5):
        h = (x[k] - net.input_mean) / net.input_std
        for i, (w, b) in enumerate(zip(net.weights, net.biases)):
            h = h @ w[k] + b[k]
            if i < len(net.weights) - 1:
                h = torch.nn.functional.silu(h)
        torch.testing.assert_close(mean[k], h[:, :3])
        torch.testing.assert_close(logvar[k], soft_bound_logvar(h[:, 3:], net.min_logvar, net.max_logvar))


def test_ensemble_fits_a_known_function_and_its_noise():
    data, held_out = toy_data(3000, noise=0.1, seed=0), toy_data(500, noise=0.1, seed=1)
    model = tiny_model(hidden_size=48, epochs=25, batch_size=128, lr=3e-3)
    before_nll, before_mse, *_ = model.evaluate(held_out)
    stats = model.train(data, held_out)
    # use_input_normalization (Table 13): inputs are standardised with the training data's moments.
    inputs = np.concatenate([data.observations, data.actions], axis=1)
    np.testing.assert_allclose(model.net.input_mean.numpy(), inputs.mean(0), atol=1e-5)
    np.testing.assert_allclose(model.net.input_std.numpy(), inputs.std(0), rtol=1e-4)
    assert stats.held_out_nll < before_nll - 1.0
    assert stats.held_out_mse < 0.2 * before_mse
    assert stats.held_out_mse < 0.03  # noise variance 0.01 plus a little model error
    # Aleatoric: the predicted variance recovers the noise variance 0.01.
    inputs = torch.as_tensor(np.concatenate([held_out.observations, held_out.actions], 1), dtype=torch.float32)
    _, logvar = model.predict(inputs.expand(5, -1, -1))
    assert 0.004 < logvar.exp().mean().item() < 0.025
    assert stats.weights_version == 1 and stats.gradient_steps == 25 * math.ceil(3000 / 128)
    assert stats.at_min_logvar == 0.0 and stats.at_max_logvar == 0.0


def test_epochs_given_to_a_training_call_override_the_configured_ones_even_zero():
    data = toy_data(200, noise=0.05)
    batches = -(-200 // tiny_model().config.batch_size)  # per epoch
    assert tiny_model(epochs=3).train(data, epochs=1).gradient_steps == batches
    assert tiny_model(epochs=3).train(data, epochs=0).gradient_steps == 0  # not the configured 3
    assert tiny_model(epochs=3).train(data).gradient_steps == 3 * batches


def test_warm_start_continues_and_from_scratch_restarts():
    data = toy_data(1000, noise=0.05)
    warm = tiny_model(epochs=10)
    warm.train(data)
    scratch = DynamicsEnsemble.from_state(*warm.export_state())
    warm_stats = warm.train(data, epochs=1)
    scratch_stats = scratch.train(data, epochs=1, from_scratch=True)
    assert scratch_stats.from_scratch and warm_stats.weights_version == scratch_stats.weights_version == 2
    assert warm_stats.train_nll < scratch_stats.train_nll - 0.5
    by_config = DynamicsEnsemble.from_state(*warm.export_state())
    by_config.config = by_config.config.model_copy(update={"retrain_from_scratch": True})
    assert by_config.train(data, epochs=1).from_scratch


@pytest.mark.parametrize("scale", [0.5, 1.0])
def test_initial_weights_are_a_truncated_normal_of_the_configured_std(scale):
    """std = init_std_scale / sqrt(fan_in), cut at 2 std (a normal cut at +-2 has 0.880 of its std)."""
    model = DynamicsEnsemble(10, 2, EnsembleConfig.preset("bridge_maze", init_std_scale=scale), seed=0)
    for weight in model.net.weights:
        nominal = scale / math.sqrt(weight.shape[1])
        assert weight.abs().max().item() <= 2 * nominal
        assert abs(weight.std().item() / (0.880 * nominal) - 1) < 0.05
    assert all(not bias.any() for bias in model.net.biases)


@pytest.mark.parametrize("keep_function", [True, False])
def test_a_warm_started_model_keeps_its_predictions_when_the_normalisation_moves(keep_function, monkeypatch):
    """New data with another mean and scale refit the normaliser; with keep_function every member predicts the
    same for every raw input right after the refit (before any gradient step); without it, it does not."""
    model = tiny_model(epochs=5, keep_function=keep_function)
    model.train(toy_data(500, noise=0.05))
    probe = torch.as_tensor(np.random.default_rng(1).uniform(-2, 2, size=(40, 5)), dtype=torch.float32)
    before = model.predict(probe.expand(5, -1, -1))
    base = toy_data(500, noise=0.05, seed=2)
    moved = Transitions(base.observations * 2 + 1, base.actions * 0.5, base.next_observations * 2 + 1)
    refitted = {}

    def predictions_before_the_first_step():
        refitted.setdefault("out", model.predict(probe.expand(5, -1, -1)))

    monkeypatch.setattr(model.optimizer, "step", predictions_before_the_first_step)
    model.train(moved, epochs=1)
    assert not torch.allclose(model.net.input_mean[:3], torch.zeros(3), atol=0.5)  # the normalisation did move
    same = all(torch.allclose(a, b, atol=1e-4) for a, b in zip(before, refitted["out"]))
    assert same == keep_function


@pytest.mark.parametrize("carry_moments", [True, False])
def test_a_rescaled_normalisation_carries_adams_moments_into_the_new_coordinates(carry_moments, monkeypatch):
    """Inputs spread twice as wide about the same mean: every member's folded first layer gets half the gradient,
    and Adam's moments scale with it (carried, they stand to the new gradients as to the old ones)."""
    import workers.dynamics.ensemble as ensemble

    if not carry_moments:
        monkeypatch.setattr(ensemble, "rescale_inputs_of", lambda weight, scale, optimiser: weight.data.mul_(scale))
    model = tiny_model(epochs=3, grad_norm=None)
    data = toy_data(300, noise=0.05)
    model.train(data)
    inputs, targets = model._inputs_targets(data)
    mean = inputs.mean(dim=0)
    wider = mean + (inputs - mean) * 2.0
    weight = model.net.weights[0]

    def gradient_and_moments():
        model.optimizer.zero_grad(set_to_none=True)
        predicted, logvar = model.net(wider.expand(model.ensemble_size, -1, -1))
        gaussian_nll(predicted, logvar, targets).backward()
        state = model.optimizer.state[weight]
        return weight.grad.clone(), state["exp_avg"].clone(), state["exp_avg_sq"].clone()

    gradient, first_moment, second_moment = gradient_and_moments()
    model.fit_normalizer(Transitions(wider[:, :3].numpy(), wider[:, 3:].numpy(), data.next_observations), True)
    new_gradient, new_first_moment, new_second_moment = gradient_and_moments()
    torch.testing.assert_close(new_gradient, gradient / 2, rtol=1e-3, atol=1e-7)
    carried = torch.allclose(new_first_moment / new_gradient, first_moment / gradient, rtol=1e-3)
    assert carried == carry_moments
    assert torch.allclose(new_second_moment / new_gradient**2, second_moment / gradient**2, rtol=1e-3) == carried


def test_gradient_clipping_is_per_member():
    model = tiny_model(grad_norm=2.0)
    scales = torch.tensor([0.1, 1.0, 10.0, 100.0, 0.0])
    for p in [*model.net.weights, *model.net.biases]:
        p.grad = torch.ones_like(p) * scales.view(-1, *([1] * (p.dim() - 1)))
    before = torch.stack([p.grad.square().flatten(1).sum(1) for p in model.net.weights]).sum(0)
    before = (before + torch.stack([p.grad.square().flatten(1).sum(1) for p in model.net.biases]).sum(0)).sqrt()
    model._clip_per_member()
    after = torch.stack([p.grad.square().flatten(1).sum(1) for p in [*model.net.weights, *model.net.biases]])
    after = after.sum(0).sqrt()
    torch.testing.assert_close(after, torch.minimum(before, torch.tensor(2.0)), rtol=1e-4, atol=1e-6)


def test_checkpoint_round_trip_without_pickle(tmp_path):
    data = toy_data(600, noise=0.05)
    model = tiny_model()
    model.train(data)
    path = tmp_path / "ensemble.npz"
    model.save(path)
    with np.load(path, allow_pickle=False) as archive:  # loadable without unpickling
        assert all(archive[name].dtype != object for name in archive.files)
    restored = DynamicsEnsemble.load(path)
    assert restored.weights_version == 1 and restored.config == model.config
    x = torch.randn(5, 9, 5)
    torch.testing.assert_close(restored.predict(x), model.predict(x), rtol=0, atol=0)
    # The Adam moments come along: continued training is identical.
    a, b = model.train(data, seed=4), restored.train(data, seed=4)
    assert a.train_nll == b.train_nll and b.weights_version == 2


def test_checkpoint_of_another_shape_is_refused():
    arrays, meta = tiny_model().export_state()
    with pytest.raises(ValueError, match="another shape"):
        tiny_model(hidden_size=8).import_state(arrays, meta)


# ------------------------------------------------------------- propagation
def test_ts1_keeps_each_members_load_balanced():
    """P = 10, K = 5: every member predicts exactly 2 particles of every sequence at every step."""
    model = tiny_model()
    actions = torch.zeros(40, 6, 2)
    prop = petsus_propagate(model, torch.zeros(3), actions, 10, "none", torch.Generator().manual_seed(0))
    counts = torch.nn.functional.one_hot(prop.members, 5).sum(dim=1)  # (N, h, K)
    assert torch.all(counts == 2)
    # ... and particles really are re-assigned at every step (TS1, not TS-infinity).
    changed = (prop.members[:, :, 1:] != prop.members[:, :, :-1]).float().mean().item()
    assert changed == pytest.approx(0.8, abs=0.1)


def test_ts1_balance_when_particles_are_not_a_multiple():
    model = tiny_model()
    prop = petsus_propagate(model, torch.zeros(3), torch.zeros(200, 3, 2), 7, "none", torch.Generator().manual_seed(0))
    counts = torch.nn.functional.one_hot(prop.members, 5).sum(dim=1)
    assert counts.min() == 1 and counts.max() == 2
    # The two surplus particles land on every member equally often.
    assert (counts == 2).float().mean(dim=(0, 1)).tolist() == pytest.approx([0.4] * 5, abs=0.06)


@pytest.mark.parametrize("particles", [5, 7, 10])  # one row per member and sequence, unused slots, two rows
def test_zero_variance_is_a_deterministic_rollout_of_the_assigned_members(particles):
    model = make_deterministic(tiny_model())
    generator = torch.Generator().manual_seed(3)
    start, actions = torch.randn(3, generator=generator), torch.rand(3, 4, 2, generator=generator) * 2 - 1
    prop = petsus_propagate(model, start, actions, particles, "per_member", generator)
    net = model.net
    for n in range(3):
        for p in range(particles):
            s = start.clone()
            for t in range(4):
                k = prop.members[n, p, t]
                mu, _ = model.predict(torch.cat([s, actions[n, t]]).view(1, 1, -1).expand(5, 1, -1))
                s = s + mu[k, 0]
                torch.testing.assert_close(prop.particles[n, p, t], s, atol=1e-5, rtol=1e-5)
        for k in range(5):  # each member's own mean trajectory
            s = start.clone()
            for t in range(4):
                mu, _ = net(torch.cat([s, actions[n, t]]).view(1, 1, -1).expand(5, 1, -1))
                s = s + mu[k, 0].detach()
                torch.testing.assert_close(prop.means[k, n, t], s, atol=1e-5, rtol=1e-5)


def test_identical_members_have_zero_epistemic_variance():
    generator = torch.Generator().manual_seed(0)
    actions = torch.rand(4, 5, 2, generator=generator) * 2 - 1
    for mode in ("per_member", "shared"):
        distinct = petsus_propagate(tiny_model(), torch.ones(3), actions, 5, mode, generator)
        assert distinct.var_epistemic.min() > 0
        same = petsus_propagate(make_identical(tiny_model()), torch.ones(3), actions, 5, mode, generator)
        assert same.var_epistemic.abs().max() < 1e-10
        assert same.var_aleatoric.min() > 0  # the noise is still there


def test_epistemic_variance_is_eq_24_at_the_mean_state():
    """Step 1: Var_k[mu_k(s0, a0)] + Var_k[Sigma_k(s0, a0)], population variance over members."""
    model = tiny_model()
    start, actions = torch.randn(3), torch.rand(2, 3, 2)
    prop = petsus_propagate(model, start, actions, 5, "shared", torch.Generator().manual_seed(0))
    mu, logvar = model.predict(torch.cat([start.expand(2, 3), actions[:, 0]], 1).expand(5, -1, -1))
    expected = mu.var(0, unbiased=False) + logvar.exp().var(0, unbiased=False)
    torch.testing.assert_close(prop.var_epistemic[:, 0], expected)
    # Shared mean: the next mean state is the members' mean prediction.
    torch.testing.assert_close(prop.means[0, :, 0], start + mu.mean(0))


def test_epistemic_variance_of_the_means_alone_leaves_out_the_variance_of_variances():
    model = tiny_model()
    start, actions = torch.randn(3), torch.rand(2, 3, 2)
    prop = petsus_propagate(model, start, actions, 5, "shared", torch.Generator().manual_seed(0), "means")
    mu, _ = model.predict(torch.cat([start.expand(2, 3), actions[:, 0]], 1).expand(5, -1, -1))
    torch.testing.assert_close(prop.var_epistemic[:, 0], mu.var(0, unbiased=False))
    # The evaluator passes the setting on: u_E (sum over steps and dimensions of sqrt Var_E) is that of the
    # means alone, below the default's.
    u_e = {
        terms: EnsembleEvaluator(
            model, lambda s, a, s2: s2[:, 0], RazerSettings(epistemic_weight=0.05, epistemic_terms=terms), particles=5
        ).costs(start.numpy(), actions.numpy())[1]["u_E"]
        for terms in ("means_and_variances", "means")
    }
    per_member = petsus_propagate(model, start, actions, 5, "per_member", epistemic_terms="means")
    np.testing.assert_allclose(u_e["means"], per_member.var_epistemic.sqrt().sum((1, 2)).numpy(), rtol=1e-5)
    assert np.all(u_e["means"] < u_e["means_and_variances"])


def test_aleatoric_variance_is_eq_22():
    """Step 1 (all particles at s0): the mean over members of Sigma_k(s0, a0)."""
    model = tiny_model()
    start, actions = torch.randn(3), torch.rand(2, 3, 2)
    prop = petsus_propagate(model, start, actions, 10, "none", torch.Generator().manual_seed(0))
    _, logvar = model.predict(torch.cat([start.expand(2, 3), actions[:, 0]], 1).expand(5, -1, -1))
    torch.testing.assert_close(prop.var_aleatoric[:, 0], logvar.exp().mean(0))


# ------------------------------------------------------------------ costs
def test_box_violation_probability_matches_monte_carlo():
    """Eq. 34 in closed form against sampling a diagonal Gaussian."""
    mean, std = torch.tensor([0.2, -0.5, 1.0]), torch.tensor([0.5, 1.5, 0.3])
    box = SafetyBox(dims=(0, 1), low=(0.0, None), high=(0.6, -0.2))
    closed = box_violation_probability(mean, std, box).item()
    samples = mean + std * torch.randn(400_000, 3, generator=torch.Generator().manual_seed(0))
    inside = ((samples[:, 0] >= 0.0) & (samples[:, 0] <= 0.6) & (samples[:, 1] <= -0.2)).float().mean().item()
    assert closed == pytest.approx(inside, abs=0.003)
    assert 0.1 < closed < 0.9


def test_moment_matched_violation_uses_the_particles_moments():
    generator = torch.Generator().manual_seed(1)
    particles = torch.tensor([1.0, 0.0]) + torch.tensor([0.5, 1.0]) * torch.randn(2, 4000, 3, 2, generator=generator)
    box = SafetyBox(dims=(0,), low=(1.3,), high=(None,))
    probability = moment_matched_violation(particles, (box,))
    assert probability.shape == (2, 3)
    assert probability.mean().item() == pytest.approx(1 - torch.special.ndtr(torch.tensor(0.6)).item(), abs=0.02)
    assert torch.all(moment_matched_violation(particles.mean(1, keepdim=True), (box,)) == 0)  # one particle: no spread


def test_the_moment_matched_spread_of_a_few_particles_is_the_unbiased_sample_variance():
    """Five particles at -2 ... 2 have sample variance 2.5 (population variance 2): a ceiling at 2.5 is crossed
    with probability 1 - Phi(2.5 / sqrt(2.5)) = 0.057, above a delta of 0.05, where the population variance
    would read 0.039, below it."""
    particles = torch.tensor([-2.0, -1.0, 0.0, 1.0, 2.0]).view(1, 5, 1, 1)
    box = SafetyBox(dims=(0,), low=(2.5,), high=(None,))
    probability = moment_matched_violation(particles, (box,)).item()
    assert probability == pytest.approx(1 - torch.special.ndtr(torch.tensor(2.5 / math.sqrt(2.5))).item(), rel=1e-5)
    assert probability > 0.05


def test_sequence_cost_terms_and_total():
    model = tiny_model()
    box = SafetyBox(dims=(0,), low=(-100.0,), high=(100.0,))  # always violated
    settings = RazerSettings(
        aleatoric_weight=2.0, epistemic_weight=0.5, safety_weight=7.0, safety_delta=0.5, safety_boxes=(box,)
    )
    evaluator = EnsembleEvaluator(model, lambda s, a, s2: s2[:, 0] - s[:, 0], settings, particles=5, seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (6, 4, 2))
    total, parts = evaluator.costs(np.zeros(3), actions)
    assert total.shape == (6,) and set(parts) == {"c", "c_A", "c_E", "c_S", "u_A", "u_E", "violation_steps"}
    np.testing.assert_allclose(total, parts["c"] + parts["c_A"] + parts["c_E"] + parts["c_S"], rtol=1e-6)
    np.testing.assert_allclose(parts["c_A"], 2.0 * parts["u_A"], rtol=1e-6)
    np.testing.assert_allclose(parts["c_E"], -0.5 * parts["u_E"], rtol=1e-6)
    np.testing.assert_allclose(parts["c_S"], 7.0 * 4)
    assert np.all(parts["u_A"] > 0) and np.all(parts["u_E"] > 0)
    # The task cost telescopes over the horizon: it pairs each particle's state with its successor.
    evaluator.reseed(5)
    prop = evaluator.propagate(np.zeros(3), actions)
    evaluator.reseed(5)
    np.testing.assert_allclose(
        evaluator.costs(np.zeros(3), actions)[1]["c"], prop.particles[:, :, -1, 0].mean(1), atol=1e-5
    )


@pytest.mark.parametrize("mode", ["per_member", "shared"])
def test_aleatoric_variance_at_the_mean_states_is_the_members_variance_there(mode):
    """aleatoric_states="means": Var_A(t+1) is the mean over members of Sigma_k at the propagated mean states
    (each member's own with per_member), not at the particles; the particles and means themselves are unchanged."""
    model = tiny_model()
    start, actions = torch.randn(3), torch.rand(2, 4, 2) * 2 - 1
    def propagate(**reading):
        return petsus_propagate(model, start, actions, 10, mode, torch.Generator().manual_seed(0), **reading)

    at_means, at_particles = propagate(aleatoric_states="means"), propagate()
    torch.testing.assert_close(at_means.particles, at_particles.particles, rtol=0, atol=0)
    torch.testing.assert_close(at_means.means, at_particles.means, rtol=0, atol=0)
    # Step 1: every particle and mean state is s0, so both readings agree there ...
    torch.testing.assert_close(at_means.var_aleatoric[:, 0], at_particles.var_aleatoric[:, 0])
    for t in range(1, 4):
        states = at_means.means[:, :, t - 1].expand(5, -1, -1)  # (K, N, d): member k at its (or the shared) mean
        _, logvar = model.predict(torch.cat([states, actions[:, t].expand(5, -1, -1)], dim=-1))
        torch.testing.assert_close(at_means.var_aleatoric[:, t], logvar.exp().mean(0))
    # ... and after it they part: the particles have spread away from the mean states.
    assert (at_means.var_aleatoric[:, 1:] - at_particles.var_aleatoric[:, 1:]).abs().max() > 1e-3


def test_aleatoric_variance_at_the_mean_states_needs_mean_propagation():
    with pytest.raises(ValueError, match="needs mean propagation"):
        petsus_propagate(tiny_model(), torch.zeros(3), torch.zeros(2, 3, 2), 5, "none", aleatoric_states="means")
    with pytest.raises(ValidationError, match="needs mean propagation"):
        RazerSettings(aleatoric_weight=0.5, aleatoric_states="means", mean_propagation="none")


def test_aleatoric_penalty_at_the_mean_states_propagates_them_without_an_epistemic_weight():
    """With w_A only, Var_A read at the means needs the mean states the evaluator otherwise skips; the particles'
    draws do not depend on them, so the task cost is the same and only c_A changes."""
    model = tiny_model()
    actions = np.random.default_rng(2).uniform(-1, 1, (6, 4, 2))

    def evaluate(states):
        settings = RazerSettings(aleatoric_weight=2.0, aleatoric_states=states)
        return EnsembleEvaluator(model, lambda s, a, s2: s2[:, 0], settings, particles=5, seed=3)

    at_means, at_particles = evaluate("means"), evaluate("particles")
    assert at_means.propagate(np.zeros(3), actions).means is not None
    assert at_particles.propagate(np.zeros(3), actions).means is None
    at_means.reseed(3)
    at_particles.reseed(3)
    (_, means), (_, particles) = at_means.costs(np.zeros(3), actions), at_particles.costs(np.zeros(3), actions)
    np.testing.assert_array_equal(means["c"], particles["c"])
    expected = petsus_propagate(
        model, torch.zeros(3), torch.as_tensor(actions, dtype=torch.float32), 5, "per_member",
        torch.Generator().manual_seed(3), aleatoric_states="means",
    ).var_aleatoric.sqrt().sum((1, 2))  # fmt: skip
    np.testing.assert_allclose(means["c_A"], 2.0 * expected.numpy(), rtol=1e-5)
    assert np.abs(means["c_A"] - particles["c_A"]).max() > 1e-3


def test_without_an_epistemic_weight_no_mean_states_are_propagated_and_the_costs_stay_the_same():
    """RAZER with w_A only: the mean states would feed Var_E alone, so they are not propagated (half the rows per
    member with one particle per member), and every cost is what it is with mean propagation switched off."""
    model = tiny_model()
    actions = np.random.default_rng(1).uniform(-1, 1, (6, 4, 2))

    def evaluate(**razer):
        settings = RazerSettings(aleatoric_weight=2.0, **razer)
        return EnsembleEvaluator(model, lambda s, a, s2: s2[:, 0], settings, particles=5, seed=3)

    razer = evaluate(mean_propagation="per_member")
    assert razer.propagate(np.zeros(3), actions).means is None
    razer.reseed(3)
    total, parts = razer.costs(np.zeros(3), actions)
    reference_total, reference_parts = evaluate(mean_propagation="none").costs(np.zeros(3), actions)
    np.testing.assert_array_equal(total, reference_total)
    np.testing.assert_array_equal(parts["c_A"], reference_parts["c_A"])
    assert "u_E" not in parts
    assert evaluate(epistemic_weight=0.1).propagate(np.zeros(3), actions).means is not None


def test_uncertainty_reductions():
    from workers.dynamics.costs import reduce_uncertainty

    variance = torch.tensor([[4.0, 9.0, 0.0]])
    assert reduce_uncertainty(variance, "sum_sqrt").item() == 5.0
    assert reduce_uncertainty(variance, "sqrt_sum").item() == pytest.approx(math.sqrt(13))
    assert reduce_uncertainty(variance, "mean_sqrt").item() == pytest.approx(5 / 3)
    assert reduce_uncertainty(variance, "sum_sqrt", dims=(1,)).item() == 3.0


def test_pets_has_only_the_task_cost_and_no_mean_propagation():
    model = tiny_model()
    evaluator = EnsembleEvaluator(model, lambda s, a, s2: s2.square().sum(-1), RazerSettings.pets(), particles=5)
    assert evaluator.propagate(np.zeros(3), np.zeros((2, 3, 2))).means is None
    total, parts = evaluator.costs(np.zeros(3), np.zeros((2, 3, 2)))
    assert "u_E" not in parts
    np.testing.assert_array_equal(total, parts["c"])


def test_evaluator_is_reproducible_per_seed():
    model = tiny_model()
    actions = np.random.default_rng(0).uniform(-1, 1, (8, 5, 2))
    cost = lambda s, a, s2: s2.square().sum(-1)  # noqa: E731
    a = EnsembleEvaluator(model, cost, RazerSettings(aleatoric_weight=1.0), particles=5, seed=3).costs(
        np.ones(3), actions
    )
    b = EnsembleEvaluator(model, cost, RazerSettings(aleatoric_weight=1.0), particles=5, seed=3).costs(
        np.ones(3), actions
    )
    c = EnsembleEvaluator(model, cost, RazerSettings(aleatoric_weight=1.0), particles=5, seed=4).costs(
        np.ones(3), actions
    )
    np.testing.assert_array_equal(a[0], b[0])
    assert not np.array_equal(a[0], c[0])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(aleatoric_weight=-1.0), "greater than or equal to 0"),
        (dict(epistemic_weight=-0.05), "greater than or equal to 0"),
        (dict(safety_weight=-1.0), "greater than or equal to 0"),
        (dict(safety_delta=0.0), "greater than 0"),
        (dict(safety_delta=1.0), "less than 1"),
        (dict(epistemic_weight=0.05, mean_propagation="none"), "needs mean propagation"),
        (dict(safety_weight=10.0), "needs at least one safety box"),
        (dict(mean_propagation="sampled"), "per_member"),
        (dict(aleatoric_weigth=1.0), "Extra inputs"),
    ],
)
def test_settings_validation(kwargs, message):
    with pytest.raises(ValidationError, match=message):
        RazerSettings(**kwargs)


@pytest.mark.parametrize("bootstrap", [False, True])
def test_each_member_trains_on_its_own_order_and_a_bootstrap_is_drawn_once_per_call(bootstrap):
    """PETS' bootstrap: one resample with replacement per member for the whole training call, reshuffled every
    epoch (about 63% distinct rows); without it every member sees all rows, each epoch in its own order."""
    n, members = 400, 3
    orders = list(epoch_orders(n, members, 5, bootstrap, torch.Generator().manual_seed(0)))
    assert len(orders) == 5 and all(order.shape == (members, n) for order in orders)
    for member in range(members):
        epochs = [order[member].sort().values for order in orders]
        assert all(torch.equal(epoch, epochs[0]) for epoch in epochs)  # the same data every epoch
        distinct = len(set(epochs[0].tolist()))
        assert (0.55 * n < distinct < 0.72 * n) if bootstrap else distinct == n
    assert not torch.equal(orders[0][0], orders[1][0]) and not torch.equal(orders[0][0], orders[0][1])


def test_safety_box_and_ensemble_config_validation():
    with pytest.raises(ValidationError, match="not below high"):
        SafetyBox(dims=(0,), low=(1.0,), high=(0.5,))
    with pytest.raises(ValidationError, match="one low and one high edge"):
        SafetyBox(dims=(0, 1), low=(1.0,), high=(None,))
    with pytest.raises(ValidationError, match="listed twice"):  # eq. 34's product is over distinct dimensions
        SafetyBox(dims=(0, 0), low=(0.3, None), high=(None, 0.5))
    with pytest.raises(ValidationError, match="neither edge"):
        SafetyBox(dims=(0, 1), low=(0.3, None), high=(None, None))
    with pytest.raises(ValidationError, match="must be below max_logvar"):
        EnsembleConfig(min_logvar=4.0, max_logvar=-10.0)
    with pytest.raises(ValueError, match="unknown ensemble preset"):
        EnsembleConfig.preset("bridgemaze")
    with pytest.raises(ValueError, match="observation dimension 7"):
        EnsembleEvaluator(tiny_model(), lambda s, a, s2: s2[:, 0], RazerSettings(uncertainty_dims=(7,)))


def test_presets_follow_tables_13_and_14():
    bridge, cheetah = EnsembleConfig.preset("bridge_maze"), EnsembleConfig.preset("noisy_halfcheetah")
    assert (bridge.hidden_layers, bridge.hidden_size, bridge.ensemble_size, bridge.activation) == (6, 400, 5, "silu")
    assert (bridge.lr, bridge.batch_size, bridge.weight_decay, bridge.grad_norm, bridge.epochs) == (
        2e-3,
        512,
        1e-5,
        2.0,
        25,
    )
    assert (bridge.min_logvar, bridge.max_logvar) == (-10.0, 4.0)
    assert (cheetah.hidden_layers, cheetah.hidden_size, cheetah.lr, cheetah.batch_size) == (4, 200, 2e-4, 256)
    assert (cheetah.weight_decay, cheetah.epochs, cheetah.min_logvar, cheetah.grad_norm) == (3e-5, 50, -6.0, None)


def test_throughput_measurement_runs_the_rows_it_counts(monkeypatch):
    """No figure is asserted (shared two-core machine): it measures, and the evaluator it times runs as many rows
    per model step as the dense side multiplies (particles and mean states)."""
    from workers.dynamics.ensemble import DynamicsEnsemble

    batches = set()
    predict = DynamicsEnsemble.predict

    def counting(self, inputs):
        batches.add(inputs.shape[0] * inputs.shape[1])
        return predict(self, inputs)

    monkeypatch.setattr(DynamicsEnsemble, "predict", counting)
    report = measure_ensemble_throughput(
        EnsembleConfig.preset("small", hidden_size=16), 4, 2, sequences=8, particles=5, horizon=3, repeats=1
    )
    assert report.dense_flops_per_second > 0 and report.particle_steps_per_second > 0 and report.ratio > 0
    assert batches == {report.rows_per_model_step} == {5 * (8 + 8)}


def test_throughput_measurement_alternates_and_keeps_each_sides_best(monkeypatch):
    """Scripted readings, no timing: the rounds interleave dense and evaluator, and each side's best counts."""
    import workers.dynamics.benchmark as benchmark

    calls = []
    dense_readings, evaluator_readings = iter([3.0, 5.0, 4.0]), iter([20.0, 10.0, 30.0])

    def dense(*args, **kwargs):
        calls.append("dense")
        return next(dense_readings)

    def evaluator(*args, **kwargs):
        calls.append("evaluator")
        return next(evaluator_readings)

    monkeypatch.setattr(benchmark, "dense_matmul_flops_per_second", dense)
    monkeypatch.setattr(benchmark, "ensemble_evaluator_particle_steps_per_second", evaluator)
    report = measure_ensemble_throughput(EnsembleConfig.preset("small", hidden_size=16), 4, 2, rounds=3)
    assert calls == ["dense", "evaluator"] * 3
    assert report.dense_flops_per_second == 5.0 and report.particle_steps_per_second == 30.0


def test_end_to_end_bridge_maze_model_plans_with_icem():
    """Random BridgeMaze data -> small ensemble -> RAZER evaluator -> one iCEM step (the service's path)."""
    from workers.planning import CEMPlanner, PlannerConfig
    from workers.tasks.bridge_maze import BridgeMaze

    task = BridgeMaze()
    env = task.make_env()
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(300):
        action = rng.uniform(-1, 1, task.action_dim)
        next_obs, _, terminated, truncated, _ = env.step(task.env_action(action))
        rows.append((obs, action, next_obs))
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
    data = Transitions(*(np.array(column) for column in zip(*rows)))
    model = DynamicsEnsemble(task.observation_dim, task.action_dim, EnsembleConfig.preset("small", epochs=3))
    stats = model.train(data)
    assert np.isfinite(stats.train_nll)
    settings = RazerSettings(aleatoric_weight=0.1, epistemic_weight=0.05)
    evaluator = EnsembleEvaluator(model, task.planning_cost, settings, particles=5, seed=0)
    config = PlannerConfig(budget=20, elites=5, horizon=5).resolved(task_beta=task.colored_noise_beta)
    result = CEMPlanner(config, task.action_dim, seed=0).plan(evaluator.cost_function(data.observations[0]))
    assert result.action.shape == (2,) and np.all(np.abs(result.action) <= 1) and np.isfinite(result.best_cost)


def test_propagated_states_stay_in_the_widened_data_range():
    """A model that extrapolates (here: it predicts delta = 2 s) is clamped to the data's range +- 25 %."""
    model = tiny_model(epochs=1)
    data = toy_data(200, noise=0.0)
    model.train(data)
    low = np.minimum(data.observations.min(0), data.next_observations.min(0))
    high = np.maximum(data.observations.max(0), data.next_observations.max(0))
    np.testing.assert_allclose(model.net.state_low.numpy(), low - 0.25 * (high - low), rtol=1e-5)
    np.testing.assert_allclose(model.net.state_high.numpy(), high + 0.25 * (high - low), rtol=1e-5)
    growing = make_deterministic(model)
    original = growing.net.forward

    def explode(inputs):  # delta = 2 s: states triple every step, without bound
        _, logvar = original(inputs)
        return 2.0 * inputs[..., :3], logvar

    growing.net.forward = explode
    start = torch.tensor([1.0, -1.0, 0.5])
    prop = petsus_propagate(growing, start, torch.zeros(2, 30, 2), particles=5, mean_propagation="per_member")
    assert torch.isfinite(prop.particles).all() and torch.isfinite(prop.var_epistemic).all()
    assert (prop.particles <= model.net.state_high + 1e-6).all() and (
        prop.particles >= model.net.state_low - 1e-6
    ).all()
    assert (prop.means <= model.net.state_high + 1e-6).all()
    unclamped = tiny_model(epochs=1, state_margin=None)
    unclamped.train(data)
    assert torch.isinf(unclamped.net.state_high).all()  # None: no clamp


@pytest.mark.parametrize("mean_propagation", ["per_member", "shared"])
def test_the_tasks_projection_moves_every_particle_and_mean_state(mean_propagation):
    """project (a task's project_states) is applied after each step, to the particles and the mean states."""
    model = tiny_model()
    start = torch.tensor([0.5, -0.5, 1.0])

    def onto_plane(states):  # the states' first dimension is pinned to 0
        return torch.cat([torch.zeros_like(states[..., :1]), states[..., 1:]], dim=-1)

    kwargs = dict(particles=5, mean_propagation=mean_propagation, generator=torch.Generator().manual_seed(0))
    free = petsus_propagate(model, start, torch.zeros(3, 6, 2), **kwargs)
    kwargs["generator"] = torch.Generator().manual_seed(0)
    projected = petsus_propagate(model, start, torch.zeros(3, 6, 2), project=onto_plane, **kwargs)
    assert (free.particles[..., 0] != 0).all() and (free.means[..., 0] != 0).all()
    assert (projected.particles[..., 0] == 0).all() and (projected.means[..., 0] == 0).all()
    # Later steps start from the projected states: the other dimensions differ from the free rollout's too.
    assert not torch.allclose(projected.particles[..., -1, 1:], free.particles[..., -1, 1:])


def test_model_episodes_plan_with_the_tasks_projection(monkeypatch):
    from workers.dynamics.episodes import run_model_episode
    from workers.planning import PlannerConfig
    from workers.tasks.bridge_maze import BridgeMaze

    task = BridgeMaze(episode_length=2)
    seen = []
    unit = task.project_states
    monkeypatch.setattr(task, "project_states", lambda states: seen.append(states.shape) or unit(states))
    model = tiny_model(task.observation_dim, task.action_dim)
    config = PlannerConfig(budget=10, elites=3, horizon=4).resolved(task_beta=task.colored_noise_beta)
    outcome = run_model_episode(task, task.make_env(), model, config, RazerSettings.pets(), particles=5, seed=0)
    assert outcome.metrics["steps"] == 2
    assert seen and all(shape[-1] == task.observation_dim for shape in seen)
