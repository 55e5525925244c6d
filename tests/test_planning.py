"""The CEM family against its definitions (thesis section 3.1-3.2, appendix B)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from workers.planning import CEMPlanner, PlannerConfig, colored_noise, truncated_normal
from workers.planning.icem import CostBatch, main_cost


# ------------------------------------------------------------------ noise
@pytest.mark.parametrize("beta", [0.0, 0.5, 1.0, 2.0, 3.0])
def test_colored_noise_has_power_law_spectrum(beta):
    """PSD ~ 1/f^beta (eq. 10): the fitted log-log slope of the periodogram is -beta."""
    noise = colored_noise(beta, (4000, 256), np.random.default_rng(0))
    psd = np.mean(np.abs(np.fft.rfft(noise, axis=-1)) ** 2, axis=0)
    frequencies = np.fft.rfftfreq(256)
    slope = np.polyfit(np.log(frequencies[1:-1]), np.log(psd[1:-1]), 1)[0]
    assert slope == pytest.approx(-beta, abs=0.1)


@pytest.mark.parametrize("beta", [0.0, 0.25, 0.5])
def test_colored_noise_is_standardised_over_long_sequences(beta):
    """C^beta(d, h) has zero mean and unit variance (section 3.2.1); exact for long, mildly colored series."""
    noise = colored_noise(beta, (400, 4096), np.random.default_rng(1))
    assert abs(noise.mean()) < 0.05
    assert noise.var() == pytest.approx(1.0, abs=0.03)


@pytest.mark.parametrize("beta, factor", [(0.0, 1.0), (0.25, 1.06), (1.0, 1.16), (2.0, 1.31), (3.0, 1.41)])
@pytest.mark.parametrize("length", [30, 31])
def test_colored_noise_variance_over_a_planning_horizon(beta, factor, length):
    """Over h = 30 steps the packaged normalisation leaves the DC term out (documented factor, release 2.1)."""
    noise = colored_noise(beta, (40000, length), np.random.default_rng(1), "2.1")
    assert np.abs(noise.mean(axis=0)).max() < 0.05
    assert noise.var(axis=0).mean() == pytest.approx(factor, rel=0.04)


def test_colored_noise_release_2_1_doubles_the_constant_term():
    """colorednoise 2.1 doubled the variance of the real DC (and Nyquist) coefficients; 1.1 did not."""
    new, old = (colored_noise(3.0, (40000, 30), np.random.default_rng(1), release) for release in ("2.1", "1.1"))
    assert new.mean(axis=1).var() == pytest.approx(2 * old.mean(axis=1).var(), rel=0.05)
    assert old.var(axis=0).mean() == pytest.approx(1.21, rel=0.04)
    with pytest.raises(ValueError, match="release"):
        colored_noise(3.0, (2, 30), np.random.default_rng(1), "2.2")


@pytest.mark.parametrize("release", ["1.1", "2.1"])
def test_beta_zero_is_white_noise_in_either_release(release):
    """Eq. 10-13 with beta = 0: a flat spectrum, i.e. independent steps; through release 1.1's transform each
    sequence's mean would have half the variance (0.5/30) and steps two apart a covariance of -0.034."""
    white = colored_noise(0.0, (40000, 30), np.random.default_rng(1), release)
    assert white.mean(axis=1).var() == pytest.approx(1 / 30, rel=0.05)
    assert abs(np.mean(white[:, :-2] * white[:, 2:])) < 0.005


def test_the_planner_samples_with_the_configured_noise_release():
    samples = {}
    for release in ("2.1", "1.1"):
        config = PlannerConfig(budget=50, horizon=30, noise_beta=3.0, noise_release=release).resolved(3.0)
        samples[release] = CEMPlanner(config, 2, seed=0)._sample(np.zeros((30, 2)), np.full((30, 2), 0.5), 2000)
    offsets = {release: values.mean(axis=1).var() for release, values in samples.items()}
    assert offsets["2.1"] > 1.5 * offsets["1.1"]


