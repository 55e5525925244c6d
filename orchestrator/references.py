"""Published figures as data: what a configuration's result is compared with.

A reference file (YAML) lists entries: the task and method they are about,
the run params that must match (dotted, as MLflow shows them), the metric,
the published value with its spread and number of runs, and where in the
paper it comes from. icemlab ships the thesis's tables
(orchestrator/published/thesis.yaml); a sweep names another file with
``reference:`` to compare against another paper.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator

from orchestrator.yaml_problems import SweepError, SweepProblem, problems_from, read_yaml

THESIS = Path(__file__).parent / "published" / "thesis.yaml"
"""The thesis's published figures (Tables 2 and 3, and those the chapters add)."""


class Reference(BaseModel):
    """One published figure."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    task: str
    """The task it is about."""
    method: str = "mpc"
    """The method it is about."""
    match: dict[str, Any] = {}
    """Run params that must be equal (dotted as in MLflow, e.g. planner.budget); null matches an unset value."""
    published_with: dict[str, Any] = {}
    """Run params the published figure was obtained with that a run may change and still be shown beside it
    (APEX's rollouts per iteration, episode length): a run that differs in any is not tested against it, and
    the report says which differ."""
    metric: str | tuple[str, ...]
    """The metric, as sweeps name it (episode_return, success, seconds_per_step, ...), or a list of the metrics
    that each stand for this figure (APEX's policy_return and evaluation_return)."""
    value: float
    """The published value (a mean, or a success rate)."""
    spread: float | None = Field(None, ge=0)
    """The published +- figure, if any."""
    spread_kind: Literal["std", "sem"] | None = Field(None, validate_default=True)
    """std: per-run standard deviation; sem: standard error of the mean. Required with a spread: read as the other,
    a test is about sqrt(runs) times too strict or too lenient."""
    runs: int | None = Field(None, ge=1)
    """Independent runs behind the figure."""
    source: str = Field(min_length=1)
    """Where in the paper (table, figure, section)."""

    @field_validator("spread_kind")
    @classmethod
    def _a_spread_says_its_kind(cls, kind: str | None, info: ValidationInfo) -> str | None:
        if kind is None and info.data.get("spread") is not None:
            raise ValueError("a spread needs its kind: std (per-run standard deviation) or sem (standard error)")
        return kind

    def matches(self, task: str, method: str, params: Mapping[str, str], metric: str) -> bool:
        metrics = (self.metric,) if isinstance(self.metric, str) else self.metric
        if (self.task, self.method) != (task, method) or metric not in metrics:
            return False
        return all(same_param(params.get(key), value) for key, value in self.match.items())

    def differences(self, params: Mapping[str, str]) -> list[str]:
        """``key=value (published other)`` for each ``published_with`` param the run did not share."""
        return [
            f"{key}={params.get(key)} (published {value})"
            for key, value in self.published_with.items()
            if not same_param(params.get(key), value)
        ]


def same_param(param: str | None, value: Any) -> bool:
    """Whether a run param (a string, as MLflow holds it) equals a value."""
    if value is None:
        return param in (None, "None")
    if param is None:
        return False
    if isinstance(value, bool):
        return param in (str(value), json.dumps(value))
    if isinstance(value, int | float):
        try:
            return float(param) == float(value)
        except ValueError:
            return False
    return param == str(value)


def load_references(path: str | Path) -> list[Reference]:
    """Read a reference file; raise SweepError with one ``FILE:LINE: path: message`` per problem."""
    path = Path(path)
    file = str(path)
    if not path.is_file():
        raise SweepError([SweepProblem(file, 1, "(file)", "reference file not found")])
    _, data, root = read_yaml(path)
    if not isinstance(data, dict) or not isinstance(data.get("entries"), list):
        raise SweepError([SweepProblem(file, 1, "(file)", "a reference file is a mapping with a list 'entries'")])
    references, problems = [], []
    for index, entry in enumerate(data["entries"]):
        try:
            references.append(Reference.model_validate(entry))
        except ValidationError as error:
            problems += problems_from(error, file, root, Reference, prefix=("entries", index))
    if problems:
        raise SweepError(sorted(problems, key=lambda p: p.line))
    return references


def find(
    references: list[Reference], task: str, method: str, params: Mapping[str, str], metric: str
) -> Reference | None:
    """The first entry about this configuration and metric, or None."""
    return next((r for r in references if r.matches(task, method, params, metric)), None)
