"""``icemlab bench``: speed figures measured in one run, as ratios.

* planner: iCEM planning throughput during MPC at each budget (horizon 30),
  in physics steps per second of planning time, and seconds per environment
  step next to the thesis's Table 2;
* raw: the same batches the planner evaluated, re-simulated by native mj_step
  loops on one thread, in physics steps per second; the ratio
  planner / (raw x threads) is the share of the machine's physics rate that
  planning achieves; the same batches re-simulated by the planner's thread
  pool alone show how much of the gap is the machine's multi-thread scaling;
* service: seconds per environment step of an MPC trial through the service
  (its actor group as ``icemlab run`` places it) against the same program
  in-process, and with one remote simulation worker.

Figures vary by tens of percent between runs on a shared machine; the ratios
are measured back to back in one run for that reason. The MPC loop and the
actor layout are the product's own (workers/mpc.py, orchestrator/placement.py).
"""

from __future__ import annotations

import resource
import time
from typing import Any

import numpy as np

from orchestrator.references import THESIS, find, load_references
from workers.actors import ProgramRunner
from workers.methods import METHODS, MpcSettings, TrialSpec
from workers.mpc import MpcEpisode, PlanningState
from workers.planning import CEMPlanner, PlannerConfig
from workers.rollout import BatchEvaluator, default_threads
from workers.tasks import SimState, make_task

HORIZON = 30
SERVICE_TASK = "halfcheetah_running"
SERVICE_BUDGET = 100
QUICK = {"tasks": ["halfcheetah_running"], "budgets": [100, 300], "steps": 10, "service_steps": 30}
"""The default measurement: about two minutes on two cores."""
FULL = {"tasks": ["halfcheetah_running", "humanoid_standup"], "budgets": [100, 300], "steps": 20, "service_steps": 60}
"""``--full``: the figures of the README's speed table, about ten minutes on two cores."""


class RecordingEvaluator:
    """Passes cost requests to a batch evaluator and keeps every batch it was asked for."""

    def __init__(self, evaluator: BatchEvaluator):
        self.evaluator = evaluator
        self.batches: list[tuple[SimState, np.ndarray]] = []

    def evaluate(self, state: PlanningState, actions: np.ndarray) -> np.ndarray:
        self.batches.append((state.sim, actions.copy()))
        return self.evaluator.costs(state.sim, actions)


def resimulate(evaluator: BatchEvaluator, batches: list[tuple[SimState, np.ndarray]]) -> tuple[int, float]:
    """Physics steps and seconds of ``evaluator`` re-simulating recorded batches (no planner work)."""
    steps, elapsed = 0, 0.0
    for state, actions in batches:
        start = time.perf_counter()
        evaluator.simulate(state, actions)
        elapsed += time.perf_counter() - start
        steps += actions.shape[0] * actions.shape[1] * evaluator.task.frame_skip
    return steps, elapsed


def table_2(task: str, budget: int, threads: int) -> float | None:
    """The thesis's seconds per environment step (Table 2), from the published references."""
    params = {"planner.algorithm": "icem", "planner.budget": str(budget), "threads": str(threads)}
    reference = find(load_references(THESIS), task, "mpc", params, "seconds_per_step")
    return None if reference is None else reference.value