def test_colored_noise_correlation_grows_with_beta():
    lag_one = []
    for beta in (0.0, 1.0, 2.0, 3.0):
        x = colored_noise(beta, (2000, 30), np.random.default_rng(2))
        lag_one.append(np.mean(x[:, 1:] * x[:, :-1]))
    assert lag_one == sorted(lag_one) and lag_one[0] == pytest.approx(0.0, abs=0.02)


def test_truncated_normal_stays_in_bounds_and_matches_moments():
    rng = np.random.default_rng(3)
    mean, std = np.array([0.0, 0.9, -0.5]), np.array([0.2, 0.5, 1.0])
    samples = truncated_normal(mean, std, -1.0, 1.0, 50000, rng)
    assert samples.min() >= -1.0 and samples.max() <= 1.0
    assert samples[:, 0].mean() == pytest.approx(0.0, abs=0.01)
    assert samples[:, 0].std() == pytest.approx(0.2, abs=0.01)  # barely truncated


# ---------------------------------------------------------------- budgets
# Table 4 of the thesis, written out: budget -> (iterations, initial N) for iCEM and for the CEM baselines.
TABLE_4 = {
    50: ((2, 25), (2, 25)), 70: ((2, 40), (2, 35)), 100: ((3, 40), (2, 50)), 150: ((3, 60), (2, 75)),
    200: ((4, 65), (3, 66)), 250: ((4, 85), (3, 83)), 300: ((4, 100), (3, 100)), 400: ((5, 120), (4, 100)),
    500: ((5, 150), (4, 125)), 1000: ((6, 270), (4, 250)), 2000: ((8, 480), (6, 333)), 4000: ((10, 900), (8, 500)),
}  # fmt: skip


@pytest.mark.parametrize("budget", sorted(TABLE_4))
def test_budget_table_4(budget):
    icem = PlannerConfig(algorithm="icem", budget=budget).resolved(task_beta=2.0)
    cem = PlannerConfig(algorithm="cem_mpc", budget=budget).resolved(task_beta=2.0)
    assert ((icem.iterations, icem.population), (cem.iterations, cem.population)) == TABLE_4[budget]
    # Table 4's settings spend roughly the nominal budget (within 8%).
    assert abs(icem.trajectories_per_step() - budget) <= 0.08 * budget
    assert abs(cem.trajectories_per_step() - budget) <= 0.08 * budget


def test_chapter_4_budget_45_is_two_iterations_of_25_and_20():
    config = PlannerConfig(algorithm="icem", budget=45).resolved(task_beta=0.25)
    assert (config.iterations, config.population) == (2, 25)
    assert config.population_sizes() == [25, 20]


def test_budget_100_is_40_32_25_plus_three_shifted_elites():
    config = PlannerConfig(budget=100).resolved(task_beta=0.25)
    assert config.population_sizes() == [40, 32, 25]  # N_i = max(N gamma^-i, 2K), section 3.2.3
    assert config.trajectories_per_step() == 100


def test_unlisted_budget_gets_a_schedule_close_to_it():
    config = PlannerConfig(budget=120).resolved(task_beta=1.0)
    assert abs(config.trajectories_per_step() - 120) <= 3


@pytest.mark.parametrize("algorithm", ["icem", "cem_mpc"])
@pytest.mark.parametrize("given", [{}, dict(iterations=3), dict(population=40), dict(population_decay=2.0, elites=3)])
def test_the_schedule_search_finds_the_closest_spend_of_every_candidate(algorithm, given):
    """The schedule is found by bisection over N (or the iterations); trying every candidate in turn, as the
    definition reads, gives the same schedule for every unlisted budget, ties going to the smaller candidate."""
    from workers.planning.config import CEM_BUDGETS, CHAPTER_4_BUDGETS, ICEM_BUDGETS, budget_schedule

    listed = ICEM_BUDGETS | CHAPTER_4_BUDGETS | CEM_BUDGETS  # Table 4's own schedules: test_budget_table_4

    def spend(config, iterations, population):
        update = dict(iterations=iterations, population=population, reevaluate_elites=False)
        return config.model_copy(update=update).trajectories_per_step()

    for budget in [b for b in range(21, 400, 3) if b not in listed] + [1001, 4001]:
        config = PlannerConfig(algorithm=algorithm, budget=budget, **given)
        if "population" in given:
            candidates = [(i, config.population) for i in range(1, budget + 1)]
        else:
            iterations = budget_schedule(algorithm, budget, config)[0]
            candidates = [(iterations, n) for n in range(max(config.elites, 2), budget + 1)]
        closest = min(candidates, key=lambda c: (abs(spend(config, *c) - budget), c))
        assert budget_schedule(algorithm, budget, config) == closest, budget


