"""The ``icemlab`` command line: thin wrappers over sweep, scheduler, tracking, report and bench."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from workers import MAX_SEED

EXIT_BAD_INPUT = 2

DESCRIPTION = """\
icemlab runs model-based planning experiments as sweeps: a YAML file in, Ray
trials out, every result in MLflow. Methods: mpc (iCEM and the CEM baselines
on MuJoCo ground truth), apex (iCEM distilled into a policy with DAgger),
mbrl (PETS, PETSUS and RAZER on learned ensembles) and napsp (neural
all-pairs shortest paths). Locally nothing needs to be started: Ray runs
in-process and MLflow writes to ./mlflow.db.

  icemlab run sweeps/quickstart.yaml           run a sweep (local Ray, ./mlflow.db)
  icemlab ui                                   open the MLflow dashboard on ./mlflow.db
  icemlab report sweeps/quickstart.yaml        its table and plots
  icemlab report sweeps/paper/door.yaml        the same, next to the thesis's Table 3
  icemlab run SWEEP --address ray://head:10001 --tracking-uri http://mlflow:5000
"""


CPUS = os.cpu_count() or 1


def _whole(low: int, high: int | None = None, what: str = ""):
    """An argparse type: a whole number in [low, high], refused with the range it must lie in."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < low or (high is not None and value > high):
            allowed = f">= {low}" if high is None else f"from {low} to {high}"
            raise argparse.ArgumentTypeError(f"must be {allowed}{what}, got {value}")
        return value

    return parse


def _add_tracking(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--tracking-uri",
        default=None,
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI, else sqlite:///./mlflow.db)",
    )


