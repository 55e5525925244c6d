"""The command line without Ray: help, validation errors, shipped sweeps, schema."""

from __future__ import annotations

import json
import re
import socket
from pathlib import Path

import pytest
import yaml
from helpers import cli, write_sweep

from orchestrator.cli import main
from orchestrator.sweep import SweepError, load_sweep, sweep_json_schema

ROOT = Path(__file__).resolve().parents[1]
PROBLEM_LINE = re.compile(r"^(?P<file>[^:]+):(?P<line>\d+): (?P<path>[^:]+): (?P<message>.+)$")
COMMANDS = ["run", "validate", "status", "report", "reproduce", "ui", "bench", "tasks", "schema"]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([command, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert f"usage: icemlab {command}" in out and len(out.splitlines()) > 3


def test_output_cut_short_by_a_closed_pipe_ends_quietly(tmp_path):
    """``icemlab schema | head -1``: the reader leaves early; no traceback, the shell's exit status for SIGPIPE."""
    import subprocess
    import sys

    command = f"'{sys.executable}' -m orchestrator.cli schema | head -1; echo \"status ${{PIPESTATUS[0]}}\" >&2"
    result = subprocess.run(["bash", "-c", command], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert result.stdout == "{\n"
    assert "Traceback" not in result.stderr and "BrokenPipeError" not in result.stderr, result.stderr
    assert "status 141" in result.stderr


def test_top_level_help_shows_the_main_commands(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "icemlab run sweeps/quickstart.yaml" in out and all(c in out for c in ("run", "validate", "bench"))


BAD_SWEEPS = {
    # name: (file text, expected (line, path) of the first problem, message fragment)
    "yaml_syntax": ("name: x\ntask: point_reach\nbase:\n  planner: {budget: 100\n", (5, "(yaml)"), "YAML syntax error"),
    "empty": ("", (1, "(file)"), "empty sweep file"),
    "not_a_mapping": ("- just\n- a list\n", (1, "(file)"), "mapping"),
    "unknown_key": (
        "name: x\ntask: point_reach\nbase:\n  planner:\n    budgte: 100\n",
        (5, "base.planner.budgte"),
        "did you mean 'budget'",
    ),
    "unknown_top_key": ("name: x\ntask: point_reach\nseed: [1]\n", (3, "seed"), "did you mean 'seeds'"),
    "wrong_type": (
        "name: x\ntask: point_reach\nbase:\n  planner:\n    budget: lots\n",
        (5, "base.planner.budget"),
        "integer",
    ),
    "budget_below_2k": (
        "name: x\ntask: point_reach\nbase:\n  planner:\n    budget: 15\n",
        (5, "base.planner.budget"),
        "below 2K",
    ),
    "negative_seed": ("name: x\ntask: point_reach\nseeds: [0, -3]\n", (3, "seeds"), ">= 0"),
    "beta_out_of_range": (
        "name: x\ntask: point_reach\nbase:\n  planner:\n    noise_beta: 6\n",
        (5, "base.planner.noise_beta"),
        "less than or equal to 5",
    ),
    "horizon_zero": (
        "name: x\ntask: point_reach\nbase:\n  planner:\n    horizon: 0\n",
        (5, "base.planner.horizon"),
        "greater than or equal to 1",
    ),
    "unknown_task": ("name: x\ntask: halfcheetah_runing\n", (2, "task"), "did you mean 'halfcheetah_running'"),
    "swept_unknown_task": (
        "name: x\ntask: point_reach\nparameters:\n  task:\n    values: [point_reach, door_spars]\n",
        (4, "task"),
        "did you mean 'door_sparse'",
    ),
    "swept_bad_budget": (
        "name: x\ntask: point_reach\nparameters:\n  planner.budget:\n    values: [5, 100]\n",
        (4, "planner.budget"),
        "below 2K",
    ),
    "unknown_parameter_path": (
        "name: x\ntask: point_reach\nparameters:\n  planner.sigma:\n    values: [0.3]\n",
        (4, "parameters.planner.sigma"),
        "did you mean 'planner.sigma_init'",
    ),
    "unknown_task_option": (
        "name: x\ntask: door_sparse\nbase:\n  task_options:\n    velocity: qvel\n",
        (5, "task_options.velocity"),
        "door_sparse has no option 'velocity' (did you mean 'velocity_term'?); its options: ",
    ),
    "bad_task_option_value": (
        "name: x\ntask: halfcheetah_running\nparameters:\n  task_options.flip_penalty:\n    values: [10, -1]\n",
        (4, "task_options.flip_penalty"),
        "greater than or equal to 0",
    ),
    "variant_bad_budget": (
        "name: x\ntask: point_reach\nvariants:\n  - name: a\n  - name: b\n    planner.budget: 5\n",
        (6, "planner.budget"),
        "below 2K",
    ),
    "variant_without_name": (
        "name: x\ntask: point_reach\nvariants:\n  - name: a\n  - planner.budget: 50\n",
        (5, "variants.1"),
        "a variant needs a 'name'",
    ),
    "baseline_not_a_variant": (
        "name: x\ntask: point_reach\nbaseline: ful\nvariants:\n  - name: full\n  - name: no-elites\n",
        (3, "baseline"),
        "baseline 'ful' is not a variant of this sweep; its variants: full, no-elites",
    ),
    "key_written_twice": (
        "name: x\ntask: point_reach\nbase:\n  planner: {budget: 100}\n  planner: {budget: 300}\n",
        (5, "base.planner"),
        "'planner' is written twice in this mapping (first on line 4)",
    ),
    "variant_replaces_a_base_block": (
        "name: x\ntask: point_reach\nbase:\n  planner: {horizon: 10, budget: 100}\nvariants:\n"
        "  - name: a\n  - {name: b, planner: {budget: 50}}\n",
        (7, "planner"),
        "variant 'b' replaces the whole of base's planner, dropping planner.horizon; "
        "to change single fields, set them by dotted path (e.g. planner.budget)",
    ),
    "grid_value_replaces_a_base_block": (
        "name: x\ntask: point_reach\nbase:\n  planner: {horizon: 10}\nparameters:\n"
        "  planner:\n    values: [{horizon: 10}, {budget: 50}]\n",
        (6, "parameters.planner"),
        "parameter 'planner' replaces the whole of base's planner, dropping planner.horizon",
    ),
    "budget_beside_a_full_schedule": (
        "name: x\ntask: point_reach\nbase:\n  planner: {budget: 200}\nvariants:\n"
        "  - {name: a, planner.iterations: 3, planner.population: 50}\n",
        (4, "planner.budget"),
        "budget 200 would be ignored: iterations and population are both given",
    ),
    "elite_reuse_that_reuses_none": (
        "name: x\ntask: point_reach\nalgorithm: cem_mpc\nvariants:\n  - name: a\n"
        "  - {name: keep, planner.keep_elites: true}\n",
        (6, "planner.keep_elites"),
        "= 0 elites, so it would change nothing",
    ),
    "task_of_another_method": (
        "name: x\ntask: halfcheetah_running\nmethod: mbrl\nbase:\n  iterations: 2\n",
        (2, "task"),
        "method mbrl plans on a learned model of a chapter-5 task",
    ),
    "metric_not_a_mapping": (
        "name: x\ntask: point_reach\nmetric: episode_return\n",
        (3, "metric"),
        "expected a mapping of keys (key: value), got 'episode_return'",
    ),
    "resources_not_a_mapping": ("name: x\ntask: point_reach\nresources: 4\n", (3, "resources"), "expected a mapping"),
    "metric_name_a_list": ("name: x\ntask: point_reach\nmetric: {name: [success]}\n", (3, "metric.name"), "string"),
    "variant_task_a_list": (
        "name: x\ntask: point_reach\nvariants:\n  - {name: a, task: [door]}\n",
        (4, "task"),
        "unknown task \"['door']\"",
    ),
    "variant_algorithm_a_list": (
        "name: x\ntask: point_reach\nvariants:\n  - {name: a, algorithm: [cem]}\n",
        (4, "planner.algorithm"),
        "Input should be 'icem', 'cem', 'cem_mpc' or 'cem_pets'",
    ),
    "variant_task_options_a_list": (
        "name: x\ntask: halfcheetah_running\nvariants:\n  - {name: a, task_options: [flip_penalty]}\n",
        (4, "task_options"),
        "task_options is a mapping of option names to values",
    ),
    "task_option_named_by_a_number": (
        "name: x\ntask: halfcheetah_running\nvariants:\n  - name: a\n    task_options: {1: 2}\n",
        (5, "task_options"),
        "task_options is a mapping of option names to values",
    ),
    "random_range_to_infinity": (
        "name: x\ntask: point_reach\nparameters:\n"
        "  planner.sigma_init: {distribution: uniform, low: 0.1, high: .inf}\n",
        (4, "parameters.planner.sigma_init.high"),
        "finite number",
    ),
    "random_range_wider_than_a_float": (
        "name: x\ntask: point_reach\nparameters:\n"
        "  planner.sigma_init: {distribution: uniform, low: -1.0e308, high: 1.0e308}\n",
        (4, "parameters.planner.sigma_init"),
        "low and high must be finite and a finite distance apart",
    ),
    "randint_beyond_64_bits": (
        "name: x\ntask: point_reach\nparameters:\n  planner.horizon: {distribution: randint, low: 1, high: 1.0e30}\n",
        (4, "parameters.planner.horizon"),
        "randint bounds must be within +-2**62",
    ),
    "randint_of_fractions": (
        "name: x\ntask: point_reach\nparameters:\n  planner.horizon: {distribution: randint, low: 1.5, high: 9}\n",
        (4, "parameters.planner.horizon"),
        "whole-number bounds",
    ),
    "budget_beyond_a_million": (
        "name: x\ntask: point_reach\nbase:\n  planner: {budget: 123456789}\n",
        (4, "base.planner.budget"),
        "less than or equal to 1000000",
    ),
    "infinite_setting": (
        "name: x\ntask: point_reach\nbase:\n  planner: {sigma_init: .inf}\n",
        (4, "base.planner.sigma_init"),
        "finite number",
    ),
    "nan_task_option": (
        "name: x\ntask: noisy_fetch_pick_place\nbase:\n  task_options: {noise_std: .nan}\n",
        (4, "task_options.noise_std"),
        "finite number",
    ),
    "seed_beyond_31_bits": ("name: x\ntask: point_reach\nseeds: [18446744073709551616]\n", (3, "seeds"), "at most"),
    "seed_range_beyond_31_bits": (
        "name: x\ntask: point_reach\nseeds: {first: 2147483600, count: 100}\n",
        (3, "seeds"),
        "the last seed, 2147483699, is above the largest, 2147483647",
    ),
    "seeds_as_text": (
        "name: x\ntask: point_reach\nseeds: \"0-4\"\n",
        (3, "seeds"),
        "seeds are a list, e.g. [0, 1, 2], or a range, e.g. {first: 0, count: 5}",
    ),
    "boolean_episodes": (
        "name: x\ntask: point_reach\nbase:\n  episodes: true\n",
        (4, "episodes"),
        "a number is expected, got true",
    ),
    "boolean_grid_value": (
        "name: x\ntask: point_reach\nparameters:\n  planner.horizon: {values: [10, false]}\n",
        (4, "planner.horizon"),
        "a number is expected, got false",
    ),
    "boolean_task_option": (
        "name: x\ntask: noisy_fetch_pick_place\nvariants:\n  - {name: a, task_options.noise_std: true}\n",
        (4, "task_options.noise_std"),
        "a number is expected, got true",
    ),
    "boolean_seed": ("name: x\ntask: point_reach\nseeds: [0, true]\n", (3, "seeds.1"), "a number is expected"),
    "boolean_sweep_count": ("name: x\ntask: point_reach\nretries: true\n", (3, "retries"), "a number is expected"),
    "too_many_trials": (
        "name: x\ntask: point_reach\nmax_trials: 5\nparameters:\n"
        "  planner.budget:\n    values: [50, 100, 150]\nseeds: [0, 1]\n",
        (4, "parameters"),
        "above max_trials = 5",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_SWEEPS))
def test_bad_sweeps_give_located_one_line_errors(case, tmp_path):
    text, (line, path), fragment = BAD_SWEEPS[case]
    sweep = tmp_path / f"{case}.yaml"
    sweep.write_text(text)
    with pytest.raises(SweepError) as error:
        load_sweep(sweep)
    first = error.value.problems[0]
    assert (first.line, first.path) == (line, path)
    assert fragment in first.message
    assert PROBLEM_LINE.match(str(first)), str(first)


def _closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.parametrize(
    "store, fragment",
    [
        ("foo://x", "scheme 'foo' is not one of sqlite, http, https"),
        ("file:///{tmp}/files", "scheme 'file' is not one of"),
        ("sqlite:///{tmp}/directory.db", "directory.db is not a file"),
        ("sqlite:///{tmp}/text.db", "text.db is not an SQLite database"),
        ("http://127.0.0.1:{port}", "no server answers at 127.0.0.1:{port}"),
    ],
)
def test_a_store_that_cannot_be_used_is_named_with_why_and_left_as_it_was(store, fragment, tmp_path):
    """Before, these were MLflow tracebacks, or minutes of retries (a directory or a silent server)."""
    (tmp_path / "directory.db").mkdir()
    (tmp_path / "text.db").write_text("notes\n")
    port = _closed_port()
    uri = store.format(tmp=tmp_path, port=port)
    result = cli("status", "--tracking-uri", uri, cwd=tmp_path, timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert f"icemlab: cannot use the MLflow store {uri}: " in result.stderr
    assert fragment.format(port=port) in result.stderr
    assert "(the URI is --tracking-uri)" in result.stderr
    from_environment = cli("report", "x", cwd=tmp_path, timeout=60, env={"MLFLOW_TRACKING_URI": uri})
    assert from_environment.returncode == 2 and "(the URI is $MLFLOW_TRACKING_URI)" in from_environment.stderr
    assert (tmp_path / "text.db").read_text() == "notes\n" and sorted(p.name for p in tmp_path.iterdir()) == [
        "directory.db", "text.db"
    ]  # fmt: skip


def test_an_empty_file_where_the_store_goes_is_no_store_and_stays_empty(tmp_path):
    (tmp_path / "empty.db").touch()
    result = cli("status", "--tracking-uri", f"sqlite:///{tmp_path}/empty.db?timeout=5", cwd=tmp_path, timeout=60)
    assert result.returncode == 0 and "no sweeps in" in result.stdout
    assert (tmp_path / "empty.db").stat().st_size == 0


def test_a_store_uri_with_a_query_names_the_same_database(tmp_path):
    from orchestrator.tracking import Tracker, default_tracking_uri

    Tracker(default_tracking_uri(tmp_path)).start_sweep("kept", "kept", "hash", "name: kept\n", {}, "dev")
    uri = default_tracking_uri(tmp_path) + "?timeout=5"
    result = cli("status", "kept", "--tracking-uri", uri, cwd=tmp_path, timeout=60)
    assert "sweep kept: RUNNING" in result.stdout, result.stdout + result.stderr


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["validate", "x.yaml", "--cores", "0"], "argument --cores: must be >= 1, got 0"),
        (["run", "x.yaml", "--max-concurrent", "-1"], "argument --max-concurrent: must be >= 1, got -1"),
        (["policy", "p.npz", "--episodes", "0"], "argument --episodes: must be >= 1, got 0"),
        (["policy", "p.npz", "--seed", "-1"], "argument --seed: must be from 0 to 2147483647, got -1"),
        (["policy", "p.npz", "--steps", "-5"], "argument --steps: must be >= 1, got -5"),
        (["reproduce", "r", "--threads", "100000"], "argument --threads: must be from 1 to"),
        (["ui", "--port", "70000"], "argument --port: must be from 1 to 65535, got 70000"),
        (["bench", "--budgets", "100", "0"], "argument --budgets: must be >= 1, got 0"),
        (["policy", "p.npz", "--episodes", "two"], "argument --episodes: expected a whole number, got 'two'"),
    ],
)
def test_numbers_out_of_range_are_refused_before_anything_starts(arguments, message, tmp_path):
    result = cli(*arguments, cwd=tmp_path, timeout=60)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert list(tmp_path.iterdir()) == []


def test_an_output_that_cannot_be_written_is_refused_before_the_work(tmp_path):
    """The report's directory, the policy's frame strip and the model's map are checked first: before, a report
    printed its table and a policy rolled its episodes, then ended in a traceback."""
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "model.npz").write_bytes(b"x")
    report = cli("report", "x", "--output", str(tmp_path / "a_file"), cwd=tmp_path, timeout=60)
    assert report.returncode == 2 and f"--output: {tmp_path / 'a_file'} exists and is not a directory" in report.stderr
    below = cli("report", "x", "--output", str(tmp_path / "a_file" / "sub"), cwd=tmp_path, timeout=60)
    assert below.returncode == 2 and "a_file is not a directory" in below.stderr
    frames = cli("policy", "p.npz", "--frames", str(tmp_path / "missing" / "f.png"), cwd=tmp_path, timeout=60)
    assert frames.returncode == 2 and f"--frames: directory {tmp_path / 'missing'} does not exist" in frames.stderr
    suffix = cli("policy", "p.npz", "--frames", str(tmp_path / "f.txt"), cwd=tmp_path, timeout=60)
    assert suffix.returncode == 2 and "f.txt must end in .png" in suffix.stderr
    model = cli("model", "model.npz", "--task", "bridge_maze", "--output", str(tmp_path), cwd=tmp_path, timeout=60)
    assert model.returncode == 2 and f"--output: {tmp_path} is a directory; name a .png file in it" in model.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "model.npz"]