@pytest.mark.parametrize(
    "switched",
    [
        dict(algorithm="icem", population_decay=1.0),
        dict(algorithm="icem", shift_elites=False),
        dict(algorithm="cem_mpc", population_decay=1.25),
        dict(algorithm="cem_mpc", shift_elites=True, elite_fraction=0.3),
    ],
)
@pytest.mark.parametrize("budget", [100, 300])
def test_ablations_spend_the_budget_of_the_table_row_they_switch(switched, budget):
    """An ablation keeps the row's CEM-iterations and re-solves N, so it spends what the full method spends."""
    ablated = PlannerConfig(budget=budget, **switched).resolved(task_beta=0.25)
    full = PlannerConfig(algorithm=switched["algorithm"], budget=budget).resolved(task_beta=0.25)
    assert ablated.iterations == full.iterations
    assert abs(ablated.trajectories_per_step() - full.trajectories_per_step()) <= 2


def test_re_evaluated_elites_come_on_top_of_any_budget():
    """A budget counts the sequences sampled: a stochastic evaluator's second draws of kept elites are extra, for a
    listed budget (Table 4's row) as for one the search solves."""
    for budget in (100, 120):
        plain = PlannerConfig(budget=budget).resolved(task_beta=0.25)
        again = PlannerConfig(budget=budget, reevaluate_elites=True).resolved(task_beta=0.25)
        assert (again.iterations, again.population) == (plain.iterations, plain.population)
        assert again.trajectories_per_step() == plain.trajectories_per_step() + 3 * (plain.iterations - 1)


def test_resolved_beta_defaults():
    assert PlannerConfig(algorithm="icem").resolved(task_beta=3.5).noise_beta == 3.5
    assert PlannerConfig(algorithm="icem", noise_beta=0.0).resolved(task_beta=3.5).noise_beta == 0.0
    assert PlannerConfig(algorithm="cem_mpc").resolved(task_beta=3.5).noise_beta == 0.0
    # iCEM without clipping (an ablation) samples truncated normals, which are white: its record says so.
    assert PlannerConfig(algorithm="icem", bounds="truncate").resolved(task_beta=3.5).noise_beta == 0.0


@pytest.mark.parametrize(
    "given, tolerance",
    [
        (dict(iterations=5), 3),  # 5 x 20 (the 2K floor) + 3 shifted: the closest there is
        (dict(population=100), 3),  # one iteration of 100 + 3 shifted (Table 4's 3 iterations would spend 247)
        (dict(elites=5), 0),  # Table 4's N = 40 with K = 5 would spend 98
    ],
)
def test_a_budget_is_spent_whatever_part_of_the_schedule_is_given(given, tolerance):
    """Given iterations, N is solved for the budget; given N, the iterations; another K re-solves Table 4's N."""
    config = PlannerConfig(budget=100, **given).resolved(task_beta=0.25)
    assert all(getattr(config, name) == value for name, value in given.items())
    spent = config.trajectories_per_step()
    assert abs(spent - 100) <= tolerance, (config.population_sizes(), config.reused_elites())


def test_a_schedule_given_in_full_records_what_it_spends_as_its_budget():
    """Without a budget, iterations and population fix the spend; the budget field must not keep its default
    100, or the run is labelled, and compared with Table 3, as budget 100. A resolved config keeps it as is."""
    config = PlannerConfig(iterations=2, population=30).resolved(task_beta=0.25)
    assert config.budget == config.trajectories_per_step() == 30 + 24 + 3
    assert PlannerConfig.model_validate(config.model_dump()).resolved(task_beta=0.25) == config
    assert PlannerConfig(budget=100, iterations=3).resolved(task_beta=0.25).budget == 100
    # Table 4's budget 45 spends 48 (25 + 20 + 3 shifted elites); resolving it again keeps its label.
    table = PlannerConfig(budget=45).resolved(task_beta=0.25)
    assert PlannerConfig.model_validate(table.model_dump()).resolved(task_beta=0.25).budget == 45