def planner_figures(task_name: str, budget: int, steps: int, threads: int) -> dict[str, Any]:
    """iCEM's planning throughput over ``steps`` MPC steps, and raw MuJoCo's on the same batches.

    Every MPC step is measured three times back to back, so that the slow
    phases of a shared machine hit all three alike:

    * planner: the planner's step with all threads (sampling, rollouts, costs, CEM updates);
    * raw: the same states and action sequences stepped by native mj_step
      loops on the calling thread (mujoco.rollout, nthread=0), so that contacts
      and controls match what the planner simulated;
    * rollouts: the same batches through the planner's thread pool with no
      planner work, which splits the gap to ``raw x threads`` into the
      machine's multi-thread scaling and the planner's own overhead.

    Ratios are medians over steps of the per-step ratios.
    """
    task = make_task(task_name)
    config = PlannerConfig(algorithm="icem", budget=budget, horizon=HORIZON).resolved(task.colored_noise_beta)
    env = task.make_env()
    env.reset(seed=0)
    model = task.build_planning_model(env)
    evaluator = BatchEvaluator(task, model, threads)
    single = BatchEvaluator(task, model, threads=0)
    recorder = RecordingEvaluator(evaluator)
    episode = MpcEpisode(task, env, CEMPlanner(config, task.action_dim, seed=0), recorder, seed=0, steps=steps)
    totals = {"planner": [0, 0.0], "raw": [0, 0.0], "rollouts": [0, 0.0]}
    ratios, scaling = [], []

    def measure(record) -> None:
        measured = {
            "planner": (record.trajectories * HORIZON * task.frame_skip, record.planning_seconds),
            "raw": resimulate(single, recorder.batches),
            "rollouts": resimulate(evaluator, recorder.batches),
        }
        recorder.batches.clear()
        for key, (n, seconds) in measured.items():
            totals[key][0] += n
            totals[key][1] += seconds
        rate = {key: n / seconds for key, (n, seconds) in measured.items()}
        ratios.append(rate["planner"] / (rate["raw"] * threads))
        scaling.append(rate["rollouts"] / (rate["raw"] * threads))

    try:
        episode.run(on_step=measure)
    finally:
        evaluator.close()
        single.close()
        env.close()
    rates = {key: n / seconds for key, (n, seconds) in totals.items()}
    return {
        "budget": budget,
        "trajectories_per_step": config.trajectories_per_step(),
        "seconds_per_step": totals["planner"][1] / steps,
        "planner_physics_steps_per_second": rates["planner"],
        "planner_env_steps_per_second": rates["planner"] / task.frame_skip,
        "raw_physics_steps_per_second": rates["raw"],
        "cores_used": threads,
        "ratio": float(np.median(ratios)),
        "ratio_quartiles": [float(q) for q in np.percentile(ratios, [25, 75])],
        "rollouts_only_ratio": float(np.median(scaling)),
        "planner_share_of_rollouts": float(np.median(np.asarray(ratios) / np.asarray(scaling))),
        "thesis_seconds_per_step_1_thread": table_2(task_name, budget, 1),
        "thesis_seconds_per_step_32_threads": table_2(task_name, budget, 32),
    }


def _mpc_trial(steps: int) -> TrialSpec:
    settings = MpcSettings(
        planner=PlannerConfig(budget=SERVICE_BUDGET, horizon=HORIZON), max_steps=steps, round_steps=steps
    )
    settings = METHODS["mpc"].resolve(settings, make_task(SERVICE_TASK))
    return TrialSpec("mpc", SERVICE_TASK, settings, 0)


def _seconds_per_step(report) -> float:
    return float(np.mean(report.series["step/planning_seconds"]))