def problems_of(tmp_path, text: str) -> list[tuple[int, str, str]]:
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(text)
    with pytest.raises(SweepError) as error:
        load_sweep(sweep)
    return [(p.line, p.path, p.message) for p in error.value.problems]


def test_a_union_value_is_judged_as_the_member_it_was_written_as(tmp_path):
    """A random parameter gets the random parameter's complaint only, not a grid's "values missing"; a grid
    parameter and a seed range likewise; pydantic's validator tags stay out of the path."""
    random = "name: x\ntask: point_reach\nparameters:\n  planner.sigma_init:\n    distribution: uniform\n" \
        "    low: 0.7\n    high: 0.3\n"
    assert problems_of(tmp_path, random) == [(4, "parameters.planner.sigma_init", "low (0.7) is above high (0.3)")]
    grid = "name: x\ntask: point_reach\nparameters:\n  planner.sigma_init:\n    values: []\nseeds: {first: 0}\n"
    assert [(line, path) for line, path, _ in problems_of(tmp_path, grid)] == [
        (5, "parameters.planner.sigma_init.values"), (6, "seeds.count")
    ]


def test_malformed_variants_do_not_make_a_baseline_unknown(tmp_path):
    text = "name: x\ntask: point_reach\nbaseline: full\nvariants:\n  - name: full\n  - planner.budget: 50\n"
    assert [message for _, _, message in problems_of(tmp_path, text)] == ["a variant needs a 'name', e.g. - {name: no-colored-noise, planner.noise_beta: 0}"]


