"""Configuration of the CEM family of planners (thesis chapter 3, appendix B).

One :class:`PlannerConfig` describes CEM, CEM_MPC, CEM_PETS or iCEM. The
``algorithm`` sets the default of every switch (Table 5 and section 3.1.1);
any switch can be overridden, which is how the ablations of Fig. 7 are run
(e.g. iCEM without colored noise, CEM_MPC with keep-elites added).
"""

from __future__ import annotations

import bisect
from collections.abc import Callable
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from workers.planning.noise import DEFAULT_NOISE_RELEASE

Algorithm = Literal["icem", "cem", "cem_mpc", "cem_pets"]
BoundHandling = Literal["clip", "truncate", "truncate_2sigma"]

# Table 4: budget (trajectories per environment step) -> (CEM-iterations, initial population N).
ICEM_BUDGETS: dict[int, tuple[int, int]] = {
    50: (2, 25),
    70: (2, 40),
    100: (3, 40),
    150: (3, 60),
    200: (4, 65),
    250: (4, 85),
    300: (4, 100),
    400: (5, 120),
    500: (5, 150),
    1000: (6, 270),
    2000: (8, 480),
    4000: (10, 900),
}
MAX_BUDGET = 1_000_000
"""Far past Table 4's largest budget (4000); bounds the schedule search and what one step may ask for."""
# Chapter 4's low budget (Tables 9-12): 45 = 25 + 20 trajectories after decay, Table 4's budget-50
# schedule counted without the shifted elites.
CHAPTER_4_BUDGETS: dict[int, tuple[int, int]] = {45: (2, 25)}
CEM_BUDGETS: dict[int, tuple[int, int]] = {
    50: (2, 25),
    70: (2, 35),
    100: (2, 50),
    150: (2, 75),
    200: (3, 66),
    250: (3, 83),
    300: (3, 100),
    400: (4, 100),
    500: (4, 125),
    1000: (4, 250),
    2000: (6, 333),
    4000: (8, 500),
}

# Switch defaults per algorithm. iCEM: section 3.2 and Table 5 (alpha 0.1,
# gamma 1.25, zeta 0.3, every improvement on, clipping). CEM_MPC (section
# 3.1.1): shift-initialised mean (eq. 32-33), momentum, truncation at the
# action bounds, white noise, no memory. CEM_PETS differs from CEM_MPC in its
# truncation (2 sigma, sigma capped at half the distance to the nearest bound)
# and a zero last step when shifting (B.4.1). Plain CEM (Alg. 1) starts every
# step from a zero mean without momentum; the thesis leaves its bound handling
# open and we truncate at the bounds like CEM_MPC.
_CEM_MPC = dict(
    momentum=0.1,
    population_decay=1.0,
    elite_fraction=0.0,
    keep_elites=False,
    shift_elites=False,
    shift_mean=True,
    shift_last="repeat",
    best_action=False,
    add_mean=False,
    bounds="truncate",
    noise_beta=0.0,
)
PRESETS: dict[str, dict[str, Any]] = {
    "icem": _CEM_MPC
    | dict(
        population_decay=1.25,
        elite_fraction=0.3,
        keep_elites=True,
        shift_elites=True,
        best_action=True,
        add_mean=True,
        bounds="clip",
        noise_beta=None,  # the task's Table 6 value, filled in by PlannerConfig.resolved
    ),
    "cem_mpc": _CEM_MPC,
    "cem_pets": _CEM_MPC | dict(shift_last="zero", bounds="truncate_2sigma"),
    "cem": _CEM_MPC | dict(momentum=0.0, shift_mean=False),
}


SPENDING_SWITCHES = ("elites", "population_decay", "elite_fraction", "keep_elites", "shift_elites")
"""Settings that change how many trajectories a schedule spends; Table 4's rows assume the preset's values (K = 10,
Table 5). Re-evaluating kept elites (``reevaluate_elites``) is not among them: a budget counts the sequences
sampled, as Table 4 does, and a stochastic evaluator's second draws of kept elites come on top of it
(``trajectories_per_step`` counts them)."""


