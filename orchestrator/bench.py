"""``icemlab bench``: speed figures measured in one run, as ratios.

* raw: single-thread native MuJoCo stepping of the task's planning model
  (mujoco.rollout on the calling thread, random action sequences of the
  planning horizon from a state of the task), in physics steps per second;
* planner: iCEM planning throughput during MPC at each budget (horizon 30),
  in physics steps per second of planning time, with the ratio
  planner / (raw x threads) and seconds per environment step next to the
  thesis's Table 2;
* service: seconds per environment step through the service (a TrialRunner
  actor with its SimulationPool, as ``icemlab run`` lays it out) against the
  same MPC loop in-process, and with one remote SimulationWorker actor.

Figures vary by tens of percent between runs on a shared machine; the ratios
are measured back to back in one run for that reason.
"""

from __future__ import annotations

import resource
import time
from typing import Any

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from orchestrator.report import PUBLISHED_SECONDS_PER_STEP
from workers.actors import TrialRunner
from workers.planning import PlannerConfig
from workers.rollout import default_threads
from workers.tasks import GroundTruthTask, SimState, make_task

HORIZON = 30
SERVICE_TASK = "halfcheetah_running"
SERVICE_BUDGET = 100


def raw_physics_rate(task: GroundTruthTask, model: mujoco.MjModel, state: SimState, seconds: float = 2.0) -> float:
    """Single-thread physics steps per second of the planning model from ``state``."""
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    runner = mj_rollout.Rollout(nthread=0)
    spec = task.control_spec(model)
    steps, elapsed = 0, 0.0
    try:
        while elapsed < seconds:
            actions = rng.uniform(-1, 1, (1, HORIZON, task.action_dim))
            if task.feedback_control:
                # Feedback controls need the simulated state; hold the captured ones instead.
                control = np.concatenate([np.zeros((1, model.nu)), state.mocap_pos.reshape(1, -1),
                                          state.mocap_quat.reshape(1, -1)], axis=1)[:, None]  # fmt: skip
            else:
                control = np.repeat(task.controls(model, state, actions), task.frame_skip, axis=1)
            start = time.perf_counter()
            runner.rollout(model, [data], state.physics[None], control, control_spec=spec,
                           nstep=HORIZON * task.frame_skip, initial_warmstart=state.warmstart[None])  # fmt: skip
            elapsed += time.perf_counter() - start
            steps += HORIZON * task.frame_skip
    finally:
        runner.close()
    return steps / elapsed


def planner_figures(task_name: str, budget: int, steps: int, threads: int) -> dict[str, Any]:
    """Run ``steps`` MPC steps of iCEM in-process and return its throughput."""
    task = make_task(task_name)
    config = PlannerConfig(algorithm="icem", budget=budget, horizon=HORIZON).resolved(task.colored_noise_beta)
    runner = TrialRunner(task_name, config, seed=0, max_steps=steps, threads=threads)
    report = runner.run_episode(0)
    runner.evaluator.close()
    seconds = float(report.planning_seconds.mean())
    return {
        "budget": budget,
        "trajectories_per_step": float(report.trajectories.mean()),
        "seconds_per_step": seconds,
        "planner_physics_steps_per_second": report.physics_steps_per_second,
        "planner_env_steps_per_second": report.simulated_steps_per_second,
        "thesis_seconds_per_step_1_thread": PUBLISHED_SECONDS_PER_STEP.get((task_name, 1, budget)),
        "thesis_seconds_per_step_32_threads": PUBLISHED_SECONDS_PER_STEP.get((task_name, 32, budget)),
    }