def test_binary_file_is_rejected(tmp_path):
    sweep = tmp_path / "binary.yaml"
    sweep.write_bytes(b"\x7fELF\x02\x01\x01\x00\x00\x00")
    with pytest.raises(SweepError, match="binary file"):
        load_sweep(sweep)


def test_every_problem_is_reported_at_once(tmp_path):
    sweep = tmp_path / "many.yaml"
    sweep.write_text("name: x\ntask: point_reach\nbase:\n  planner:\n    horizon: 0\n    budgett: 3\nseeds: [-1]\n")
    with pytest.raises(SweepError) as error:
        load_sweep(sweep)
    assert [p.line for p in error.value.problems] == [5, 6, 7]


@pytest.mark.parametrize(
    "case, unchecked",
    [("unknown_key", True), ("variant_without_name", True), ("too_many_trials", True), ("variant_bad_budget", False),
     ("budget_beside_a_full_schedule", False)],
)
def test_problems_found_before_the_trials_are_checked_say_that_those_checks_did_not_run(tmp_path, case, unchecked):
    """A sweep's own keys and the method's settings are checked before its trials, which need them valid: a
    problem found early says the trials are still to check, so one fix is not taken for the last."""
    sweep = tmp_path / "bad.yaml"
    sweep.write_text(BAD_SWEEPS[case][0])
    with pytest.raises(SweepError) as error:
        load_sweep(sweep)
    assert (error.value.unchecked is not None) == unchecked


