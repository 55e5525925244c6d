"""User YAML files read whole, and their problems located: ``FILE:LINE: path: message``.

Sweep files (orchestrator/sweep.py) and reference files (orchestrator/references.py) are both read here and
report every problem against the line of the YAML node it concerns, with a did-you-mean hint for a
misspelt key.
"""

from __future__ import annotations

import difflib
import re
import types
import typing
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import yaml
from pydantic import BaseModel, ValidationError

MAX_FILE_BYTES = 1 << 20
"""Sweep files are read whole before anything is checked; a bound keeps a bad file cheap to refuse."""


class SweepProblem(NamedTuple):
    """One problem of a sweep file, located."""

    file: str
    line: int
    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}:{self.line}: {self.path}: {self.message}"


class SweepError(Exception):
    """A sweep file that cannot run; ``problems`` lists every located problem found.

    ``unchecked`` names the checks that could not run because of them (each check needs the parts before it
    valid: the file's keys, then the method's settings, then every trial), or is None when all ran.
    """

    def __init__(self, problems: list[SweepProblem], unchecked: str | None = None):
        self.problems = problems
        self.unchecked = unchecked
        super().__init__("\n".join(str(p) for p in problems))


def submodel(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model inside an annotation (``Model``, ``Model | None``), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        models = [a for a in typing.get_args(annotation) if isinstance(a, type) and issubclass(a, BaseModel)]
        return models[0] if len(models) == 1 else None
    return None



def _leaves(annotation: Any) -> list[Any]:
    """The alternatives of an annotation: the members of a union (``int | None``), unwrapped from ``Annotated``."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _leaves(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return [leaf for arg in typing.get_args(annotation) for leaf in _leaves(arg)]
    return [annotation]


def _number_only(annotation: Any) -> bool:
    """Whether a field takes numbers but not booleans (nor anything at all)."""
    leaves = _leaves(annotation)
    kinds = {type(v) for leaf in leaves if typing.get_origin(leaf) is typing.Literal for v in typing.get_args(leaf)}
    kinds |= {leaf for leaf in leaves if isinstance(leaf, type)}
    return bool(kinds & {int, float}) and bool not in kinds and Any not in leaves


def _element_annotation(annotation: Any, index: int, length: int) -> Any:
    """What the ``index``-th of ``length`` items of a list written for ``annotation`` is validated as, or Any."""
    for leaf in _leaves(annotation):
        origin, args = typing.get_origin(leaf), typing.get_args(leaf)
        if origin in (list, tuple, set, frozenset, Sequence):
            if origin is tuple and args and args[-1] is not Ellipsis:
                return args[index] if len(args) == length else Any
            return args[0] if args else Any
    return Any


def booleans_for_numbers(model: type[BaseModel], data: Any, loc: tuple[Any, ...] = ()) -> list[tuple[tuple, bool]]:
    """Where ``data``, written for ``model``, has YAML's true or false in a field that takes numbers.

    Pydantic's lax mode reads them as 1 and 0 without a word (``episodes: true`` would run one episode); each is
    returned as (location, value) for a located problem. Nested models, lists and mappings are walked.
    """
    found: list[tuple[tuple, bool]] = []

    def walk(annotation: Any, value: Any, where: tuple[Any, ...]) -> None:
        inner = submodel(annotation)
        if inner is not None and isinstance(value, dict):
            found.extend(booleans_for_numbers(inner, value, where))
        elif isinstance(value, bool):
            if _number_only(annotation):
                found.append((where, value))
        elif isinstance(value, list):
            for index, item in enumerate(value):
                walk(_element_annotation(annotation, index, len(value)), item, (*where, index))
        elif isinstance(value, dict):
            mappings = [leaf for leaf in _leaves(annotation) if typing.get_origin(leaf) is dict]
            if mappings and len(typing.get_args(mappings[0])) == 2:
                for key, item in value.items():
                    walk(typing.get_args(mappings[0])[1], item, (*where, key))

    if isinstance(data, dict):
        for key, value in data.items():
            field = model.model_fields.get(key) if isinstance(key, str) else None
            if field is not None:
                walk(field.annotation, value, (*loc, key))
    return found


def node_line(root: yaml.Node | None, loc: tuple[Any, ...]) -> int:
    """1-based line of the deepest node along ``loc`` that exists in the YAML."""
    node, line = root, (root.start_mark.line + 1 if root is not None else 1)
    for part in loc:
        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                if key.value == str(part):
                    line, node = key.start_mark.line + 1, value
                    break
            else:
                return line
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int) and part < len(node.value):
            node = node.value[part]
            line = node.start_mark.line + 1
        else:
            return line
    return line


def closest_hint(word: str, candidates: Iterable[str], prefix: str = "") -> str:
    """' (did you mean 'X'?)' for the candidate closest to ``word``, or ''."""
    close = difflib.get_close_matches(word, list(candidates), n=1)
    return f" (did you mean '{prefix}{close[0]}'?)" if close else ""


def _did_you_mean(model: type[BaseModel], loc: tuple[Any, ...], key: str) -> str:
    """A hint for an unknown key, from the fields of the model the key sits in."""
    for part in loc[:-1]:
        field = model.model_fields.get(str(part)) if isinstance(part, str) else None
        inner = submodel(field.annotation) if field else None
        if inner is None:
            return ""
        model = inner
    return closest_hint(key, model.model_fields)


_UNION_MEMBERS = {"GridParameter", "RandomParameter", "SeedRange", "list[int]", "[key]"}
_VALIDATOR_TAG = re.compile(r"^function-(after|before|wrap|plain)\[")


def _is_tag(part: Any) -> bool:
    """A location part pydantic adds for a union member or a validator function: not a YAML key."""
    return isinstance(part, str) and (part in _UNION_MEMBERS or bool(_VALIDATOR_TAG.match(part)))


def _member(part: Any) -> str | None:
    """The union member a location part names, also inside a validator tag ("function-after[f(), Model]")."""
    if not isinstance(part, str):
        return None
    if part in _UNION_MEMBERS - {"[key]"}:
        return part
    inner = _VALIDATOR_TAG.match(part) and part.rstrip("]").rsplit(", ", 1)[-1]
    return inner if inner in _UNION_MEMBERS else None


def _meant_member(value: Any) -> str | None:
    """The union member a value was written as: the others' complaints about it are noise."""
    if isinstance(value, list):
        return "list[int]"
    if isinstance(value, dict):
        if "distribution" in value:
            return "RandomParameter"
        if "values" in value:
            return "GridParameter"
        if "first" in value or "count" in value:
            return "SeedRange"
    return None


def _other_member(loc: tuple[Any, ...], data: Any) -> bool:
    """Whether an error is about a union member other than the one the written value meant."""
    node = data
    for part in loc:
        member = _member(part)
        if member is not None:
            meant = _meant_member(node)
            return meant is not None and member != meant
        if _is_tag(part):
            continue
        if isinstance(node, dict):
            node = node.get(part)
        elif isinstance(node, list) and isinstance(part, int) and part < len(node):
            node = node[part]
        else:
            return False
    return False


def problems_from(
    error: ValidationError, file: str, root, model: type[BaseModel], prefix=(), data: Any = None
) -> list[SweepProblem]:
    """Pydantic's errors as located problems (``prefix`` places the validated model inside the file; ``data``,
    the validated input, tells which member of a union a value was written as)."""
    problems = []
    for item in error.errors():
        if data is not None and _other_member(item["loc"], data):
            continue
        # Pydantic names union members and validator functions in the location; they are not YAML keys.
        loc = tuple(p for p in item["loc"] if not _is_tag(p))
        message = item["msg"].removeprefix("Value error, ")
        if item["type"] == "extra_forbidden":
            message = f"unknown key{_did_you_mean(model, loc, str(loc[-1]))}"
        elif item["type"] == "missing":
            message = "required key is missing"
        elif item["type"] in ("model_type", "model_attributes_type", "dict_type"):
            # Pydantic's text names the model class ("... or instance of Metric"), which a sweep's author never wrote.
            message = f"expected a mapping of keys (key: value), got {item['input']!r}"
        loc = tuple(prefix) + loc
        path = ".".join(str(p) for p in loc) or "(file)"
        problems.append(SweepProblem(file, node_line(root, loc), path, message))
    return problems


def sorted_problems(problems: list[SweepProblem]) -> list[SweepProblem]:
    return sorted(dict.fromkeys(problems), key=lambda p: p.line)


def read_yaml(path: Path) -> tuple[str, Any, yaml.Node | None]:
    """(text, parsed data, root node for locating problems); unreadable, binary, huge or malformed files raise."""
    file = str(path)
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise SweepError([SweepProblem(file, 1, "(file)", (
                f"the file is {size:,} bytes, above the {MAX_FILE_BYTES:,}-byte limit of sweep files; "
                "write long seed lists as seeds: {first: 0, count: N}"
            ))])  # fmt: skip
        raw_bytes = path.read_bytes()
    except OSError as error:
        raise SweepError([SweepProblem(file, 1, "(file)", f"cannot read: {error.strerror or error}")]) from None
    if b"\x00" in raw_bytes:
        raise SweepError([SweepProblem(file, 1, "(file)", "binary file, not a YAML sweep")])
    try:
        text = raw_bytes.decode("utf-8")
    except UnicodeDecodeError as error:
        raise SweepError([SweepProblem(file, 1, "(file)", f"not UTF-8 text ({error.reason})")]) from None
    loader_class = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        loader = loader_class(text)
        try:
            root = loader.get_single_node()
            data = loader.construct_document(root) if root is not None else None
        finally:
            loader.dispose()
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        line = mark.line + 1 if mark is not None else 1
        reason = getattr(error, "problem", None) or str(error)
        context, context_mark = getattr(error, "context", None), getattr(error, "context_mark", None)
        if context and context_mark is not None and context_mark.line + 1 != line:
            reason += f" ({context} on line {context_mark.line + 1})"
        raise SweepError([SweepProblem(file, line, "(yaml)", f"YAML syntax error: {reason}")]) from None
    repeated = duplicate_keys(file, root)
    if repeated:
        raise SweepError(repeated)
    return text, data, root


def duplicate_keys(file: str, root: yaml.Node | None, path: tuple[str, ...] = ()) -> list[SweepProblem]:
    """A key written twice in one mapping: YAML loaders keep the last silently, so one of the two settings a
    user wrote would be dropped without a word."""
    problems: list[SweepProblem] = []
    if isinstance(root, yaml.MappingNode):
        first: dict[str, int] = {}
        for key, value in root.value:
            name = str(key.value)
            line = key.start_mark.line + 1
            where = ".".join((*path, name))
            if name in first:
                problems.append(SweepProblem(file, line, where, (
                    f"{name!r} is written twice in this mapping (first on line {first[name]}); keep one"
                )))  # fmt: skip
            else:
                first[name] = line
            problems += duplicate_keys(file, value, (*path, name))
    elif isinstance(root, yaml.SequenceNode):
        for index, item in enumerate(root.value):
            problems += duplicate_keys(file, item, (*path, str(index)))
    return problems