def service_figures(steps: int, threads: int) -> dict[str, Any]:
    """Seconds per environment step in-process vs through the service's actor group, same run."""
    import ray

    from orchestrator.placement import TrialGroup
    from orchestrator.scheduler import connect_ray

    trial = _mpc_trial(steps)

    def in_process() -> float:
        runner = ProgramRunner(trial, {}, threads)
        try:
            return _seconds_per_step(runner.run_round(0)[0])
        finally:
            runner.close()

    def through_service(unit: int, simulation_workers: int) -> tuple[float, float]:
        group = TrialGroup(trial, unit, {"simulation": simulation_workers}, max_restarts=0)
        try:
            ray.get(group.ready())
            runner = group.start()
            report, _, _ = ray.get(runner.run_round.remote(0))
            return _seconds_per_step(report), ray.get(runner.peak_memory_mb.remote())
        finally:
            group.teardown()

    started_ray = connect_ray(None, num_cpus=threads)
    try:
        local_s, service_s, split_local_s, split_s, memory = [], [], [], [], []
        for _ in range(3):  # alternate, so that machine noise hits both alike
            local_s.append(in_process())
            seconds, peak = through_service(threads, 1)  # the default layout: one co-located worker
            service_s.append(seconds)
            memory.append(peak)
        half = max(1, threads // 2)
        for _ in range(3):  # half the CPUs co-located, half in one remote SimulationWorker
            split_local_s.append(in_process())
            split_s.append(through_service(half, 2)[0])
    finally:
        if started_ray:
            ray.shutdown()
    local, service = float(np.median(local_s)), float(np.median(service_s))
    split_local, split = float(np.median(split_local_s)), float(np.median(split_s))
    return {
        "task": SERVICE_TASK,
        "budget": SERVICE_BUDGET,
        "steps": steps,
        "in_process_seconds_per_step": local,
        "service_seconds_per_step": service,
        "ratio": service / local,
        "overhead_percent": 100.0 * (service / local - 1.0),
        "service_one_remote_worker_seconds_per_step": split,
        "one_remote_worker_ratio": split / split_local,
        "service_runner_peak_memory_mb": max(memory),
    }


def run_benchmark(
    tasks: list[str], budgets: list[int], steps: int, threads: int | None, service: bool = True, service_steps: int = 30
) -> dict[str, Any]:
    """All figures of ``icemlab bench`` as one JSON-serialisable dict."""
    threads = threads or default_threads()
    results: dict[str, Any] = {"threads": threads, "horizon": HORIZON, "tasks": {}}
    for name in tasks:
        results["tasks"][name] = [planner_figures(name, budget, steps, threads) for budget in budgets]
    results["in_process_peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if service:
        results["service"] = service_figures(service_steps, threads)
    return results


def print_report(results: dict[str, Any]) -> None:
    threads = results["threads"]
    print(f"icemlab bench: {threads} thread(s), horizon {results['horizon']}\n")
    columns = ("budget", "raw 1-thr", "planner", "ratio", "rollouts", "s/step", "thesis 1/32 thr")
    widths = (6, 12, 12, 6, 8, 8, 16)
    header = f"{'task':22s} " + " ".join(f"{c:>{w}s}" for c, w in zip(columns, widths))
    print(header)
    print("-" * len(header))
    for name, entries in results["tasks"].items():
        for e in entries:
            thesis = "-"
            if e["thesis_seconds_per_step_1_thread"] is not None:
                thesis = f"{e['thesis_seconds_per_step_1_thread']:.3f}/{e['thesis_seconds_per_step_32_threads']:.3f}"
            print(
                f"{name:22s} {e['budget']:>6d} {e['raw_physics_steps_per_second']:>12,.0f} "
                f"{e['planner_physics_steps_per_second']:>12,.0f} {e['ratio']:>6.2f} "
                f"{e['rollouts_only_ratio']:>8.2f} {e['seconds_per_step']:>8.3f} {thesis:>16s}"
            )
    print("\nplanner: physics steps/s of planning with all threads; raw: the same batches re-simulated by")
    print(f"native mj_step loops on one thread; ratio = planner / (raw x {threads}); rollouts = the same batches")
    print(f"through the planner's thread pool alone / (raw x {threads}), the machine's multi-thread scaling.")
    print("Each MPC step is measured all three ways back to back; ratios are medians over steps.")
    print("s/step: planning seconds per environment step.")
    print(f"peak memory of the in-process runs: {results['in_process_peak_memory_mb']:.0f} MB")
    if "service" in results:
        s = results["service"]
        print(f"\nservice vs in-process ({s['task']}, budget {s['budget']}, {s['steps']} steps, median of 3):")
        print(f"  in-process          {s['in_process_seconds_per_step']:.4f} s/step")
        print(
            f"  service (default)   {s['service_seconds_per_step']:.4f} s/step   ratio {s['ratio']:.3f} "
            f"({s['overhead_percent']:+.1f}%)"
        )
        print(
            f"  one remote worker   {s['service_one_remote_worker_seconds_per_step']:.4f} s/step   "
            f"ratio {s['one_remote_worker_ratio']:.3f}"
        )
        print(f"  trial actor peak memory {s['service_runner_peak_memory_mb']:.0f} MB")