def test_run_with_a_bad_sweep_exits_2_and_starts_nothing(tmp_path):
    sweep = tmp_path / "bad.yaml"
    sweep.write_text(BAD_SWEEPS["unknown_key"][0])
    ray_sessions = set(Path("/tmp/ray").glob("session_*")) if Path("/tmp/ray").exists() else set()
    result = cli("run", str(sweep), cwd=tmp_path)
    assert result.returncode == 2
    problems = [line for line in result.stderr.splitlines() if PROBLEM_LINE.match(line)]
    assert problems == [f"{sweep}:5: base.planner.budgte: unknown key (did you mean 'budget'?)"]
    assert "nothing was started" in result.stderr
    assert "not checked yet: each trial's settings" in result.stderr  # the later checks need these fixed
    assert not (tmp_path / "mlflow.db").exists()  # no MLflow store, so no run
    after = set(Path("/tmp/ray").glob("session_*")) if Path("/tmp/ray").exists() else set()
    assert after == ray_sessions  # no Ray session


def test_validate_lists_trials(tmp_path):
    sweep = write_sweep(tmp_path, parameters={"planner.budget": {"values": [50, 100]}}, seeds=[0, 1])
    result = cli("validate", str(sweep), cwd=tmp_path)
    assert result.returncode == 0
    assert "valid, 4 trial(s)" in result.stdout
    # The estimate may calibrate for minutes: the output says so before it starts, and how to skip it.
    lines = result.stdout.splitlines()
    notice = next(i for i, line in enumerate(lines) if "(--no-estimate skips it)" in line)
    assert notice < next(i for i, line in enumerate(lines) if line.startswith("plan: "))


