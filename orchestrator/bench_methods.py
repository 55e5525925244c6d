"""``icemlab bench --methods``: speed figures of the learning methods, as ratios measured in one run.

* apex: relabeled states per second through one and through two RelabelWorker
  actors (Ray, one CPU each) on the same chunks of a HalfCheetah policy
  episode, guided iCEM_pi at budget 45 (Table 12's setting); the policy
  trainer's gradient steps per second; and the core-minutes of one APEX
  iteration on HalfCheetah (one 1000-step expert episode, 1000 relabeled
  states, two trainings of 1000 gradient steps; Table 10) estimated from
  those rates, next to Table 12's 5.6 min x 32 cores;
* mbrl: the ensemble evaluator's linear-layer FLOP rate against plain dense
  matmuls of the same layer sizes and batch, per ensemble preset;
* napsp: SAC + HER learner updates per second (Table 19 networks, the
  learned-distance reward recomputed at sampling time) against a bare torch
  loop of the same networks on one fixed batch; and seconds per iteration
  with the learner and the DistanceTrainer as two Ray actors, in ``sync``
  order against ``pipelined``.

The measurements themselves live next to the code they measure
(workers/policy/benchmark.py, workers/dynamics/benchmark.py,
workers/distance/bench.py); this module picks their settings and runs them.
"""

from __future__ import annotations

from typing import Any

METHODS = ("apex", "mbrl", "napsp")
TABLE_12_CORE_MINUTES = 5.6 * 32
"""Table 12: one APEX iteration on HalfCheetah took 5.6 minutes on 32 cores."""
APEX_TASK = "halfcheetah_running"
APEX_EPISODE_STEPS = 1000
APEX_GRADIENT_STEPS = 1000


def apex_figures(quick: bool) -> dict[str, Any]:
    """Relabeling with 1 and 2 RelabelWorker actors, training speed, and core-minutes per iteration."""
    import ray

    from orchestrator.placement import RayRoleGroup
    from orchestrator.scheduler import connect_ray
    from workers.policy.benchmark import relabel_rates, relabel_workload, training_rates
    from workers.policy.worker import RelabelWorker
    from workers.tasks import make_task

    workload = relabel_workload(APEX_TASK, states=40 if quick else 100, chunk=10)
    started_ray = connect_ray(None, num_cpus=2)
    try:
        remote = ray.remote(num_cpus=1)(RelabelWorker)
        actors = [remote.remote(APEX_TASK, None, 1) for _ in range(2)]
        groups = [RayRoleGroup("relabel", actors[:1]), RayRoleGroup("relabel", actors)]
        relabel = relabel_rates(groups, workload)
    finally:
        if started_ray:
            ray.shutdown()
    task = make_task(APEX_TASK)
    observation_size = len(workload.chunks[0][1][0])
    training = training_rates(observation_size, task.action_dim, threads=(1,), steps=100 if quick else 300)
    # One iteration (n = 1): the expert episode and the relabeling each plan 1000 steps at the same budget;
    # the policy episode itself is a forward pass per step (negligible); two trainings.
    planning_core_seconds = 2 * APEX_EPISODE_STEPS / relabel["states_per_second"][0]
    training_core_seconds = 2 * APEX_GRADIENT_STEPS / training["steps_per_second"][0]
    core_minutes = (planning_core_seconds + training_core_seconds) / 60.0
    return {
        "task": APEX_TASK,
        "budget": workload.settings.planner.budget,
        "relabel": relabel,
        "training": training,
        "iteration_core_minutes": core_minutes,
        "table_12_core_minutes": TABLE_12_CORE_MINUTES,
        "fraction_of_table_12": core_minutes / TABLE_12_CORE_MINUTES,
    }


def mbrl_figures(quick: bool) -> dict[str, Any]:
    """Ensemble evaluator against dense matmuls, for the thesis's presets on their tasks' shapes and ``small``."""
    from workers.dynamics.benchmark import measure_ensemble_throughput
    from workers.dynamics.settings import PRESET_SHAPES, EnsembleConfig

    shapes = dict(PRESET_SHAPES) | {"small": PRESET_SHAPES["bridge_maze"]}
    results = {}
    for preset, (obs_dim, action_dim) in shapes.items():
        report = measure_ensemble_throughput(
            EnsembleConfig.preset(preset), obs_dim, action_dim, sequences=64 if quick else 128, repeats=3
        )
        results[preset] = report._asdict()
    return {"presets": results}


def napsp_figures(quick: bool) -> dict[str, Any]:
    """Learner updates per second against a bare torch loop, Point Maze and FetchReach shapes."""
    from workers.distance.bench import measure_learner_updates
    from workers.distance.config import LearnerSettings
    from workers.tasks import make_task

    results = {}
    for name in ("point_maze", "fetch_reach"):
        task = make_task(name)
        results[name] = measure_learner_updates(
            LearnerSettings(),
            task.obs_dim,
            task.action_dim,
            task.goal_dim,
            updates=60 if quick else 200,
            blocks=3 if quick else 5,
        )
    return {"tasks": results, "modes": napsp_mode_figures(quick)}