def _add_plan_options(parser: argparse.ArgumentParser, tracking: bool = True) -> None:
    if tracking:
        _add_tracking(parser)
    parser.add_argument(
        "--cores", type=_whole(1), default=32, metavar="N",
        help="also estimate the wall time on a cluster of N CPUs (32)",
    )  # fmt: skip
    parser.add_argument("--no-estimate", action="store_true", help="no time estimate (no calibration run)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="icemlab", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    run = commands.add_parser(
        "run",
        help="run a sweep",
        description="Validate a sweep, then run its trials on Ray and log them to MLflow. "
        "Finished trials (same config and seed) are never run twice within a sweep run; "
        "--resume continues the latest run of the sweep after a crash or Ctrl-C.",
    )
    run.add_argument("sweep", type=Path, help="sweep YAML file")
    run.add_argument(
        "--address",
        default=os.environ.get("RAY_ADDRESS"),
        help="Ray cluster address, e.g. ray://head:10001 or 10.0.0.1:6379 (default: $RAY_ADDRESS, else a local Ray)",
    )
    _add_tracking(run)
    run.add_argument(
        "--resume", action="store_true", help="continue the latest run of this sweep: run only missing trials"
    )
    run.add_argument("--max-concurrent", type=_whole(1), default=None, metavar="N", help="at most N trials at a time")
    run.add_argument(
        "--allow-physics-change",
        action="store_true",
        help="resume even if finished trials ran another mujoco or gymnasium-robotics version",
    )
    run.add_argument("--quiet", action="store_true", help="no progress display")
    run.add_argument(
        "--dry-run",
        action="store_true",
        help="print the trials and the plan, start no trial (the time estimate may run a few planning steps of "
        "each configuration without past runs here; --no-estimate skips it)",
    )
    _add_plan_options(run, tracking=False)

    validate = commands.add_parser(
        "validate",
        help="check a sweep without running it",
        description="Check a sweep file and every trial it expands to; print one FILE:LINE: path: message "
        "line per problem and exit 2, or the trials and a plan (trials already finished in the store, "
        "core-hours, wall time here and on a cluster) and exit 0. Starts nothing.",
    )
    validate.add_argument("sweep", type=Path, help="sweep YAML file")
    validate.add_argument("--quiet", action="store_true", help="print nothing when the sweep is valid")
    _add_plan_options(validate)

    status = commands.add_parser(
        "status",
        help="what ran, what runs, what failed",
        description=(
            "Without SWEEP: every sweep in the store, its trials finished of those planned and, while it runs, "
            "the time to go at its recent pace. With SWEEP (file or name): the same line, then its trials."
        ),
    )
    status.add_argument("sweep", nargs="?", help="sweep file or sweep name")
    status.add_argument(
        "--provenance", action="store_true", help="with each trial: run id, commit, package versions, CPU"
    )
    _add_tracking(status)

    report_cmd = commands.add_parser(
        "report",
        help="summary table and plots of a sweep, next to the thesis",
        description="Summarise the latest run of a sweep: the mean per configuration with its 95% interval "
        "(Student's t over seeds below 15 runs, bootstrap from 15; Wilson for success rates; the sem in "
        "summary.csv), "
        "next to the thesis's published figure where there is one (Tables 3 and 9), and each variant against the "
        "sweep's baseline (paired by seed, or by episode where episodes start alike); summary.csv, summary.txt "
        "and the plots that fit the sweep: budget curves (Fig. 5), variants, each method's curves over its steps, "
        "Fig. 19a/19b (frozen success, drop rate against w_A and against the noise), "
        "coverage.",
    )
    report_cmd.add_argument("sweep", help="sweep file or sweep name")
    report_cmd.add_argument(
        "--output", type=Path, default=None, help="directory for summary.csv and plots (default: reports/NAME)"
    )
    _add_tracking(report_cmd)

    reproduce = commands.add_parser(
        "reproduce",
        help="run one finished trial again and compare",
        description="Run a finished trial again in this process from the configuration and seed its MLflow run "
        "recorded (trial.json), and say whether its headline figures are identical; the package versions it "
        "recorded are compared with this installation's. Exit 0 when identical, 1 when not.",
    )
    reproduce.add_argument("run_id", help="the trial's MLflow run id (icemlab status SWEEP --provenance lists them)")
    reproduce.add_argument(
        "--threads",
        type=_whole(1, CPUS, " (this machine's CPUs)"),
        default=None,
        help="CPUs per unit of work (default: as the trial ran, which torch-trained methods need to repeat)",
    )
    _add_tracking(reproduce)

    ui = commands.add_parser(
        "ui",
        help="open the MLflow dashboard on the store",
        description="Serve the MLflow UI for the tracking store (default ./mlflow.db) on 127.0.0.1.",
    )
    _add_tracking(ui)
    ui.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    ui.add_argument("--port", type=_whole(1, 65535), default=5000, help="port (default 5000)")

    bench = commands.add_parser(
        "bench",
        help="planner speed vs raw MuJoCo, service vs in-process, the learning methods' throughput",
        description="Measure, in one run: raw single-thread mj_step throughput per task; iCEM planning "
        "throughput at each budget (horizon 30) and its ratio to raw x threads; seconds per environment "
        "step next to the thesis's Table 2; and the service's overhead against in-process planning. "
        "The default takes about two minutes on two cores; --full measures what the README's tables show "
        "(about ten minutes).",
    )
    bench.add_argument("--full", action="store_true", help="the README's tables: HalfCheetah and Humanoid, 20 steps per budget, every method")
    bench.add_argument("--tasks", nargs="+", default=None, help="tasks to measure (default: halfcheetah_running; with --full also humanoid_standup)")
    bench.add_argument("--budgets", nargs="+", type=_whole(1), default=None, help="budgets (default: 100 300)")
    bench.add_argument(
        "--steps", type=_whole(1), default=None,
        help="MPC steps measured per task and budget (default 10; 20 with --full)",
    )  # fmt: skip
    bench.add_argument(
        "--threads", type=_whole(1, CPUS, " (this machine's CPUs)"), default=None,
        help="rollout threads (default: all CPUs)",
    )  # fmt: skip
    bench.add_argument("--no-service", action="store_true", help="skip the service-overhead measurement (--methods still starts a local Ray)")
    bench.add_argument(
        "--methods",
        nargs="*",
        choices=("apex", "mbrl", "napsp"),
        default=None,
        help="learning methods to measure: apex (relabeling with 1 vs 2 workers, core-minutes per iteration), "
        "mbrl (ensemble evaluator vs dense matmuls), napsp (learner vs a bare torch loop, pipelined vs sync "
        "iterations); default: all with --full, none otherwise; --methods alone: all",
    )
    bench.add_argument("--json", action="store_true", help="print the figures as one JSON document")

    policy = commands.add_parser(
        "policy",
        help="roll a trained APEX policy in the real environment",
        description="Roll a policy checkpoint of an APEX trial (artifact policy/policy_NNNN.npz of its run) in "
        "the task's real environment and print return and success per episode. Refuses a checkpoint of "
        "another task. --frames writes a strip of frames of the first episode where MuJoCo renders headless "
        "(MUJOCO_GL=egl or osmesa).",
    )
    policy.add_argument("checkpoint", type=Path, help="policy checkpoint (.npz)")
    policy.add_argument("--task", default=None, help="the task to roll it on (default: the checkpoint's)")
    policy.add_argument("--episodes", type=_whole(1), default=1, help="episodes (seeds SEED, SEED+1, ...; default 1)")
    policy.add_argument("--seed", type=_whole(0, MAX_SEED), default=0, help="seed of the first episode (default 0)")
    policy.add_argument(
        "--steps", type=_whole(1), default=None,
        help="steps per episode (default: chapter 4's, which APEX trains on: 500 on humanoid_standup, else the task's)",
    )  # fmt: skip
    policy.add_argument("--frames", type=Path, default=None, metavar="PNG", help="write a frame strip here")

    model = commands.add_parser(
        "model",
        help="describe a trained ensemble and draw its uncertainty map",
        description="Describe an ensemble checkpoint of an mbrl trial (artifact models/model_vNNN.npz of its run) "
        "and, for a task with a plane (bridge_maze), draw its one-step uncertainty over the plane: Var_A (eq. 22) "
        "and Var_E (eq. 24), reduced over dimensions as the planner reduces them, for the state the task's probe "
        "puts at each point. Refuses a checkpoint whose state or action size differs from the task's.",
    )
    model.add_argument("checkpoint", type=Path, help="ensemble checkpoint (.npz)")
    model.add_argument("--task", required=True, help="the task the model was trained on (e.g. bridge_maze)")
    model.add_argument(
        "--output", type=Path, default=None, metavar="PNG", help="where the map goes (default: uncertainty_vNNN.png)"
    )
    model.add_argument(
        "--epistemic-terms",
        choices=("means_and_variances", "means"),
        default="means_and_variances",
        help="Var_E as eq. 24 writes it, or the variance of the members' means alone (razer.epistemic_terms; "
        "default means_and_variances)",
    )
    model.add_argument(
        "--dims",
        type=int,
        nargs="+",
        default=None,
        metavar="D",
        help="state dimensions whose uncertainty counts (razer.uncertainty_dims; default: all)",
    )

    commands.add_parser("tasks", help="list the tasks", description="List the tasks a sweep can name.")
    commands.add_parser(
        "schema",
        help="print the JSON Schema of sweep files",
        description="Print the JSON Schema of sweep files (for editor completion).",
    )
    return parser