@pytest.mark.parametrize("sweep", sorted(str(p.relative_to(ROOT)) for p in (ROOT / "sweeps").rglob("*.yaml")))
def test_shipped_sweeps_are_valid(sweep):
    loaded = load_sweep(ROOT / sweep)
    assert loaded.trials


def test_quickstart_has_at_least_four_trials():
    assert len(load_sweep(ROOT / "sweeps" / "quickstart.yaml").trials) >= 4


def test_committed_schema_is_current():
    committed = json.loads((ROOT / "sweeps" / "sweep.schema.json").read_text())
    assert committed == json.loads(json.dumps(sweep_json_schema(builtin_only=True))), (
        "sweeps/sweep.schema.json is stale: icemlab schema > sweeps/sweep.schema.json"
    )


def test_schema_describes_every_field():
    schema = sweep_json_schema()
    assert "parameters" in schema["properties"]
    planner = schema["$defs"]["PlannerConfig"]["properties"]
    assert all(field.get("description") for field in planner.values())


def test_trial_keys_ignore_resources_but_not_config(tmp_path):
    a = load_sweep(write_sweep(tmp_path, "a")).trials[0]
    b = load_sweep(write_sweep(tmp_path, "b", resources={"simulation_workers": 2})).trials[0]
    c = load_sweep(write_sweep(tmp_path, "c", seeds=[1])).trials[0]
    assert a.key == b.key != c.key