def test_no_budget_needs_a_full_schedule_and_with_one_keeps_the_trials_key():
    """``budget: null`` says "no budget": with half a schedule it is refused rather than planned as budget 100's;
    with iterations and population it means the same config as leaving the budget out (one trial key)."""
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="without a budget, set both iterations and population"):
        PlannerConfig(budget=None, iterations=3)
    full = PlannerConfig(budget=None, iterations=3, population=128)
    assert full == PlannerConfig(iterations=3, population=128)
    assert full.resolved(task_beta=2.0).budget == full.resolved(task_beta=2.0).trajectories_per_step()


# ------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(budget=15), "budget"),
        (dict(noise_beta=5.5), "noise_beta"),
        (dict(noise_beta=-1), "noise_beta"),
        (dict(horizon=0), "horizon"),
        (dict(sigma_init=0), "sigma_init"),
        (dict(momentum=1.0), "momentum"),
        (dict(algorithm="mppi"), "algorithm"),
        (dict(colored=True), "colored"),
    ],
)
def test_bad_planner_config_names_the_field(kwargs, field):
    with pytest.raises(ValidationError) as error:
        PlannerConfig(**kwargs)
    assert field in str(error.value)


def test_colored_noise_needs_clipping():
    with pytest.raises(ValidationError, match="bounds: clip"):
        PlannerConfig(algorithm="cem_mpc", noise_beta=2.0)
    PlannerConfig(algorithm="cem_mpc", noise_beta=2.0, bounds="clip")  # the Fig. 7 "+colored noise" addition


@pytest.mark.parametrize("switch", ["keep_elites", "shift_elites"])
def test_elite_reuse_switched_on_that_would_reuse_none_is_refused(switch):
    """CEM_MPC has zeta = 0: keep- or shift-elites added to it without an elite_fraction reuse floor(0 x K) = 0
    elites and change nothing (the Fig. 7 additions set zeta 0.3); said, not run as if it were the ablation."""
    with pytest.raises(ValidationError, match=f"{switch} reuses floor"):
        PlannerConfig(algorithm="cem_mpc", **{switch: True})
    with pytest.raises(ValidationError, match="= 0 elites"):
        PlannerConfig(algorithm="cem_mpc", elites=3, elite_fraction=0.3, **{switch: True})
    assert PlannerConfig(algorithm="cem_mpc", elite_fraction=0.3, **{switch: True}).reused_elites() == 3
    PlannerConfig(algorithm="icem", elites=3)  # iCEM's own switches with a small K: as configured, not refused


# --------------------------------------------------------------- planning
TARGET = np.linspace(-0.8, 0.8, 10)[:, None] * np.array([1.0, -0.5])


def quadratic_cost(actions: np.ndarray) -> np.ndarray:
    """Distance of each (N, 10, 2) sequence to a fixed target sequence."""
    return np.sum((actions - TARGET) ** 2, axis=(1, 2))


def make(algorithm="icem", seed=0, objective=main_cost, **overrides):
    # iCEM's Table 4 schedule at budget 100, fixed: the tests switch elites off to isolate a behaviour, which
    # would otherwise re-solve N to keep the budget.
    schedule = dict(iterations=3, population=40) if algorithm == "icem" else {}
    config = PlannerConfig(algorithm=algorithm, budget=100, horizon=10, **(schedule | overrides))
    config = config.resolved(task_beta=1.0)
    return CEMPlanner(config, action_dim=2, seed=seed, objective=objective)


class Recorder:
    """A cost function that remembers every batch it was asked to evaluate."""

    def __init__(self):
        self.batches: list[np.ndarray] = []

    def __call__(self, actions):
        self.batches.append(actions.copy())
        return quadratic_cost(actions)