NAPSP_MODES_TASK = "fetch_reach"


def napsp_mode_figures(quick: bool) -> dict[str, Any]:
    """Seconds per iteration, sync against pipelined, each with its learner and DistanceTrainer as Ray actors.

    FetchReach with Table 19/20's networks and updates (``--quick``: a tenth of
    the updates). Each role actor runs torch on one thread and asks Ray for half
    a CPU, so both modes' four actors fit on two cores; only one mode runs at a
    time, so a pipelined iteration has one core per role, as it would in a sweep.
    """
    import ray

    from orchestrator.placement import RayRoleGroup
    from orchestrator.scheduler import connect_ray
    from workers.distance.bench import compare_modes
    from workers.methods import TrialSpec
    from workers.methods.napsp import NapspProgram, NapspSettings
    from workers.tasks import make_task

    task = make_task(NAPSP_MODES_TASK)
    measured, warmup = (2, 1) if quick else (4, 1)
    tenth = {"updates_per_episode": 10} if quick else {}
    started_ray = connect_ray(None, num_cpus=2)
    try:
        programs = {}
        for mode in ("sync", "pipelined"):
            raw = NapspSettings.model_validate({
                "mode": mode,
                "iterations": warmup + measured,
                "iterations_per_round": 1,
                "plot_every": 0,
                "learner": tenth,
                "distance": {"temporal_updates_per_episode": 10, "triangular_updates_per_episode": 10} if quick else {},
            })  # fmt: skip
            spec = TrialSpec("napsp", NAPSP_MODES_TASK, NapspProgram.resolve(raw, task), 0)
            roles = {}
            for role in NapspProgram.roles_for(spec, 1, {}):
                actor = ray.remote(num_cpus=0.5)(role.worker).remote(**role.kwargs)
                roles[role.name] = RayRoleGroup(role.name, [actor])
            programs[mode] = NapspProgram(spec, roles, 1)
        figures = compare_modes(programs, measured, warmup)
    finally:
        if started_ray:
            ray.shutdown()
    return {"task": NAPSP_MODES_TASK, **figures}


FIGURES = {"apex": apex_figures, "mbrl": mbrl_figures, "napsp": napsp_figures}


def method_figures(methods: list[str], quick: bool) -> dict[str, Any]:
    return {name: FIGURES[name](quick) for name in methods}


def print_method_report(results: dict[str, Any]) -> None:
    if "apex" in results:
        a = results["apex"]
        r = a["relabel"]
        print(f"\napex ({a['task']}, iCEM_pi, budget {a['budget']}, {r['states']} states, {r['chunks']} chunks):")
        for workers, rate, ratio in zip(r["workers"], r["states_per_second"], r["ratio_to_first"]):
            print(f"  relabeling, {workers} RelabelWorker(s) {rate:8.2f} states/s   x{ratio:.2f}")
        print(f"  policy training, 1 thread {a['training']['steps_per_second'][0]:8.1f} gradient steps/s")
        print(
            f"  one iteration (1000-step expert episode, 1000 relabeled states, 2 x 1000 gradient steps): "
            f"{a['iteration_core_minutes']:.2f} core-minutes, {a['fraction_of_table_12']:.4f} of Table 12's "
            f"{a['table_12_core_minutes']:.0f}"
        )
    if "mbrl" in results:
        print("\nmbrl: ensemble evaluator vs dense matmuls of the same layer sizes (linear-layer FLOP/s):")
        for preset, r in results["mbrl"]["presets"].items():
            print(
                f"  {preset:18s} {r['particle_steps_per_second']:>12,.0f} particle-steps/s  "
                f"{r['ensemble_flops_per_second'] / 1e9:6.2f} GFLOP/s vs {r['dense_flops_per_second'] / 1e9:6.2f}  "
                f"ratio {r['ratio']:.2f}  ({r['rows_per_model_step']} rows, {r['threads']} threads)"
            )
    if "napsp" in results:
        print("\nnapsp: SAC + HER learner updates vs a bare torch loop of the same networks:")
        for name, r in results["napsp"]["tasks"].items():
            print(
                f"  {name:12s} learner {r['learner_updates_per_second']:7.1f} updates/s, bare "
                f"{r['bare_updates_per_second']:7.1f}   ratio {r['ratio']:.2f} "
                f"(median over blocks {r['ratio_median_over_blocks']:.2f})"
            )
        m = results["napsp"]["modes"]
        seconds = m["seconds_per_iteration"]
        print(
            f"  {m['task']}: one iteration, learner and DistanceTrainer as two actors: sync {seconds['sync']:.2f} s, "
            f"pipelined {seconds['pipelined']:.2f} s   pipelined/sync {m['pipelined_over_sync']:.2f} "
            f"(median of {m['iterations']})"
        )