@pytest.mark.parametrize(
    "sweep, first, last, earlier_reading",
    [
        ("fetch_pick_place", "a5f5dd7184910803", "b51fb7a40058f900", {"planner": {"noise_release": "2.1"}}),
        (
            "razer_bridge_maze",
            "d52a4c09b582765a",
            "df252c548e89626c",
            {
                "model": {"keep_function": False},
                "planner": {"noise_release": "2.1"},
                "task_options": {"unit_quaternion": False},
            },
        ),
        # Pins release "2.1", the release of the trials it compares with: its keys are those of the stored runs.
        ("relocate_contact_margin", "336241e8e1476ee8", "d77398c6ac6c00e9", {}),
        ("razer_noisy_fetch", "ebed66b6819b91c3", "58604de3f2ccae60", {}),  # pins "2.1" too, as its rows ran
        # Its frozen rows ran at the loop's 150 steps before they ran the task's 200.
        ("razer_bridge_maze_compact_small", "57e830e596d8d9c1", "f1b81308b3016272", {"frozen": {"task_options": {}}}),
    ],
)
def test_settings_added_at_their_neutral_default_keep_trial_keys(sweep, first, last, earlier_reading, tmp_path):
    """Keys of shipped sweeps as they were before `planner.noise_release` existed: --resume still finds their
    trials at the behaviour they ran with. A new default that changes the behaviour (the colored noise's
    release "1.1"; the ensemble's `keep_function`) makes new trials; the earlier ones stay reachable at the old
    value."""
    data = yaml.safe_load((ROOT / "sweeps" / "paper" / f"{sweep}.yaml").read_text())
    shipped = load_sweep(ROOT / "sweeps" / "paper" / f"{sweep}.yaml").trials
    for section, values in earlier_reading.items():
        data["base"].setdefault(section, {}).update(values)
    path = tmp_path / f"{sweep}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    trials = load_sweep(path).trials
    assert (trials[0].key, trials[-1].key) == (first, last)
    assert (shipped[0].key == first) == (not earlier_reading)


