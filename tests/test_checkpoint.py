"""Checkpoints: lossless trees, no unpickling ever, atomic and verified in the artifact store."""

from __future__ import annotations

import io
import json
import os
import pickle
import zipfile

import numpy as np
import pytest

from orchestrator.tracking import Tracker, default_tracking_uri
from workers import checkpoint
from workers.checkpoint import CheckpointError


class RunsCode:
    """Unpickling this object runs a shell command (what an attacker would plant)."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_tree_round_trip_keeps_arrays_values_and_structure():
    rng = np.random.default_rng(5)
    rng.normal(size=3)
    tree = {
        "weights": {"layer": np.arange(6, dtype=np.float32).reshape(2, 3), "bias": np.zeros(0)},
        "step": 7,
        "name": "mpc",
        "flags": [True, None, 1.5],
        "empty": {},
        "rng": checkpoint.rng_state(rng),
    }
    back = checkpoint.from_bytes(checkpoint.to_bytes(tree))
    np.testing.assert_array_equal(back["weights"]["layer"], tree["weights"]["layer"])
    assert back["weights"]["layer"].dtype == np.float32 and back["weights"]["bias"].shape == (0,)
    assert (back["step"], back["name"], back["flags"], back["empty"]) == (7, "mpc", [True, None, 1.5], {})
    assert checkpoint.restore_rng(back["rng"]).normal() == rng.normal()


def test_torch_state_dicts_survive_as_arrays():
    import torch

    model = torch.nn.Linear(3, 2)
    optimiser = torch.optim.Adam(model.parameters())
    model(torch.ones(4, 3)).sum().backward()
    optimiser.step()
    tree = {"model": checkpoint.tensors_to_arrays(model.state_dict()),
            "optimiser": checkpoint.tensors_to_arrays(optimiser.state_dict())}  # fmt: skip
    back = checkpoint.from_bytes(checkpoint.to_bytes(tree))
    other = torch.nn.Linear(3, 2)
    other.load_state_dict(checkpoint.arrays_to_tensors(back["model"]))
    other_optimiser = torch.optim.Adam(other.parameters())
    other_optimiser.load_state_dict(checkpoint.arrays_to_tensors(back["optimiser"]))
    assert torch.equal(other.weight, model.weight)
    assert torch.equal(
        other_optimiser.state_dict()["state"][0]["exp_avg"], optimiser.state_dict()["state"][0]["exp_avg"]
    )


def test_object_arrays_cannot_be_written():
    with pytest.raises(TypeError, match="object arrays"):
        checkpoint.to_bytes({"bad": np.array([object()], dtype=object)})


def test_a_planted_pickle_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "pwned"
    with pytest.raises(CheckpointError, match="not a checkpoint archive"):
        checkpoint.from_bytes(pickle.dumps(RunsCode(str(marker))))
    assert not marker.exists()


def test_an_npz_with_a_pickled_member_is_refused_and_runs_nothing(tmp_path):
    """An archive that looks right but holds an object array (numpy would unpickle it if allowed)."""
    marker = tmp_path / "pwned"
    buffer = io.BytesIO()
    np.savez(buffer, payload=np.array([RunsCode(str(marker))], dtype=object), __json__=np.frombuffer(b"{}", np.uint8))
    with pytest.raises(CheckpointError, match="refusing"):
        checkpoint.from_bytes(buffer.getvalue())
    assert not marker.exists()


def test_truncated_bytes_are_refused():
    data = checkpoint.to_bytes({"x": np.arange(1000.0)})
    with pytest.raises(CheckpointError):
        checkpoint.from_bytes(data[: len(data) // 2])


def test_load_reads_a_checkpoint_file(tmp_path):
    path = tmp_path / "state.npz"
    path.write_bytes(checkpoint.to_bytes({"program": {"weights": np.ones(3)}}))
    np.testing.assert_array_equal(checkpoint.load(path)["program"]["weights"], np.ones(3))


@pytest.fixture
def store(tmp_path):
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("ckpt", "ckpt", "hash", "name: ckpt\n", {}, "dev")
    run_id = tracker.start_trial(parent, "key", "trial", {}, {})
    return tracker, run_id


def state_file(tracker: Tracker, run_id: str, round_index: int):
    from pathlib import Path
    from urllib.parse import urlparse

    root = Path(urlparse(tracker.client.get_run(run_id).info.artifact_uri).path)
    return root / "checkpoints" / f"round_{round_index:06d}"


def test_the_store_keeps_the_newest_checkpoints_and_verifies_them(store):
    tracker, run_id = store
    for index in range(5):
        tracker.save_checkpoint(run_id, index, checkpoint.to_bytes({"round": index}))
    assert tracker.list_files(run_id, "checkpoints") == [f"checkpoints/round_{i:06d}" for i in (2, 3, 4)]
    stored, notes = tracker.load_checkpoint(run_id)
    assert stored.round_index == 4 and checkpoint.from_bytes(stored.data)["round"] == 4 and notes == []


def test_a_trial_gone_back_past_its_newest_checkpoints_keeps_the_ones_it_writes_anew(store):
    """Rounds 5-7 were refused and the trial began again: its new checkpoints are older than those, yet each is
    the one a later loss must restart from, so pruning counts only the checkpoints up to the one written."""
    tracker, run_id = store
    for index in (5, 6, 7):
        tracker.save_checkpoint(run_id, index, checkpoint.to_bytes({"round": index}))
    for index in range(5):
        tracker.save_checkpoint(run_id, index, checkpoint.to_bytes({"round": index, "again": True}))
    kept = [f"checkpoints/round_{i:06d}" for i in (2, 3, 4, 5, 6, 7)]
    assert tracker.list_files(run_id, "checkpoints") == kept
    stored, _ = tracker.load_checkpoint(run_id, skip={5, 6, 7})
    assert stored.round_index == 4 and checkpoint.from_bytes(stored.data)["again"]


def test_a_truncated_checkpoint_falls_back_to_the_previous_round(store):
    tracker, run_id = store
    for index in range(3):
        tracker.save_checkpoint(run_id, index, checkpoint.to_bytes({"round": index, "data": np.arange(100.0)}))
    latest = state_file(tracker, run_id, 2) / "state.npz"
    latest.write_bytes(latest.read_bytes()[:200])  # a crash while copying
    stored, notes = tracker.load_checkpoint(run_id)
    assert stored.round_index == 1 and "round 2 does not match its manifest" in notes[0]


def test_a_checkpoint_without_manifest_is_incomplete_and_skipped(store):
    tracker, run_id = store
    for index in range(2):
        tracker.save_checkpoint(run_id, index, checkpoint.to_bytes({"round": index}))
    (state_file(tracker, run_id, 1) / "manifest.json").unlink()  # the writer died between the two files
    stored, notes = tracker.load_checkpoint(run_id)
    assert stored.round_index == 0 and "incomplete" in notes[0]


def test_a_pickle_with_a_forged_manifest_passes_the_store_but_not_the_reader(store, tmp_path):
    """The checksum catches accidents; the reader's refusal to unpickle catches an attacker."""
    tracker, run_id = store
    tracker.save_checkpoint(run_id, 0, checkpoint.to_bytes({"round": 0}))
    marker = tmp_path / "pwned"
    payload = pickle.dumps(RunsCode(str(marker)))
    folder = state_file(tracker, run_id, 0)
    (folder / "state.npz").write_bytes(payload)
    manifest = {"round": 0, "bytes": len(payload), "sha256": checkpoint.digest(payload)}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    stored, _ = tracker.load_checkpoint(run_id)
    with pytest.raises(CheckpointError):
        checkpoint.from_bytes(stored.data)
    assert not marker.exists()
    assert not zipfile.is_zipfile(io.BytesIO(stored.data))