class PlannerConfig(BaseModel):
    """A planner of the CEM family; every field is a sweepable parameter."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    algorithm: Algorithm = "icem"
    """Member of the CEM family: icem, cem (Alg. 1), cem_mpc or cem_pets (section 3.1.1). Sets the switch defaults."""
    elites: int = Field(10, ge=1)
    """Size K of the elite-set (Table 5)."""
    bounds: BoundHandling | None = None
    """Action bounds: clip (iCEM), truncate at the bounds (CEM_MPC), or at 2 sigma with sigma capped (CEM_PETS)."""
    budget: int | None = Field(100, ge=1, le=MAX_BUDGET)
    """Trajectories evaluated per environment step; sets iterations and population by Table 4 (given one of them,
    the other is chosen to spend the budget). Must be >= 2 * elites, at most a million (Table 4 ends at 4000).
    Not given with both iterations and population: it then records the trajectories they spend per step."""
    iterations: int | None = Field(None, ge=1)
    """CEM-iterations per environment step. Default: from the budget (Table 4); given with a budget, the population
    is chosen to spend it."""
    population: int | None = Field(None, ge=2)
    """Initial population N (samples in the first CEM-iteration). Default: from the budget (Table 4); given with a
    budget, the iterations are chosen to spend it."""
    horizon: int = Field(30, ge=1)
    """Planning horizon h in environment steps (30 with ground-truth models, Table 6)."""
    sigma_init: float = Field(0.5, gt=0)
    """Initial standard deviation sigma_init, in units of half the action range (Table 5); reset every step."""
    noise_beta: float | None = Field(None, ge=0, le=5)
    """Colored-noise exponent beta, PSD ~ 1/f^beta (eq. 10); 0 is white. Default: the task's Table 6 value for icem."""
    noise_release: Literal["1.1", "2.1"] = DEFAULT_NOISE_RELEASE
    """Which colorednoise release the colored noise follows: "1.1", as the authors' public iCEM code ran (the
    thesis's figures), leaves the constant (DC) and Nyquist terms as drawn; "2.1" (from June 2022) doubles their
    variance (workers/planning/noise.py). At beta 3 over h = 30 "2.1" gives the per-sequence constant offset twice
    the variance. On Fetch and Relocate "1.1" reaches Table 3 and "2.1" falls short (docs/results/icem.md)."""
    momentum: float | None = Field(None, ge=0, lt=1)
    """Momentum alpha of the refit: mu <- alpha mu + (1 - alpha) mu_elites, same for sigma (section 3.1.1)."""
    population_decay: float | None = Field(None, ge=1)
    """Population decay gamma: N_i = max(N gamma^-i, 2K) (section 3.2.3). 1 disables it."""
    elite_fraction: float | None = Field(None, ge=0, le=1)
    """Fraction zeta of the elite-set reused by keep-elites and shift-elites (section 3.2.2)."""
    keep_elites: bool | None = None
    """Add the best zeta K elites of an iteration to the next iteration's samples (section 3.2.2). Switched on for
    an algorithm that has it off (CEM_MPC), it needs an elite_fraction that reuses at least one elite."""
    shift_elites: bool | None = None
    """Reuse the best zeta K final elites at the next step: shifted by one step, a random action appended."""
    shift_mean: bool | None = None
    """Initialise the mean from the previous step's mean shifted by one step (eq. 32); otherwise from zero."""
    shift_last: Literal["repeat", "zero"] | None = None
    """Last step of the shifted mean: repeat the previous last step (eq. 33) or zero (CEM_PETS)."""
    best_action: bool | None = None
    """Execute the first action of the best sequence evaluated at this step instead of the mean's (section 3.2.3)."""
    best_from: Literal["step", "last_iteration"] = "step"
    """With best_action, which best sequence is executed: "step" the best evaluated in any CEM-iteration of this
    step (section 3.2.3, "the best sequence ever evaluated"), "last_iteration" the best of the last iteration's
    elite-set (Alg. 5, line 11). They differ when costs are random: with re-evaluated kept elites,
    "last_iteration" ranks current draws only, where "step" may execute a sequence on a draw that its
    re-evaluation has since replaced."""
    add_mean: bool | None = None
    """Evaluate the mean sequence in the last CEM-iteration (B.4.3)."""
    reevaluate_elites: bool = False
    """Evaluate kept elites again in the next iteration instead of reusing their costs: needed when costs are
    random (learned stochastic models, chapter 5); ground truth is deterministic, so reusing is exact there."""

    @model_validator(mode="before")
    @classmethod
    def _fill_switch_defaults(cls, data: Any) -> Any:
        if isinstance(data, dict):
            no_budget = "budget" in data and data["budget"] is None
            algorithm = data.get("algorithm", "icem")
            # Not a name (e.g. a list): no preset; the field's own validation says what it takes.
            preset = PRESETS.get(algorithm) if isinstance(algorithm, str) else None
            if preset is not None:
                data = {**preset, **{k: v for k, v in data.items() if v is not None}}
            if no_budget and (data.get("iterations") is None or data.get("population") is None):
                # "No budget" with half a schedule would silently plan budget 100's: kept, so that
                # _schedule_is_defined refuses it. With a full schedule the budget records what it spends.
                data = {**data, "budget": None}
        return data

    @field_validator("budget")
    @classmethod
    def _budget_covers_two_elite_sets(cls, budget: int | None, info: ValidationInfo) -> int | None:
        elites = info.data.get("elites")
        if budget is not None and elites is not None and budget < 2 * elites:
            raise ValueError(
                f"budget {budget} is below 2K = {2 * elites} (twice the elite-set size); raise it or lower elites"
            )
        return budget

    @field_validator("population")
    @classmethod
    def _population_holds_the_elites(cls, population: int | None, info: ValidationInfo) -> int | None:
        elites = info.data.get("elites")
        if population is not None and elites is not None and population < elites:
            raise ValueError(f"population {population} is smaller than the elite-set ({elites})")
        return population

    @field_validator("noise_beta")
    @classmethod
    def _colored_noise_needs_clipping(cls, beta: float | None, info: ValidationInfo) -> float | None:
        if beta not in (None, 0.0) and info.data.get("bounds") not in (None, "clip"):
            raise ValueError("colored noise (noise_beta > 0) needs bounds: clip; truncated normals are white")
        return beta

    @field_validator("keep_elites", "shift_elites")
    @classmethod
    def _switched_on_reuse_reuses_some(cls, on: bool | None, info: ValidationInfo) -> bool | None:
        # On where the preset has it off is the user's doing (CEM_MPC + keep-elites, Fig. 7); with CEM_MPC's
        # zeta = 0 it would reuse floor(zeta K) = 0 elites and change nothing.
        preset = PRESETS.get(info.data.get("algorithm", ""), {})
        if on and preset.get(info.field_name) is False:
            fraction, elites = info.data.get("elite_fraction") or 0.0, info.data.get("elites")
            if elites is not None and int(elites * fraction) == 0:
                raise ValueError(
                    f"{info.field_name} reuses floor(elite_fraction x elites) = floor({fraction} x {elites}) = 0 "
                    "elites, so it would change nothing; set elite_fraction with it (iCEM's is 0.3)"
                )
        return on

    @model_validator(mode="after")
    def _schedule_is_defined(self) -> PlannerConfig:
        if self.budget is None and (self.iterations is None or self.population is None):
            raise ValueError("without a budget, set both iterations and population")
        return self

    # ----------------------------------------------------------- resolving
    def resolved(self, task_beta: float) -> PlannerConfig:
        """The same config with every default made concrete (beta, iterations, population).

        The task's beta is iCEM's with clipping only: truncated normals are white, so an iCEM that truncates
        (an ablation) samples white noise and records beta 0.
        """
        colored = self.algorithm == "icem" and self.bounds == "clip"
        beta = self.noise_beta if self.noise_beta is not None else (task_beta if colored else 0.0)
        iterations, population = self.iterations, self.population
        if iterations is None or population is None:
            table_iterations, table_population = budget_schedule(self.algorithm, self.budget or 0, self)
            iterations = iterations or table_iterations
            population = population or table_population
        resolved = self.model_copy(update=dict(noise_beta=beta, iterations=iterations, population=population))
        if self.iterations is not None and self.population is not None and "budget" not in self.model_fields_set:
            # A schedule given in full spends what it spends: the budget records that, not the field's default
            # (which would label the run, and match it with the published figures, as budget 100).
            resolved = resolved.model_copy(update={"budget": resolved.trajectories_per_step()})
        return resolved

    def population_sizes(self) -> list[int]:
        """N_i for every CEM-iteration (section 3.2.3); needs a resolved config."""
        assert self.iterations is not None and self.population is not None and self.population_decay is not None
        return [max(int(self.population * self.population_decay**-i), 2 * self.elites) for i in range(self.iterations)]

    def reused_elites(self) -> int:
        """How many elites keep-elites and shift-elites reuse: floor(zeta K)."""
        return int(self.elites * (self.elite_fraction or 0.0))

    def trajectories_per_step(self) -> int:
        """Trajectories evaluated per environment step (the budget actually spent)."""
        shifted = self.reused_elites() if self.shift_elites else 0
        reevaluated = self.reused_elites() * (self.iterations - 1) if self.keep_elites and self.reevaluate_elites else 0
        return sum(self.population_sizes()) + shifted + reevaluated