def service_figures(steps: int, threads: int) -> dict[str, Any]:
    """Seconds per environment step in-process vs through Ray actors, same run."""
    import ray

    from orchestrator.pool import SimulationPool
    from orchestrator.scheduler import connect_ray

    task = make_task(SERVICE_TASK)
    config = PlannerConfig(algorithm="icem", budget=SERVICE_BUDGET, horizon=HORIZON).resolved(task.colored_noise_beta)
    in_process = TrialRunner(SERVICE_TASK, config, seed=0, max_steps=steps, threads=threads)
    started_ray = connect_ray(None, num_cpus=threads)
    try:
        runner_actor = ray.remote(num_cpus=threads, max_concurrency=2)(TrialRunner)
        service = runner_actor.remote(SERVICE_TASK, config, 0, SimulationPool(SERVICE_TASK, threads, []), steps)
        worker_actor = ray.remote(num_cpus=max(1, threads // 2))(_simulation_worker_class())
        remote_worker = worker_actor.remote(SERVICE_TASK, max(1, threads // 2))
        split_pool = SimulationPool(SERVICE_TASK, max(1, threads // 2), [remote_worker])
        split = ray.remote(num_cpus=0, max_concurrency=2)(TrialRunner).remote(SERVICE_TASK, config, 0, split_pool, steps)
        ray.get([service.pid.remote(), split.pid.remote()])
        # Alternate the three so that machine noise hits all of them alike.
        local_s, service_s, split_s = [], [], []
        for _ in range(3):
            local_s.append(in_process.run_episode(0).planning_seconds.mean())
            service_s.append(ray.get(service.run_episode.remote(0)).planning_seconds.mean())
            split_s.append(ray.get(split.run_episode.remote(0)).planning_seconds.mean())
        service_memory = ray.get(service.peak_memory_mb.remote())
    finally:
        in_process.evaluator.close()
        if started_ray:
            ray.shutdown()
    local, through_service, through_split = (float(np.median(x)) for x in (local_s, service_s, split_s))
    return {
        "task": SERVICE_TASK,
        "budget": SERVICE_BUDGET,
        "steps": steps,
        "in_process_seconds_per_step": local,
        "service_seconds_per_step": through_service,
        "ratio": through_service / local,
        "overhead_percent": 100.0 * (through_service / local - 1.0),
        "service_one_remote_worker_seconds_per_step": through_split,
        "one_remote_worker_ratio": through_split / local,
        "service_runner_peak_memory_mb": service_memory,
    }


def _simulation_worker_class():
    from workers.actors import SimulationWorker

    return SimulationWorker


def run_benchmark(tasks: list[str], budgets: list[int], steps: int, threads: int | None, service: bool = True):
    """All figures of ``icemlab bench`` as one JSON-serialisable dict."""
    threads = threads or default_threads()
    results: dict[str, Any] = {"threads": threads, "horizon": HORIZON, "tasks": {}}
    for name in tasks:
        task = make_task(name)
        env = task.make_env()
        env.reset(seed=0)
        model = task.build_planning_model(env)
        raw = raw_physics_rate(task, model, task.capture(env))
        env.close()
        entries = []
        for budget in budgets:
            figures = planner_figures(name, budget, steps, threads)
            figures["raw_physics_steps_per_second"] = raw
            figures["cores_used"] = threads
            figures["ratio"] = figures["planner_physics_steps_per_second"] / (raw * threads)
            entries.append(figures)
        results["tasks"][name] = entries
    results["in_process_peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if service:
        results["service"] = service_figures(steps * 3, threads)
    return results


def print_report(results: dict[str, Any]) -> None:
    threads = results["threads"]
    print(f"icemlab bench: {threads} thread(s), horizon {results['horizon']}\n")
    header = f"{'task':22s} {'budget':>6s} {'raw 1-thr':>12s} {'planner':>12s} {'ratio':>6s} {'s/step':>8s} {'thesis 1/32 thr':>16s}"
    print(header)
    print("-" * len(header))
    for name, entries in results["tasks"].items():
        for e in entries:
            thesis = "-"
            if e["thesis_seconds_per_step_1_thread"] is not None:
                thesis = f"{e['thesis_seconds_per_step_1_thread']:.3f}/{e['thesis_seconds_per_step_32_threads']:.3f}"
            print(f"{name:22s} {e['budget']:>6d} {e['raw_physics_steps_per_second']:>12,.0f} "
                  f"{e['planner_physics_steps_per_second']:>12,.0f} {e['ratio']:>6.2f} "
                  f"{e['seconds_per_step']:>8.3f} {thesis:>16s}")  # fmt: skip
    print("\nraw: physics steps/s, one thread; planner: physics steps/s of planning with all threads;")
    print(f"ratio = planner / (raw x {threads}); s/step: planning seconds per environment step.")
    print(f"peak memory of the in-process runs: {results['in_process_peak_memory_mb']:.0f} MB")
    if "service" in results:
        s = results["service"]
        print(f"\nservice vs in-process ({s['task']}, budget {s['budget']}, {s['steps']} steps, median of 3):")
        print(f"  in-process          {s['in_process_seconds_per_step']:.4f} s/step")
        print(f"  service (default)   {s['service_seconds_per_step']:.4f} s/step   ratio {s['ratio']:.3f} "
              f"({s['overhead_percent']:+.1f}%)")  # fmt: skip
        print(f"  one remote worker   {s['service_one_remote_worker_seconds_per_step']:.4f} s/step   "
              f"ratio {s['one_remote_worker_ratio']:.3f}")  # fmt: skip
        print(f"  trial actor peak memory {s['service_runner_peak_memory_mb']:.0f} MB")