# ----------------------------------------------------------------- commands
def _load(path: Path):
    from orchestrator.sweep import SweepError, load_sweep

    try:
        return load_sweep(path)
    except SweepError as error:
        for problem in error.problems:
            print(problem, file=sys.stderr)
        print(f"icemlab: {len(error.problems)} problem(s) in {path}; nothing was started", file=sys.stderr)
        if error.unchecked:
            print(f"icemlab: not checked yet: {error.unchecked}; fix these and validate again", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT) from None


def _missing_sqlite(uri: str) -> bool:
    """Whether ``uri`` names an embedded store that does not exist, or is an empty file (opening it would create
    the store)."""
    from orchestrator.tracking import sqlite_path

    database = sqlite_path(uri)
    return database is not None and (not database.exists() or (database.is_file() and database.stat().st_size == 0))


def _output_problem(path: Path, suffix: str | None = None) -> str | None:
    """Why ``path`` cannot be written, checked before any work is done, or None: a file ending in ``suffix``, or a
    directory (created with its parents) when ``suffix`` is None."""
    if suffix is not None:
        if path.is_dir():
            return f"{path} is a directory; name a {suffix} file in it"
        if path.suffix.lower() != suffix:
            return f"{path} must end in {suffix}"
        if not path.parent.is_dir():
            return f"directory {path.parent} does not exist"
        return None if os.access(path.parent, os.W_OK) else f"cannot write in {path.parent}"
    if path.exists() and not path.is_dir():
        return f"{path} exists and is not a directory"
    existing = next(p for p in (path.absolute(), *path.absolute().parents) if p.exists())
    if not existing.is_dir():
        return f"{existing} is not a directory"
    return None if os.access(existing, os.W_OK) else f"cannot write in {existing}"


def _refuse_output(path: Path | None, option: str, suffix: str | None = None) -> None:
    """End the command, before it starts its work, when ``path`` cannot be written."""
    problem = _output_problem(path, suffix) if path is not None else None
    if problem:
        print(f"icemlab: {option}: {problem}", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT)


def _tracker(uri: str | None):
    """A Tracker on the store ``uri`` (or the default one); a store that cannot be used ends the command with one
    line saying which, why and where its URI came from."""
    from orchestrator.tracking import StoreUnavailable, Tracker, tracking_uri_source

    try:
        return Tracker(uri)
    except StoreUnavailable as error:
        print(f"icemlab: {error} (the URI is {tracking_uri_source(uri)})", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT) from None


def _existing_store(uri: str | None):
    """(resolved URI, a Tracker on the store or None if it does not exist yet): plans, reports and status never
    create one."""
    from orchestrator.tracking import resolve_tracking_uri

    resolved = resolve_tracking_uri(uri)
    return resolved, None if _missing_sqlite(resolved) else _tracker(uri)


def _print_plan(loaded, args) -> None:
    from orchestrator import plan

    _, tracker = _existing_store(args.tracking_uri)
    finished = plan.finished_keys(loaded, tracker)
    print(f"{loaded.path}: valid, {len(loaded.trials)} trial(s)")
    for trial in loaded.trials:
        shown = ({"variant": trial.variant} if trial.variant else {}) | trial.overrides
        swept = ", ".join(f"{k}={v}" for k, v in shown.items())
        done = "  (finished)" if trial.key in finished else ""
        print(f"  {trial.key}  seed {trial.config.seed}  {swept}{done}")
    if args.no_estimate:
        return
    # Calibrating a configuration with no past runs can take minutes on a large planner: say so before it starts.
    print("time estimate: from past runs, or a few planning steps of each new configuration here "
          "(--no-estimate skips it) ...", flush=True)  # fmt: skip
    for line in plan.describe(loaded, plan.plan_sweep(loaded, tracker), args.cores):
        print(line)


def cmd_validate(args) -> int:
    loaded = _load(args.sweep)
    if not args.quiet:
        _print_plan(loaded, args)
    return 0