def budget_schedule(algorithm: str, budget: int, config: PlannerConfig) -> tuple[int, int]:
    """(CEM-iterations, initial N) for a budget.

    Budgets listed in Table 4 use its values (the iCEM row for icem, the CEM
    row for the CEM baselines), and chapter 4's budget 45 uses Table 4's
    budget-50 schedule. Other budgets take the iterations of the
    nearest listed budget below and the N whose total comes closest to the
    budget under the config's decay and elite reuse.

    A Table 4 row holds for its algorithm's own decay and elite reuse; a
    config that switches one of them (an ablation, Fig. 7) keeps the row's
    iterations and gets the N that spends the same budget, so that variants
    compare at equal trajectories per step. A config that gives its
    iterations gets the N that spends the budget with them; one that gives
    its N gets the iterations that come closest.
    """
    table = ICEM_BUDGETS | CHAPTER_4_BUDGETS if algorithm == "icem" else CEM_BUDGETS
    preset = PRESETS.get(algorithm, {})
    defaults = {name: PlannerConfig.model_fields[name].default for name in SPENDING_SWITCHES}
    spends_as_tabled = all(getattr(config, name) == preset.get(name, defaults[name]) for name in SPENDING_SWITCHES)
    if config.population is not None:
        # Every CEM-iteration adds at least 2K trajectories: past the budget, more only go further past it.
        most = min(budget, budget // (2 * config.elites) + 1)
        return _closest_spend(config, budget, lambda i: (i, config.population), 1, most)
    if budget in table and spends_as_tabled and config.iterations in (None, table[budget][0]):
        return table[budget]
    # Given iterations, or the row of the budget itself when listed, otherwise of the nearest listed below.
    listed = sorted(table)
    iterations = config.iterations or table[listed[max(0, bisect.bisect_right(listed, budget) - 1)]][0]
    return _closest_spend(config, budget, lambda n: (iterations, n), max(config.elites, 2), budget)


def _closest_spend(
    config: PlannerConfig, budget: int, schedule: Callable[[int], tuple[int, int]], low: int, high: int
) -> tuple[int, int]:
    """The schedule ``schedule(x)``, x in [low, high], whose trajectories per step come closest to ``budget``
    (the smallest x of equals).

    What a schedule spends never falls as x (its N, or its iterations) grows, so the closest is the first x that
    reaches the budget or the first x of the spend just below it: two bisections, not a pass over every x (a
    budget of a million would otherwise try a million schedules).
    """

    def spend(x: int) -> int:
        iterations, population = schedule(x)
        # Sampled sequences only: re-evaluated kept elites come on top of a budget (see SPENDING_SWITCHES).
        update = dict(iterations=iterations, population=population, reevaluate_elites=False)
        return config.model_copy(update=update).trajectories_per_step()

    def first_reaching(target: int) -> int:
        """The smallest x in [low, high] that spends at least ``target``; high + 1 if none does."""
        return low + bisect.bisect_left(range(low, high + 1), True, key=lambda x: spend(x) >= target)

    if low > high:
        raise ValueError(f"budget {budget} is too small for {schedule(low)[0]} iterations")
    reaching = first_reaching(budget)
    candidates = [first_reaching(spend(reaching - 1))] if reaching > low else []
    candidates += [reaching] if reaching <= high else []
    best = min(candidates, key=lambda x: (abs(spend(x) - budget), x))
    return schedule(best)