def test_apex_trials_of_the_earlier_readings_keep_their_keys(tmp_path):
    """APEX's window now counts iterations and relabeling restarts at every state, so the shipped sweep's
    trials are new ones; with `window_counts: episodes` and `relabel_restart: chunk`, the earlier behaviour,
    --resume still finds the trials run before."""
    sweep = yaml.safe_load((ROOT / "sweeps" / "paper" / "apex_fetch.yaml").read_text())
    earlier = ("7677980e0b9d8bb4", "848f08eb2c6baebe")
    shipped = load_sweep(ROOT / "sweeps" / "paper" / "apex_fetch.yaml").trials
    assert shipped[0].key not in earlier and shipped[-1].key not in earlier
    sweep["base"]["window_counts"] = "episodes"
    sweep["base"]["relabel_restart"] = "chunk"
    for added_since in ("evaluation_episodes", "evaluate_every"):  # the sweep evaluates its final policies now
        del sweep["base"][added_since]
    sweep["base"].setdefault("policy", {})["keep_function"] = False
    sweep["base"].setdefault("planner", {})["noise_release"] = "2.1"
    path = tmp_path / "apex_fetch.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    trials = load_sweep(path).trials
    assert (trials[0].key, trials[-1].key) == earlier


def test_the_noise_releases_are_different_trials_and_the_default_is_1_1(tmp_path):
    keys = [
        load_sweep(write_sweep(tmp_path, f"n{i}", base={"planner": {"budget": 50, **release}})).trials[0].key
        for i, release in enumerate(({}, {"noise_release": "1.1"}, {"noise_release": "2.1"}))
    ]
    assert keys[0] == keys[1] != keys[2]


class PastCosts:
    """A store stand-in: the core-seconds per step of past runs, by their exact tags."""

    def __init__(self, *runs: tuple[dict[str, str], float]):
        self.runs, self.asked = runs, []

    def past_costs(self, tags):
        self.asked.append(dict(tags))
        return [cost for run_tags, cost in self.runs if run_tags == tags]


def test_time_estimates_reuse_past_runs_only_at_the_same_horizon_and_particles(tmp_path, monkeypatch):
    """A step's cost grows with the horizon and the particles, so runs that differ in either are not reused."""
    from orchestrator.plan import cost_per_work
    from workers.methods.mpc import MpcProgram

    monkeypatch.setattr(MpcProgram, "calibrate", classmethod(lambda cls, spec, cpus: None))
    icem_50 = {"method": "mpc", "algorithm": "icem", "budget": "50"}
    store = PastCosts(
        ({"task": "point_reach", **icem_50, "horizon": "10"}, 0.25),
        ({"task": "noisy_fetch_pick_place", **icem_50, "horizon": "10", "particles": "4"}, 3.0),
    )

    def estimate(task, horizon=10, **base):
        name = f"{task}_{horizon}_{len(store.asked)}"
        sweep = write_sweep(tmp_path, name, task=task, base={"planner": {"budget": 50, "horizon": horizon}, **base})
        loaded = load_sweep(sweep)
        return cost_per_work(loaded, loaded.trials[0], store, {})

    assert estimate("point_reach") == (0.25, "1 past run(s)")
    assert estimate("point_reach", horizon=20) is None and store.asked[-1]["horizon"] == "20"
    assert estimate("noisy_fetch_pick_place", ensemble={"particles": 4}) == (3.0, "1 past run(s)")
    assert estimate("noisy_fetch_pick_place", ensemble={"particles": 16}) is None
    assert store.asked[-1]["particles"] == "16"


def test_random_parameters_are_repeatable(tmp_path):
    fields = dict(
        parameters={"planner.sigma_init": {"distribution": "uniform", "low": 0.2, "high": 0.8}}, num_samples=3
    )
    first = [t.config.settings.planner.sigma_init for t in load_sweep(write_sweep(tmp_path, "r", **fields)).trials]
    second = [t.config.settings.planner.sigma_init for t in load_sweep(write_sweep(tmp_path, "r", **fields)).trials]
    assert first == second and len(set(first)) == 3 and all(0.2 <= s <= 0.8 for s in first)


def test_variants_run_side_by_side_with_grids_and_seeds(tmp_path):
    sweep = write_sweep(
        tmp_path,
        "ablation",
        variants=[
            {"name": "full"},
            {"name": "white", "planner.noise_beta": 0.0},
            {"name": "mpc", "algorithm": "cem_mpc"},
        ],
        parameters={"planner.budget": {"values": [50, 100]}},
        seeds=[0, 1],
    )
    trials = load_sweep(sweep).trials
    assert len(trials) == 3 * 2 * 2
    by_variant = {}
    for trial in trials:
        by_variant.setdefault(trial.variant, []).append(trial.config.settings.planner)
    assert {p.noise_beta for p in by_variant["full"]} == {1.0}  # point_reach's beta
    assert {p.noise_beta for p in by_variant["white"]} == {0.0}
    assert {p.algorithm for p in by_variant["mpc"]} == {"cem_mpc"}


