"""Exportable state as plain numpy arrays plus JSON, never pickle.

Every stateful part of neural APSP (networks, Adam moments, count sketches,
replay buffers, random generators) exports a :class:`State`: a flat dict of
numpy arrays and a JSON-serialisable dict. The service can ship both between
actors (the DistanceTrainer and the learner exchange weights once per
iteration) and checkpoint them with :func:`save_state` (``.npz`` written with
``allow_pickle=False`` plus a ``.json`` file).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch


class State(NamedTuple):
    """A part's exported state."""

    arrays: dict[str, np.ndarray]
    """Numeric content, by flat key."""
    meta: dict[str, Any]
    """JSON-serialisable content (counters, RNG states, optimiser hyper-parameters)."""


def merge_states(**parts: State) -> State:
    """One State from named parts; keys become ``part/key``."""
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] = {}
    for name, part in parts.items():
        arrays.update({f"{name}/{key}": value for key, value in part.arrays.items()})
        meta[name] = part.meta
    return State(arrays, meta)


def with_prefix(arrays: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    """The arrays whose keys start with ``prefix``, with the prefix removed."""
    return {key[len(prefix) :]: value for key, value in arrays.items() if key.startswith(prefix)}


def part_of(state: State, name: str) -> State:
    """The named part of a merged State (arrays under ``name/``, meta under ``name``)."""
    return State(with_prefix(state.arrays, f"{name}/"), state.meta[name])


def save_state(state: State, path: str | Path) -> None:
    """Write ``path.npz`` (no pickled objects) and ``path.json``."""
    path = Path(path)
    np.savez(path.with_suffix(".npz"), **state.arrays)
    path.with_suffix(".json").write_text(json.dumps(state.meta))


def load_state(path: str | Path) -> State:
    """Read a State written by :func:`save_state`."""
    path = Path(path)
    with np.load(path.with_suffix(".npz"), allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    return State(arrays, json.loads(path.with_suffix(".json").read_text()))


# ------------------------------------------------------------- torch parts
def module_arrays(module: torch.nn.Module) -> dict[str, np.ndarray]:
    """Parameters and buffers of a module as numpy copies."""
    return {key: value.detach().cpu().numpy().copy() for key, value in module.state_dict().items()}


def load_module_arrays(module: torch.nn.Module, arrays: dict[str, np.ndarray]) -> None:
    """Inverse of :func:`module_arrays` (strict: every key must match)."""
    module.load_state_dict({key: torch.as_tensor(np.asarray(value)) for key, value in arrays.items()}, strict=True)


def optimizer_state(optimizer: torch.optim.Optimizer) -> State:
    """Adam (or any per-parameter tensor) optimiser state without pickle."""
    full = optimizer.state_dict()
    arrays: dict[str, np.ndarray] = {}
    slots: dict[str, list[str]] = {}
    for index, entry in full["state"].items():
        slots[str(index)] = sorted(entry)
        for name, value in entry.items():
            tensor = value if isinstance(value, torch.Tensor) else torch.tensor(value)
            arrays[f"{index}/{name}"] = tensor.detach().cpu().numpy().copy()
    return State(arrays, {"param_groups": full["param_groups"], "slots": slots})


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: State) -> None:
    """Inverse of :func:`optimizer_state`."""
    entries = {}
    for index, names in state.meta["slots"].items():
        entries[int(index)] = {name: torch.as_tensor(state.arrays[f"{index}/{name}"]) for name in names}
    optimizer.load_state_dict({"state": entries, "param_groups": state.meta["param_groups"]})


# --------------------------------------------------------------- generators
def generator_state(rng: np.random.Generator) -> dict[str, Any]:
    """A numpy Generator's bit-generator state (plain ints and strings, JSON-safe)."""
    return rng.bit_generator.state


def restore_generator(rng: np.random.Generator, meta: dict[str, Any]) -> None:
    """Put a numpy Generator back into an exported state."""
    rng.bit_generator.state = meta


def torch_generator_array(generator: torch.Generator) -> np.ndarray:
    """A torch Generator's state as a uint8 array."""
    return generator.get_state().numpy().copy()


def restore_torch_generator(generator: torch.Generator, array: np.ndarray) -> None:
    """Inverse of :func:`torch_generator_array`."""
    generator.set_state(torch.as_tensor(np.asarray(array, dtype=np.uint8)))