@pytest.mark.parametrize("algorithm", ["icem", "cem", "cem_mpc", "cem_pets"])
def test_same_seed_same_actions(algorithm):
    def actions(seed):
        planner = make(algorithm, seed=seed)
        return np.array([planner.plan(quadratic_cost).action for _ in range(5)])

    np.testing.assert_array_equal(actions(7), actions(7))
    assert not np.array_equal(actions(7), actions(8))


@pytest.mark.parametrize("algorithm", ["icem", "cem", "cem_mpc", "cem_pets"])
def test_planners_reduce_cost_and_respect_bounds(algorithm):
    recorder = Recorder()
    result = make(algorithm).plan(recorder)
    everything = np.concatenate(recorder.batches)
    assert everything.min() >= -1.0 and everything.max() <= 1.0
    random_cost = quadratic_cost(np.random.default_rng(0).uniform(-1, 1, (1000, 10, 2))).mean()
    assert result.best_cost < 0.5 * random_cost
    assert result.trajectories == sum(len(b) for b in recorder.batches)


@pytest.mark.parametrize("best_from", ["step", "last_iteration"])
def test_a_step_whose_every_cost_is_not_finite_still_gives_an_action(best_from):
    """A learned model early in training may put out NaN for every sample: the step executes something."""
    planner = make("icem", best_from=best_from)
    result = planner.plan(lambda actions: np.full(len(actions), np.nan))
    assert result.action.shape == (2,) and np.all(np.abs(result.action) <= 1.0)


def test_icem_spends_its_budget_per_step():
    planner = make("icem")
    first, second = Recorder(), Recorder()
    planner.plan(first)
    planner.plan(second)
    assert [len(b) for b in first.batches] == [40, 32, 25]  # no elites to shift yet
    assert [len(b) for b in second.batches] == [43, 32, 25]  # + 3 shifted elites


def test_add_mean_evaluates_the_mean_in_the_last_iteration_only(monkeypatch):
    planner = make("icem", shift_elites=False, keep_elites=False)
    means = []
    sample = planner._sample
    monkeypatch.setattr(
        planner, "_sample", lambda mean, std, count: means.append(mean.copy()) or sample(mean, std, count)
    )
    recorder = Recorder()
    planner.plan(recorder)
    np.testing.assert_array_equal(recorder.batches[-1][0], means[-1])
    for batch, mean in zip(recorder.batches[:-1], means[:-1]):
        assert not any(np.array_equal(row, mean) for row in batch)


def test_best_action_executes_the_best_evaluated_sequence():
    recorder = Recorder()
    result = make("icem").plan(recorder)
    everything = np.concatenate(recorder.batches)
    best = everything[np.argmin(quadratic_cost(everything))]
    np.testing.assert_array_equal(result.action, best[0])
    assert result.best_cost == pytest.approx(quadratic_cost(best[None])[0])


def test_mean_action_without_best_action():
    planner = make("icem", best_action=False)
    result = planner.plan(quadratic_cost)
    # The next step's mean is the shifted final mean, so the executed action is its predecessor.
    np.testing.assert_array_equal(result.plan[1:], planner.mean[:-1])
    np.testing.assert_array_equal(result.action, result.plan[0])


@pytest.mark.parametrize("algorithm, last", [("cem_mpc", "repeat"), ("cem_pets", "zero")])
def test_shift_initialisation_eq_32_33(algorithm, last):
    planner = make(algorithm)
    result = planner.plan(quadratic_cost)
    final_mean = result.plan  # mean action: plan is the final mean
    np.testing.assert_array_equal(planner.mean[:-1], final_mean[1:])  # eq. 32
    expected_last = final_mean[-1] if last == "repeat" else np.zeros(2)  # eq. 33 / CEM_PETS
    np.testing.assert_array_equal(planner.mean[-1], expected_last)


def test_plain_cem_restarts_from_zero_mean():
    planner = make("cem")
    planner.plan(quadratic_cost)
    np.testing.assert_array_equal(planner.mean, np.zeros((10, 2)))


class CandidateLog:
    """An objective that records every CEM-iteration's candidates (samples and kept elites) and their costs."""

    def __init__(self):
        self.batches: list[CostBatch] = []

    def __call__(self, batch: CostBatch, iteration: int) -> np.ndarray:
        self.batches.append(batch)
        return main_cost(batch, iteration)