def test_bench_json_reports_ratios_per_task_and_budget(capsys):
    """A tiny ``icemlab bench --json`` run: the figures scripts read are present and consistent."""
    assert (
        main(
            ["bench", "--tasks", "point_reach", "--budgets", "20", "40", "--steps", "2", "--threads", "2"]
            + ["--no-service", "--json"]
        )
        == 0
    )
    results = json.loads(capsys.readouterr().out)
    assert results["threads"] == 2 and "service" not in results
    entries = results["tasks"]["point_reach"]
    assert [e["budget"] for e in entries] == [20, 40]
    for e in entries:
        assert e["cores_used"] == 2
        assert e["planner_physics_steps_per_second"] > 0 and e["raw_physics_steps_per_second"] > 0
        assert 0 < e["ratio"] < 10 and 0 < e["rollouts_only_ratio"] < 10
        assert e["ratio_quartiles"][0] <= e["ratio"] <= e["ratio_quartiles"][1]
        assert e["thesis_seconds_per_step_1_thread"] is None  # no published figure for the test task


def test_two_million_seeds_are_refused_before_parsing_or_expanding(tmp_path):
    """A 16 MB seed list is refused by its size before YAML parses it; a seed range by max_trials before the
    trials are built (the message says which guard fired; neither is a time limit)."""
    listed = tmp_path / "listed.yaml"
    listed.write_text("name: x\ntask: point_reach\nseeds: [" + ", ".join(map(str, range(2_000_000))) + "]\n")
    ranged = tmp_path / "ranged.yaml"
    ranged.write_text("name: x\ntask: point_reach\nseeds: {first: 0, count: 2000000}\n")
    for sweep, (line, path, fragment) in {
        listed: (1, "(file)", "write long seed lists as seeds: {first: 0, count: N}"),
        ranged: (3, "seeds", "2,000,000 trials, above max_trials = 1000"),
    }.items():
        result = cli("validate", str(sweep), cwd=tmp_path)
        assert result.returncode == 2
        problem = PROBLEM_LINE.match(result.stderr.splitlines()[0])
        assert problem and (int(problem["line"]), problem["path"]) == (line, path)
        assert fragment in problem["message"]


def test_seed_ranges_expand_to_consecutive_seeds(tmp_path):
    sweep = tmp_path / "range.yaml"
    sweep.write_text("name: x\ntask: point_reach\nseeds: {first: 3, count: 4}\n")
    assert [t.config.seed for t in load_sweep(sweep).trials] == [3, 4, 5, 6]


@pytest.mark.slow
def test_bench_methods_json_reports_each_methods_ratios(capsys):
    """``icemlab bench --methods --json``: each learning method's same-run figures are present and consistent."""
    assert main(["bench", "--tasks", "point_reach", "--budgets", "20", "--steps", "2", "--no-service"]
                + ["--methods", "--json"]) == 0  # fmt: skip
    methods = json.loads(capsys.readouterr().out)["methods"]
    relabel = methods["apex"]["relabel"]
    assert relabel["workers"] == [1, 2] and relabel["ratio_to_first"][0] == 1.0
    assert all(rate > 0 for rate in relabel["states_per_second"])
    apex = methods["apex"]
    assert apex["fraction_of_table_12"] == pytest.approx(apex["iteration_core_minutes"] / (5.6 * 32))
    assert set(methods["mbrl"]["presets"]) == {"bridge_maze", "noisy_halfcheetah", "small"}
    for preset in methods["mbrl"]["presets"].values():
        assert preset["ratio"] == pytest.approx(preset["ensemble_flops_per_second"] / preset["dense_flops_per_second"])
    for task in methods["napsp"]["tasks"].values():
        assert task["ratio"] == pytest.approx(task["learner_updates_per_second"] / task["bare_updates_per_second"])
    modes = methods["napsp"]["modes"]
    seconds = modes["seconds_per_iteration"]
    assert modes["pipelined_over_sync"] == pytest.approx(seconds["pipelined"] / seconds["sync"])