def cmd_run(args) -> int:
    loaded = _load(args.sweep)
    if args.dry_run:
        _print_plan(loaded, args)
        return 0
    from orchestrator.interrupt import describe
    from orchestrator.progress import ProgressDisplay
    from orchestrator.scheduler import PhysicsChangedError, ResourceError, SweepBusyError, SweepScheduler
    from orchestrator.tracking import KILLED, RUNNING

    tracker = _tracker(args.tracking_uri)
    experiment = loaded.sweep.tracking.experiment or loaded.sweep.name
    previous = None if args.resume else tracker.find_sweep_run(experiment, loaded.sweep.name)
    if previous is not None and previous.status in (RUNNING, KILLED):
        print(
            f"icemlab: note: the last run of {loaded.sweep.name} ({previous.run_id}) did not finish; "
            "this starts a new one. `--resume` would continue it instead.",
            file=sys.stderr,
        )
    display = None if args.quiet else ProgressDisplay()
    print(
        f"icemlab: running {loaded.sweep.name} ({len(loaded.trials)} trials, method {loaded.sweep.method}), "
        f"tracking at {tracker.uri}",
        file=sys.stderr,
    )
    scheduler = SweepScheduler(
        loaded,
        tracker,
        address=args.address,
        resume=args.resume,
        max_concurrent=args.max_concurrent,
        display=display,
        allow_physics_change=args.allow_physics_change,
        notice=display.note if display else None,
    )
    try:
        outcome = scheduler.run()
    except ConnectionError as error:
        print(f"icemlab: {error}", file=sys.stderr)
        return 1
    except ResourceError as error:
        print(f"icemlab: {error}; nothing was started", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (PhysicsChangedError, SweepBusyError) as error:
        print(f"icemlab: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt as stop:
        if display:
            display.close()
        print(
            f"icemlab: interrupted ({describe(stop)}); running trials were stopped and marked KILLED. "
            f"Continue with: icemlab run {args.sweep} --resume",
            file=sys.stderr,
        )
        return 128 + int(getattr(stop, "signum", signal.SIGINT))  # the shell's code: 130 for Ctrl-C, 143 for SIGTERM
    except Exception as error:
        if display:
            display.close()
        recorded = "the sweep's runs say so in MLflow" if getattr(error, "recorded_in_mlflow", False) else (
            "MLflow could not be told"
        )
        print(
            f"icemlab: the driver stopped on {type(error).__name__}: {error} (traceback below); {recorded}. "
            f"Once the cause is fixed, continue with: icemlab run {args.sweep} --resume",
            file=sys.stderr,
        )
        raise
    if display:
        display.close()
    print(outcome.table)
    print(
        f"\n{outcome.finished} trial(s) finished, {outcome.failed} failed, {outcome.skipped} already done. "
        f"Parent run {outcome.parent_run_id}; see `icemlab ui` (tracking URI {tracker.uri}).",
        file=sys.stderr,
    )
    if outcome.failed:
        print(f"icemlab: see why with: icemlab status {args.sweep}", file=sys.stderr)
    return 1 if outcome.failed else 0


def _sweep_name(argument: str):
    """(sweep name, experiment, loaded sweep or None) from a file path or a plain name."""
    path = Path(argument)
    if path.suffix in (".yaml", ".yml") or path.exists():
        loaded = _load(path)
        return loaded.sweep.name, loaded.sweep.tracking.experiment or loaded.sweep.name, loaded
    return argument, argument, None


PACE_ROUNDS = 5
"""A running trial's time to go is told from the pace of its last this many rounds."""


def _trial_counts(sweep, tracker, plan: set[str] | None = None) -> str:
    """'finished 41 of 200  running 2  failed 0  killed 0', and for a running sweep the time to go at the pace
    of its current session.

    With ``plan`` (the trial keys of the sweep file) only those trials count: a resume with changed keys leaves
    the earlier trials' runs under the same parent. The pace is the trials finished since the session began
    (start or latest resume) over the time since: finish times bunch when trials started together, and a gap
    between sessions is no part of the pace. A trial that failed before the session began is being retried and
    counts as to go.
    """
    children = [c for c in tracker.trial_runs(sweep.run_id) if plan is None or c.trial_key in plan]
    counts = {s: sum(c.status == s for c in children) for s in ("FINISHED", "RUNNING", "FAILED", "KILLED")}
    parts = [f"{state.lower()} {count}" for state, count in counts.items()]
    if sweep.planned_trials is None:
        return "  ".join(parts)
    parts[0] += f" of {sweep.planned_trials}"
    began = sweep.session_started
    if sweep.status != "RUNNING" or began is None:
        return "  ".join(parts)
    in_session = [c for c in children if c.end_time and c.end_time >= began]
    finished = sum(c.status == "FINISHED" for c in in_session)
    failed = sum(c.status == "FAILED" for c in in_session)
    remaining = sweep.planned_trials - counts["FINISHED"] - failed
    elapsed = time.time() - began
    if remaining > 0 and finished and elapsed > 0:
        from orchestrator.plan import duration_text

        parts.append(
            f"about {duration_text(remaining * elapsed / finished)} to go at this session's pace ({finished} "
            f"finished in {duration_text(elapsed)})"
        )
    return "  ".join(parts)


def cmd_status(args) -> int:
    from orchestrator.tracking import TAG_ERROR, TAG_ERROR_CLASS

    uri, tracker = _existing_store(args.tracking_uri)
    if not args.sweep:
        sweeps = tracker.sweeps() if tracker else []
        if not sweeps:
            print(f"no sweeps in {uri}; start one with: icemlab run sweeps/quickstart.yaml")
            return 0
        for sweep in sweeps:
            print(f"{sweep.name:24s} {sweep.status:9s} run {sweep.run_id}  {_trial_counts(sweep, tracker)}")
        return 0
    name, experiment, loaded = _sweep_name(args.sweep)
    parent = tracker.find_sweep_run(experiment, name) if tracker else None
    if parent is None:
        print(f"sweep {name!r} has not run in {uri}", file=sys.stderr)
        return 1
    plan = {trial.key for trial in loaded.trials} if loaded else None
    print(f"sweep {name}: {parent.status}, parent run {parent.run_id}; {_trial_counts(parent, tracker, plan)}")
    cause = next((line for line in parent.tags.get(TAG_ERROR, "").splitlines() if line.strip()), "")
    if cause:  # the driver itself stopped on an error
        print(f"  {parent.tags.get(TAG_ERROR_CLASS, 'error')}: {cause[:300]}")
    metric = _recorded_metric(_recorded_sweep(tracker, parent.run_id))
    children = sorted(tracker.trial_runs(parent.run_id), key=lambda c: c.name)
    # A resume with changed keys leaves the old plan's runs under the parent: the file says which are its own.
    own = [child for child in children if plan is None or child.trial_key in plan]
    for child in own:
        shown = _trial_metric_text(tracker, child, metric[0] if metric else None)
        rounds = f"{child.rounds:>4d}" + (f"/{child.planned_rounds}" if child.planned_rounds else "")
        if parent.status == "RUNNING" and child.status == "RUNNING":
            shown += _trial_time_to_go(tracker, child)
        print(f"  {child.trial_key}  {child.status:9s} {child.name:44s} rounds {rounds}  attempts {child.attempts}  "
              f"{shown}")  # fmt: skip
        if child.error:
            print(f"      {child.error_class or 'error'}: {child.error.strip().splitlines()[-1][:300]}")
        if args.provenance:
            machine = child.machine
            print(f"      run {child.run_id}; code {child.code}")
            print("      " + ", ".join(f"{name} {v}" for name, v in sorted(child.versions.items())))
            print(f"      ran on {machine.get('cpu_model', '?')}, {machine.get('cpus', '?')} CPUs, "
                  f"host {machine.get('host', '?')}")  # fmt: skip
    if stale := len(children) - len(own):
        print(f"  and {stale} run{'' if stale == 1 else 's'} of trials this file no longer defines "
              f"(an earlier version of it); not counted above")  # fmt: skip
    return 0


def _trial_metric_text(tracker, child, metric: str | None) -> str:
    """A trial's figure of the sweep's metric: its summary once it finished; while it runs, the mean of the rounds
    logged so far, so that a long trial shows where it is heading (said as such: an unfinished figure)."""
    if metric is None:
        figure = child.metrics.get("mean_return")
        return "" if figure is None else f"return {figure:.1f}"
    from workers.methods import METHODS

    program = METHODS.get(child.params.get("method", child.tags.get("method", "mpc")))
    summary_key = (program.metrics if program else {}).get(metric, metric)
    if summary_key in child.metrics and child.status != "RUNNING":
        return f"{metric} {child.metrics[summary_key]:.4g}"
    by_round = dict(tracker.metric_history(child.run_id, metric))  # a round logged twice counts once
    if not by_round:
        return ""
    values = list(by_round.values())
    return f"{metric} {sum(values) / len(values):.3g} so far (mean of the {len(values)} logged)"


def _trial_time_to_go(tracker, child) -> str:
    """'  about 1 h 40 min to go (5 rounds at the pace of its last 5)' for a running trial whose planned rounds are
    recorded; empty before it has logged a round. Rounds count by their recorded relative work (an MBRL trial's
    frozen row takes many iterations' time), all alike where none is recorded."""
    from orchestrator.plan import duration_text
    from orchestrator.tracking import ROUND_SECONDS

    planned = child.planned_rounds or 0
    remaining = planned - child.rounds
    if remaining <= 0:
        return ""
    work = child.round_work
    if work is None or len(work) != planned:
        work = [1.0] * planned
    by_round = dict(tracker.metric_history(child.run_id, ROUND_SECONDS))  # a round logged twice counts once
    # Rounds expected to take no time (an MBRL trial's round 0 of random episodes) say nothing of the pace.
    recent = [index for index in sorted(by_round) if 0 <= index < planned and work[index] > 0][-PACE_ROUNDS:]
    recent_work = sum(work[index] for index in recent)
    if recent_work <= 0:
        return ""
    seconds = sum(work[child.rounds :]) * sum(by_round[index] for index in recent) / recent_work
    return (f"  about {duration_text(seconds)} to go ({remaining} round{'' if remaining == 1 else 's'} at the pace "
            f"of its last {len(recent)})")  # fmt: skip


def _recorded_sweep(tracker, run_id: str) -> dict:
    """The sweep file recorded on a sweep's run, parsed (empty when absent or unreadable)."""
    import yaml

    text = tracker.recorded_sweep(run_id)
    try:
        recorded = yaml.safe_load(text) if text else None
    except yaml.YAMLError:
        return {}
    return recorded if isinstance(recorded, dict) else {}


def _reloaded_sweep(tracker, run_id: str):
    """The sweep file recorded on a sweep's run, loaded again (trials keyed by this code, its reference file
    read); None, said on stderr, when it does not load here: its reference file lay beside a sweep file that is
    not here, or this code no longer accepts or expands it. The report then goes on from what the file names."""
    import tempfile

    from orchestrator.sweep import load_sweep

    text = tracker.recorded_sweep(run_id)
    if not text:
        return None
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "sweep.yaml"
        path.write_text(text)
        try:
            return load_sweep(path)
        except Exception as error:  # noqa: BLE001 - any failure to plan it again still leaves a report to write
            first_line = (str(error).strip().splitlines() or [""])[0]
            print(
                f"icemlab: the sweep file recorded on this sweep's run does not load here ({type(error).__name__}: "
                f"{first_line}); the report uses the metric and baselines it names, and counts every finished run",
                file=sys.stderr,
            )
            return None


def _recorded_metric(recorded: dict) -> tuple[str, str] | None:
    """(metric name, mode) of a recorded sweep file, if it names one."""
    metric = recorded.get("metric")
    if not isinstance(metric, dict) or not isinstance(metric.get("name"), str):
        return None
    return metric["name"], str(metric.get("mode", "max"))


def _recorded_pairing(recorded: dict):
    """The report's pairing of variants with baselines, as a recorded sweep file named it."""
    from orchestrator.report import Pairing

    baseline = recorded.get("baseline") or []
    baselines = [baseline] if isinstance(baseline, str) else [b for b in baseline if isinstance(b, str)]
    parameters = recorded.get("parameters")
    return Pairing(tuple(baselines), tuple(parameters) if isinstance(parameters, dict) else ()) if baselines else None


def cmd_report(args) -> int:
    from orchestrator.tracking import FINISHED

    _refuse_output(args.output, "--output")
    uri, tracker = _existing_store(args.tracking_uri)
    name, experiment, loaded = _sweep_name(args.sweep)
    _refuse_output(Path("reports") / name if args.output is None else None, "the default output, reports/NAME")
    parent = tracker.find_sweep_run(experiment, name) if tracker else None
    if parent is None:
        print(f"sweep {name!r} has not run in {uri}; run it with: icemlab run SWEEP.yaml", file=sys.stderr)
        return 1
    # Imported only when there is something to report: the methods bring torch and every task.
    from orchestrator import report
    from orchestrator.scheduler import episode_histories, report_histories
    from workers.methods import METHODS

    children = tracker.trial_runs(parent.run_id)
    runs = [r for r in children if r.status == FINISHED]
    if not runs:
        running = sum(r.status == "RUNNING" for r in children)
        print(
            f"sweep {name!r} has no finished trial yet ({running} running, {len(children) - running} stopped or "
            f"failed); `icemlab status {name}` shows each trial's figure so far",
            file=sys.stderr,
        )
        return 1
    planned = None
    if loaded is None:  # by name: the sweep recorded on its run, planned by this code as `report FILE` would
        loaded = _reloaded_sweep(tracker, parent.run_id)
    if loaded is not None:
        metric, mode, references = loaded.sweep.metric_name(), loaded.sweep.metric.mode, loaded.references
        planned = {trial.key for trial in loaded.trials}
        pairing = report.pairing(loaded.sweep)
    else:  # by name: the metric and baselines the sweep file named when it ran (recorded on the sweep's run)
        from orchestrator.references import THESIS, load_references

        method = runs[0].params.get("method", "mpc") if runs else "mpc"
        recorded = _recorded_sweep(tracker, parent.run_id)
        metric, mode = _recorded_metric(recorded) or (next(iter(METHODS[method].metrics)), "max")
        pairing = _recorded_pairing(recorded)
        references = load_references(THESIS)
        if recorded.get("reference"):
            print(
                f"icemlab: the sweep compared with {recorded['reference']}, which a report by name cannot read "
                "(the recorded sweep no longer loads here); the thesis's tables stand in. Report the sweep file "
                "to use its reference.",
                file=sys.stderr,
            )
    program = METHODS.get(report.result_from_run(runs[0]).method)
    episodes = episode_histories(tracker, runs, program, metric, pairing)
    summary = report.summarize(runs, metric, mode, references, planned, pairing, episodes)
    print(report.format_table(summary))
    output = args.output or Path("reports") / name
    histories = report_histories(tracker, runs, program) if program else None
    written = report.write_files(summary, output, histories)
    results = [report.result_from_run(run) for run in runs]
    copied = report.copy_trial_plots(tracker, results, {run.run_id: run.name for run in runs}, output)
    print(f"\nwrote {', '.join(str(p) for p in written)}", file=sys.stderr)
    if copied:
        print(f"copied {len(copied)} plot(s) of the trials' runs to {output / 'trials'}", file=sys.stderr)
    return 0


def cmd_reproduce(args) -> int:
    from orchestrator.reproduce import ReproduceError, reproduce, same_figure

    uri, tracker = _existing_store(args.tracking_uri)
    if tracker is None:
        print(f"icemlab: no store at {uri}; pass the sweep's --tracking-uri", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        outcome = reproduce(tracker, args.run_id, args.threads)
    except ReproduceError as error:
        print(f"icemlab: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    for key, recorded, now in outcome.figures:
        same = "identical" if same_figure(recorded, now) else f"differs by {now - recorded:+.6g}"
        print(f"{key}: recorded {recorded!r}, now {now!r}: {same}")
    if not outcome.figures:
        print("nothing to compare: the run and the new run share none of the method's headline figures")
        return 1
    for package, (recorded, now) in outcome.version_changes.items():
        print(f"note: the run used {package} {recorded}, this is {now}")
    if outcome.recorded_threads not in (None, outcome.threads):
        print(
            f"note: the run used {outcome.recorded_threads} thread(s) per worker, this {outcome.threads}; "
            "torch-trained figures differ with the thread count"
        )
    print("identical" if outcome.identical else "NOT identical")
    return 0 if outcome.identical else 1


RUNS_VIEW = "#/{path}?workflowType=machine_learning"
"""MLflow 3 opens every experiment in its GenAI view: the experiment tag mlflow.experimentKind does not change
that (checked in Chromium with MLflow 3.17); the URL's workflowType does, so icemlab's links carry it."""


def _sweep_links(uri: str, base: str, newest: int = 5) -> list[tuple[str, str]]:
    """Links that open the newest sweeps' runs in the dashboard (for a store that exists)."""
    if _missing_sqlite(uri):
        return []
    return [
        (sweep.name, f"{base}/{RUNS_VIEW.format(path=f'experiments/{sweep.experiment_id}/runs')}")
        for sweep in _tracker(uri).sweeps()[:newest]
    ]


def cmd_ui(args) -> int:
    from orchestrator.tracking import resolve_tracking_uri

    uri = resolve_tracking_uri(args.tracking_uri)
    env = dict(os.environ, MLFLOW_SERVER_ENABLE_JOB_EXECUTION="false", MLFLOW_DISABLE_TELEMETRY="true")
    command = [
        sys.executable,
        "-m",
        "mlflow",
        "ui",
        "--backend-store-uri",
        uri,
        "--host",
        args.host,
        "--port",
        str(args.port),
        "--workers",
        "1",
    ]
    base = f"http://{args.host}:{args.port}"
    print(
        f"MLflow dashboard for {uri} at {base}/{RUNS_VIEW.format(path='experiments')} (Ctrl-C stops it)",
        file=sys.stderr,
    )
    for name, link in _sweep_links(uri, base):
        print(f"  {name}: {link}", file=sys.stderr)
    try:
        return subprocess.call(command, env=env)
    except KeyboardInterrupt:
        return 0


def cmd_bench(args) -> int:
    from orchestrator.bench import FULL, QUICK, print_report, run_benchmark
    from orchestrator.bench_methods import METHODS, method_figures, print_method_report

    plan = dict(FULL if args.full else QUICK)
    for key in ("tasks", "budgets", "steps"):
        if getattr(args, key) is not None:
            plan[key] = getattr(args, key)
    methods = [] if args.methods is None and not args.full else list(args.methods or METHODS)
    results = run_benchmark(
        plan["tasks"],
        plan["budgets"],
        plan["steps"],
        args.threads,
        service=not args.no_service,
        service_steps=plan["service_steps"],
    )
    if methods:
        results["methods"] = method_figures(methods, quick=not args.full)
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print_report(results)
        print_method_report(results.get("methods", {}))
    return 0


def cmd_policy(args) -> int:
    from workers.policy.evaluate import PolicyCheckpointError, roll_policy
    from workers.tasks import TASKS, unknown_task_message

    if args.task is not None and args.task not in TASKS:
        print(f"icemlab: {unknown_task_message(args.task)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    _refuse_output(args.frames, "--frames", ".png")
    try:
        result = roll_policy(args.checkpoint, args.task, args.episodes, args.seed, args.steps, args.frames)
    except PolicyCheckpointError as error:
        print(f"icemlab: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"{result.task}: policy version {result.version}, {len(result.returns)} episode(s) of {result.steps} steps")
    for episode, (total, success) in enumerate(zip(result.returns, result.successes)):
        shown = "" if success is None else f"  success {int(success)}"
        print(f"  episode {episode} (seed {args.seed + episode}): return {total:.2f}{shown}")
    rate = None if result.successes[0] is None else sum(map(bool, result.successes)) / len(result.successes)
    shown = "" if rate is None else f"  success rate {rate:.2f}"
    print(f"mean return {sum(result.returns) / len(result.returns):.2f}{shown}")
    if result.frames_note:
        print(result.frames_note, file=sys.stderr)
    return 0


def cmd_model(args) -> int:
    from workers.dynamics.ensemble import DynamicsEnsemble
    from workers.dynamics.settings import RazerSettings
    from workers.methods.mbrl import model_uncertainty_png
    from workers.tasks import TASKS, ModelBasedTask, make_task, unknown_task_message

    if args.task not in TASKS:
        print(f"icemlab: {unknown_task_message(args.task)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not issubclass(TASKS[args.task], ModelBasedTask):
        print(f"icemlab: task {args.task!r} is not a task of the mbrl method (see icemlab tasks)", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not args.checkpoint.is_file():
        print(f"icemlab: no file {args.checkpoint}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not os.access(args.checkpoint, os.R_OK):
        print(f"icemlab: cannot read {args.checkpoint}", file=sys.stderr)
        return EXIT_BAD_INPUT
    _refuse_output(args.output, "--output", ".png")
    try:
        model = DynamicsEnsemble.load(args.checkpoint)
    except Exception:  # noqa: BLE001 - whatever else the file is, the answer is the same
        print(
            f"icemlab: {args.checkpoint} is not an ensemble checkpoint (an mbrl run's models/model_vNNN.npz)",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    task = make_task(args.task)
    if (model.obs_dim, model.action_dim) != (task.observation_dim, task.action_dim):
        print(
            f"icemlab: {args.checkpoint} predicts a {model.obs_dim}-d state from a {model.action_dim}-d action; "
            f"task {args.task} has a {task.observation_dim}-d state and a {task.action_dim}-d action",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    dims = tuple(args.dims) if args.dims else None
    if dims is not None and not (all(0 <= d < model.obs_dim for d in dims) and len(set(dims)) == len(dims)):
        print(f"icemlab: --dims must be distinct dimensions in 0..{model.obs_dim - 1}, got {list(dims)}",
              file=sys.stderr)  # fmt: skip
        return EXIT_BAD_INPUT
    config = model.config
    print(
        f"{args.checkpoint}: weights version {model.weights_version}, {config.ensemble_size} members x "
        f"{config.hidden_layers} hidden layers of {config.hidden_size} ({config.activation}), "
        f"{model.obs_dim}-d state, {model.action_dim}-d action"
    )
    razer = RazerSettings(epistemic_terms=args.epistemic_terms, uncertainty_dims=dims)
    png = model_uncertainty_png(model, task, razer, args.task)
    if png is None:
        print(f"task {args.task} has no plane to draw the model's uncertainty in")
        return 0
    output = args.output or Path(f"uncertainty_v{model.weights_version:03d}.png")
    output.write_bytes(png)
    print(f"uncertainty map: {output}")
    return 0


def cmd_tasks(args) -> int:
    from workers.tasks import TASKS

    for name, task in TASKS.items():
        beta = getattr(task, "colored_noise_beta", None)  # goal tasks (chapter 6) have no planner beta
        shown = f"beta {beta:<4}" if beta is not None else "goal task"
        print(f"{name:25s} {shown:9s}  {task.description}")
        for option, field in task.Options.model_fields.items():
            doc = " ".join((field.description or "").split())
            print(f"{'':27s}task_options.{option} (default {field.default!r}): {doc}")
    return 0


def cmd_schema(args) -> int:
    from orchestrator.sweep import sweep_json_schema

    print(json.dumps(sweep_json_schema(), indent=2))
    return 0


COMMANDS = {
    "run": cmd_run,
    "validate": cmd_validate,
    "status": cmd_status,
    "report": cmd_report,
    "reproduce": cmd_reproduce,
    "ui": cmd_ui,
    "bench": cmd_bench,
    "policy": cmd_policy,
    "model": cmd_model,
    "tasks": cmd_tasks,
    "schema": cmd_schema,
}


def secure_local_ray(args) -> None:
    """A local Ray that icemlab starts keeps Ray's token authentication and is reachable from this machine only.

    The token is kept whatever the environment says; Ray's Prometheus exporters answer anyone without a
    token, and icemlab does not use them.
    Ray reads these variables when it is imported, so this runs before any command imports it.
    """
    if not (args.command == "bench" or (args.command == "run" and not args.address)):
        return
    mode = os.environ.get("RAY_AUTH_MODE", "token")
    if mode != "token":
        print(f"icemlab: RAY_AUTH_MODE={mode} ignored: the local Ray keeps token authentication on", file=sys.stderr)
    os.environ["RAY_AUTH_MODE"] = "token"
    os.environ.setdefault("RAY_enable_metrics_collection", "0")
    # Ray's local-only mode (its default on macOS and Windows): every node address is 127.0.0.1, so the
    # Prometheus exporters of its autoscaler monitor and dashboard head, which take no token, bind to the
    # loopback instead of every interface. A local run needs no other machine.
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    args = build_parser().parse_args(argv)
    secure_local_ray(args)
    try:
        status = COMMANDS[args.command](args)
        sys.stdout.flush()  # inside the handler: a closed pipe may show only when buffered output is written
        return status
    except BrokenPipeError:
        # The reader of our output went away (`icemlab validate ... | head`): stop quietly, as Unix tools do.
        # stdout is pointed at /dev/null so that flushing it at exit raises nothing more.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a tool ended by a closed pipe


if __name__ == "__main__":
    raise SystemExit(main())