def spy_sampling(planner: CEMPlanner, monkeypatch) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Record the (mean, std, count) of every sampling call of the planner."""
    calls = []
    sample = planner._sample
    monkeypatch.setattr(
        planner,
        "_sample",
        lambda mean, std, count: calls.append((mean.copy(), std.copy(), count)) or sample(mean, std, count),
    )
    return calls


@pytest.mark.parametrize("keep", [True, False])
def test_keep_elites_adds_the_best_of_the_last_iteration_with_their_costs(keep):
    """Section 3.2.2: iteration i + 1 ranks its samples together with the best zeta K elites of iteration i."""
    log = CandidateLog()
    planner = make("icem", keep_elites=keep, shift_elites=False)
    planner.objective = log
    recorder = Recorder()
    planner.plan(recorder)
    sizes = [len(b.costs) for b in log.batches]
    evaluated = [len(b) for b in recorder.batches]
    if not keep:
        assert sizes == evaluated == [40, 32, 25]
        return
    assert evaluated == [40, 32, 25] and sizes == [40, 35, 28]  # 3 = floor(0.3 * 10) kept, not re-simulated
    for before, after in zip(log.batches, log.batches[1:]):
        best_before = np.sort(before.costs)[:3]
        np.testing.assert_array_equal(np.sort(after.costs[-3:]), best_before)


def test_reevaluated_elites_are_simulated_again():
    recorder = Recorder()
    planner = make("icem", shift_elites=False, reevaluate_elites=True)
    planner.plan(recorder)
    assert [len(b) for b in recorder.batches] == [40, 35, 28]
    first_best = recorder.batches[0][np.argsort(quadratic_cost(recorder.batches[0]))[:3]]
    np.testing.assert_array_equal(recorder.batches[1][-3:], first_best)
    assert planner.config.trajectories_per_step() == 40 + 35 + 28


class LuckyFirstDraw(Recorder):
    """A random cost: the first iteration's best sequence drew far below its real cost, which its re-evaluation
    in the next iteration (a kept elite) shows."""

    def __call__(self, actions):
        costs = super().__call__(actions)
        if len(self.batches) == 1:
            costs[np.argmin(costs)] -= 1000.0
        return costs


@pytest.mark.parametrize("best_from", ["step", "last_iteration"])
def test_the_executed_best_comes_from_the_step_or_the_last_iterations_elites(best_from):
    """Section 3.2.3 executes the best sequence ever evaluated at the step; Alg. 5 (line 11) the best of the final
    elite-set, which with re-evaluated elites is ranked on current draws only."""
    cost = LuckyFirstDraw()
    planner = make("icem", shift_elites=False, reevaluate_elites=True, best_from=best_from)
    result = planner.plan(cost)
    lucky = cost.batches[0][np.argmin(quadratic_cost(cost.batches[0]))]
    last = cost.batches[-1][np.argmin(quadratic_cost(cost.batches[-1]))]
    assert any(np.array_equal(lucky, s) for s in cost.batches[1])  # re-evaluated, with its real cost
    assert not np.array_equal(lucky, last)
    if best_from == "step":
        np.testing.assert_array_equal(result.plan, lucky)
        assert result.best_cost == quadratic_cost(lucky[None])[0] - 1000.0
    else:
        np.testing.assert_array_equal(result.plan, last)
        assert result.best_cost == quadratic_cost(last[None])[0]
    np.testing.assert_array_equal(result.action, result.plan[0])


@pytest.mark.parametrize("algorithm", ["icem", "cem_mpc", "cem"])
def test_refit_moves_mean_and_std_to_the_elites_with_momentum(algorithm, monkeypatch):
    """mu <- alpha mu + (1 - alpha) mean(elites), sigma likewise (section 3.1.1; alpha 0 for plain CEM)."""
    log = CandidateLog()
    planner = make(algorithm, shift_elites=False)
    planner.objective = log
    calls = spy_sampling(planner, monkeypatch)
    candidates = []
    cost = Recorder()
    planner.plan(lambda actions: candidates.append(actions.copy()) or cost(actions))
    alpha = planner.config.momentum
    assert alpha == (0.0 if algorithm == "cem" else 0.1)
    kept = None
    for i in range(len(calls) - 1):
        samples = candidates[i] if kept is None else np.concatenate([candidates[i], kept])
        order = np.argsort(log.batches[i].costs, kind="stable")[:10]
        elites = samples[order]
        mean, std, _ = calls[i]
        next_mean, next_std, _ = calls[i + 1]
        np.testing.assert_allclose(next_mean, alpha * mean + (1 - alpha) * elites.mean(axis=0), atol=1e-12)
        np.testing.assert_allclose(next_std, alpha * std + (1 - alpha) * elites.std(axis=0), atol=1e-12)
        kept = elites[: planner.reused] if planner.config.keep_elites else None


def test_sigma_is_reset_and_the_shifted_mean_starts_the_next_step(monkeypatch):
    planner = make("icem")
    calls = spy_sampling(planner, monkeypatch)
    planner.plan(quadratic_cost)
    shifted = planner.mean.copy()
    count_first = len(calls)
    planner.plan(quadratic_cost)
    mean, std, _ = calls[count_first]
    np.testing.assert_array_equal(mean, shifted)  # eq. 32: the next step starts from the shifted mean
    np.testing.assert_array_equal(std, np.full((10, 2), 0.5))  # sigma_init at every step


def test_shift_elites_moves_last_steps_elites_one_step_in_time():
    planner = make("icem")
    planner.plan(quadratic_cost)
    previous = planner.memory.elites.copy()
    recorder = Recorder()
    planner.plan(recorder)
    shifted = recorder.batches[0][-3:]
    np.testing.assert_array_equal(shifted[:, :-1], previous[:3, 1:])  # the best 3 elites, shifted
    assert not np.array_equal(shifted[:, -1], previous[:3, -1])  # a fresh random last action


def test_proposals_replace_samples_of_the_last_iteration_only():
    proposal = np.full((1, 10, 2), 0.25)
    recorder = Recorder()
    make("icem", shift_elites=False).plan(recorder, proposals=proposal)
    last = recorder.batches[-1]
    np.testing.assert_array_equal(last[1], proposal[0])  # after the mean (sample 0)
    assert len(last) == 25  # the budget is unchanged
    for batch in recorder.batches[:-1]:
        assert not any(np.array_equal(row, proposal[0]) for row in batch)


def test_particle_costs_are_reduced_by_their_aggregate():
    """A stochastic evaluator's (N, P) costs are averaged per sequence (PETS), or their worst case taken."""
    particles = np.random.default_rng(0).normal(size=(30, 5))
    assert np.array_equal(CostBatch(particles).main(), particles.mean(axis=1))
    assert np.array_equal(CostBatch(particles, "max").main(), particles.max(axis=1))
    planner = make("icem")
    result = planner.plan(lambda a: CostBatch(np.repeat(quadratic_cost(a)[:, None], 4, axis=1) + np.arange(4)))
    assert result.best_cost == pytest.approx(quadratic_cost(result.plan[None])[0] + 1.5)


