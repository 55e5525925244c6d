"""Checkpoints that can be read back without running anyone's code.

A checkpoint is a tree of nested dicts whose leaves are numpy arrays or
JSON values (numbers, strings, booleans, None and lists of them). On disk it
is one ``.npz`` archive: every array under its path in the tree, and the JSON
leaves as one UTF-8 document in the member ``__json__``. Reading uses
``numpy.load(allow_pickle=False)`` and ``json.loads`` only, so a file planted
in a shared artifact store cannot make a worker unpickle (and so run) code:
object arrays and pickles are refused with :class:`CheckpointError`.

Torch state dicts go through :func:`tensors_to_arrays` and back; optimiser
states are trees of tensors and numbers and fit the same format.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

JSON_MEMBER = "__json__"
SEPARATOR = "/"

Tree = dict[str, Any]
"""A checkpoint tree: nested dicts, leaves numpy arrays or JSON values."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be read safely (corrupt, truncated, or not a checkpoint at all)."""


def _flatten(tree: Mapping[str, Any], prefix: str, arrays: dict[str, np.ndarray], values: dict[str, Any]) -> None:
    for key, value in tree.items():
        if not isinstance(key, str) or SEPARATOR in key or key == JSON_MEMBER:
            raise TypeError(f"checkpoint keys are strings without {SEPARATOR!r}, got {key!r}")
        path = prefix + key
        if isinstance(value, Mapping):
            if not value:
                values[path] = {}
            _flatten(value, path + SEPARATOR, arrays, values)
        elif isinstance(value, np.ndarray):
            if value.dtype == object:
                raise TypeError(f"{path}: object arrays cannot be checkpointed safely")
            arrays[path] = value
        else:
            values[path] = _json_value(path, value)


def _json_value(path: str, value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, list | tuple):
        return [_json_value(path, item) for item in value]
    raise TypeError(f"{path}: cannot checkpoint a {type(value).__name__} (use arrays, numbers, strings or dicts)")


def _insert(tree: Tree, path: str, value: Any) -> None:
    *parents, leaf = path.split(SEPARATOR)
    node = tree
    for part in parents:
        node = node.setdefault(part, {})
    if isinstance(value, dict) and leaf in node:
        return  # an empty dict marker for a node that has children
    node[leaf] = value


def to_bytes(tree: Mapping[str, Any]) -> bytes:
    """Serialise a checkpoint tree to the bytes of an ``.npz`` archive."""
    arrays: dict[str, np.ndarray] = {}
    values: dict[str, Any] = {}
    _flatten(tree, "", arrays, values)
    buffer = io.BytesIO()
    document = np.frombuffer(json.dumps(values, sort_keys=True).encode(), dtype=np.uint8)
    np.savez(buffer, **arrays, **{JSON_MEMBER: document})
    return buffer.getvalue()


def from_bytes(data: bytes) -> Tree:
    """Read a checkpoint tree written by :func:`to_bytes`, refusing anything that would need unpickling."""
    if not zipfile.is_zipfile(io.BytesIO(data)):
        raise CheckpointError("not a checkpoint archive (expected an .npz written by icemlab); refusing to load it")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            names = list(archive.files)
            if JSON_MEMBER not in names:
                raise CheckpointError("checkpoint archive has no metadata member; refusing to load it")
            tree: Tree = {}
            values = json.loads(archive[JSON_MEMBER].tobytes().decode())
            for name in names:
                if name != JSON_MEMBER:
                    _insert(tree, name, archive[name])
    except CheckpointError:
        raise
    except (ValueError, OSError, zipfile.BadZipFile, EOFError, json.JSONDecodeError, UnicodeDecodeError) as error:
        # numpy refuses object arrays (pickles) with a ValueError when allow_pickle is False.
        raise CheckpointError(f"unreadable checkpoint ({error}); refusing to load it") from None
    for path, value in values.items():
        _insert(tree, path, value)
    return tree


def load(path: str | Path) -> Tree:
    """Read a checkpoint file, e.g. ``mlruns/<run>/artifacts/checkpoints/round_000003/state.npz``.

    The one-liner for a trained model: ``from workers.checkpoint import load; state = load(path)``;
    ``state["program"]`` holds the method's state (weights as numpy arrays).
    """
    return from_bytes(Path(path).read_bytes())


def digest(data: bytes) -> str:
    """sha256 hex digest, the checksum a checkpoint's manifest records."""
    return hashlib.sha256(data).hexdigest()


def tensors_to_arrays(state: Mapping[str, Any]) -> Tree:
    """A torch state dict (possibly nested, e.g. an optimiser's) with every tensor as a numpy array.

    Integer keys (optimiser parameter ids) become strings; :func:`arrays_to_tensors`
    turns them back.
    """
    import torch

    def convert(value: Any) -> Any:
        if isinstance(value, torch.Tensor):
            return value.detach().cpu().numpy().copy()
        if isinstance(value, Mapping):
            return {f"#{k}" if isinstance(k, int) else str(k): convert(v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            if all(not isinstance(v, Mapping | torch.Tensor) for v in value):
                return list(value)
            return {f"@{i}": convert(v) for i, v in enumerate(value)}
        return value

    return convert(state)


def arrays_to_tensors(tree: Mapping[str, Any]) -> dict[Any, Any]:
    """Inverse of :func:`tensors_to_arrays`: arrays become tensors, '#3' keys ints, '@i' dicts lists."""
    import torch

    def convert(value: Any) -> Any:
        if isinstance(value, np.ndarray):
            return torch.from_numpy(np.array(value))
        if isinstance(value, Mapping):
            if value and all(k.startswith("@") for k in value):
                return [convert(value[f"@{i}"]) for i in range(len(value))]
            return {int(k[1:]) if k.startswith("#") else k: convert(v) for k, v in value.items()}
        return value

    return convert(tree)


def rng_state(rng: np.random.Generator) -> Tree:
    """A numpy Generator's state as JSON values (bit generator name and its integers)."""
    return json.loads(json.dumps(rng.bit_generator.state))


def restore_rng(state: Mapping[str, Any]) -> np.random.Generator:
    """A numpy Generator continuing exactly where :func:`rng_state` captured it."""
    bit_generator = getattr(np.random, state["bit_generator"])()
    bit_generator.state = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in state.items()}
    return np.random.Generator(bit_generator)