def test_objective_weighs_cost_components_and_reports_the_best_ones():
    """An objective sees every component, also of kept elites, and decides the ranking (APEX guidance)."""

    def evaluate(actions):
        return CostBatch(quadratic_cost(actions), components={"guide": np.abs(actions).sum(axis=(1, 2))})

    seen = []

    def objective(batch, iteration):
        seen.append(len(batch.components["guide"]) == len(batch.costs))
        return batch.costs + 100.0 * batch.components["guide"]

    planner = make("icem", objective=objective)
    result = planner.plan(evaluate)
    assert all(seen) and set(result.components) == {"guide"}
    plain = make("icem").plan(evaluate)
    assert result.components["guide"] < plain.components["guide"]  # the heavy weight pulls actions to zero


def test_planner_state_round_trip_continues_identically():
    a = make("icem", seed=3)
    a.plan(quadratic_cost)
    b = make("icem", seed=99)
    b.load_state_dict(a.state_dict())
    np.testing.assert_array_equal(a.plan(quadratic_cost).action, b.plan(quadratic_cost).action)


def test_pets_caps_sigma_at_half_the_distance_to_the_bounds():
    planner = make("cem_pets")
    mean = np.full((10, 2), 0.9)
    capped = planner._cap_std(mean, np.full((10, 2), 0.5))
    np.testing.assert_allclose(capped, 0.05)


def test_colored_noise_samples_are_smoother_with_higher_beta():
    def roughness(beta):
        recorder = Recorder()
        make("icem", noise_beta=beta, sigma_init=0.3).plan(recorder)
        first = recorder.batches[0]
        return np.abs(np.diff(first, axis=1)).mean()

    assert roughness(3.0) < roughness(1.0) < roughness(0.0)


def test_truncated_normal_matches_scipy_with_offset_means():
    """Inverse-CDF sampling against scipy's truncnorm, for means away from zero and near a bound."""
    from scipy.stats import truncnorm

    rng = np.random.default_rng(4)
    mean, std = np.array([0.6, -0.7, 0.2]), np.array([0.5, 0.3, 1.5])
    samples = truncated_normal(mean, std, -1.0, 1.0, 60000, rng)
    a, b = (-1.0 - mean) / std, (1.0 - mean) / std
    np.testing.assert_allclose(samples.mean(axis=0), truncnorm.mean(a, b, loc=mean, scale=std), atol=0.01)
    np.testing.assert_allclose(samples.std(axis=0), truncnorm.std(a, b, loc=mean, scale=std), atol=0.01)


def test_colored_samples_spread_by_sigma_around_the_mean():
    """iCEM samples clip(mu + C^beta sigma): the spread scales with sigma, centred on the mean."""
    for sigma in (0.05, 0.2):
        recorder = Recorder()
        planner = make("icem", noise_beta=0.0, sigma_init=sigma, shift_elites=False, add_mean=False)
        planner.memory = planner.initial_memory(np.full((10, 2), 0.3))
        planner.plan(recorder)
        first = recorder.batches[0]
        assert first.mean() == pytest.approx(0.3, abs=0.02)
        assert first.std() == pytest.approx(sigma, rel=0.15)


def test_without_add_mean_the_mean_is_not_evaluated(monkeypatch):
    planner = make("cem_mpc")
    means = []
    sample = planner._sample
    monkeypatch.setattr(
        planner, "_sample", lambda mean, std, count: means.append(mean.copy()) or sample(mean, std, count)
    )
    recorder = Recorder()
    planner.plan(recorder)
    assert not any(np.array_equal(row, means[-1]) for row in recorder.batches[-1])


def test_several_proposals_are_clipped_into_the_action_bounds():
    proposals = np.stack([np.full((10, 2), 0.25), np.full((10, 2), 3.0)])
    recorder = Recorder()
    make("icem", shift_elites=False).plan(recorder, proposals=proposals)
    last = recorder.batches[-1]
    np.testing.assert_array_equal(last[1], proposals[0])
    np.testing.assert_array_equal(last[2], np.ones((10, 2)))  # clipped to the bound


def test_cost_batches_keep_their_aggregate_and_refuse_mismatches():
    batch = CostBatch(np.arange(12.0).reshape(4, 3), "max", {"guide": np.arange(4.0)})
    taken = batch.take(np.array([2, 0]))
    assert taken.aggregate == "max" and list(taken.main()) == [8.0, 2.0]
    with pytest.raises(ValueError, match="different components"):
        CostBatch.concatenate(batch, CostBatch(np.zeros((1, 3))))
    planner = make("icem")
    with pytest.raises(ValueError, match="expected"):
        planner.plan(lambda actions: np.zeros(len(actions) + 1))
    with pytest.raises(ValueError, match="component 'guide'"):
        planner.plan(lambda actions: CostBatch(np.zeros(len(actions)), components={"guide": np.zeros(2)}))


def test_fresh_planner_state_round_trips_without_elites():
    fresh = make("icem", seed=3)
    other = make("icem", seed=9)
    other.load_state_dict(fresh.state_dict())
    assert other.memory.elites is None
    np.testing.assert_array_equal(fresh.plan(quadratic_cost).action, other.plan(quadratic_cost).action)
