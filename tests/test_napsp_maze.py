"""The learned distance on a fixed Point Maze dataset (thesis section 6.4.3, Fig. 20 and 23).

The dataset never connects the start room to the goal room within one
episode: scripted episodes move back and forth between two adjacent rooms
through their door (lower left - upper left, upper left - upper right, lower
left - lower right, lower right - upper right), and the most recent episodes
start in the start room with a goal in the goal room and push straight at it,
sticking in the corner by the central wall block (the Euclidean local
optimum of Fig. 20). The temporal loss alone never sees a start-room state
with a goal-room goal; the triangular loss joins start-room-to-side-room and
side-room-to-goal-room segments through states that reached the goal.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import spearmanr

from workers.distance.buffer import Episodes
from workers.distance.config import CountSettings, DistanceSettings
from workers.distance.trainer import DistanceTrainer
from workers.tasks.goal_tasks import make_goal_task

ROOMS = {
    "start": [(4, 1), (4, 2), (5, 1), (5, 2)],
    "upper_left": [(1, 1), (1, 2), (2, 1), (2, 2)],
    "goal": [(1, 4), (1, 5), (2, 4), (2, 5)],
    "lower_right": [(4, 4), (4, 5), (5, 4), (5, 5)],
}
DOORS = {
    ("start", "upper_left"): (3, 1),
    ("upper_left", "goal"): (1, 3),
    ("start", "lower_right"): (5, 3),
    ("lower_right", "goal"): (3, 5),
}


def cell_xy(row: int, col: int) -> np.ndarray:
    """Centre of a cell of the 7 x 7 map (gymnasium-robotics' convention, scale 1)."""
    return np.array([col - 3.0, 3.0 - row])


def in_room(points: np.ndarray, room: str) -> np.ndarray:
    x, y = points[..., 0], points[..., 1]
    return {
        "start": (x < -0.5) & (y < -0.5),
        "upper_left": (x < -0.5) & (y > 0.5),
        "goal": (x > 0.5) & (y > 0.5),
        "lower_right": (x > 0.5) & (y < -0.5),
    }[room]


class Scripted:
    """Episodes of a noisy waypoint controller in the Point Maze task."""

    def __init__(self, seed: int):
        self.task = make_goal_task("point_maze")
        self.env = self.task.make_env()
        self.rng = np.random.default_rng(seed)

    def point(self, room: str) -> np.ndarray:
        return cell_xy(*ROOMS[room][self.rng.integers(4)]) + self.rng.uniform(-0.4, 0.4, 2)

    def _run(self, start: str, goal: str, next_target) -> tuple:
        options = {
            "reset_cell": np.array(ROOMS[start][self.rng.integers(4)]),
            "goal_cell": np.array(ROOMS[goal][self.rng.integers(4)]),
        }
        observation, _ = self.env.reset(seed=int(self.rng.integers(2**31)), options=options)
        state, _, desired = self.task.split(observation)
        states, actions = [state], []
        for _ in range(self.task.episode_length):
            target = next_target(state, desired)
            action = np.clip(4 * (target - state[:2]) - 0.6 * state[2:], -1, 1) + 0.3 * self.rng.normal(size=2)
            action = np.clip(action, -1, 1)
            state = self.task.split(self.env.step(action)[0])[0]
            states.append(state)
            actions.append(action)
        states = np.array(states)
        return states, np.array(actions), states[:, :2].copy(), desired

    def patrol(self, first: str, second: str) -> tuple:
        """Keep moving between random points of two adjacent rooms, through their door."""
        door = cell_xy(*DOORS.get((first, second), DOORS.get((second, first))))
        plan, room = [self.point(first)], [first]

        def next_target(state, _):
            if np.linalg.norm(state[:2] - plan[0]) < 0.35:
                plan.pop(0)
                if not plan:
                    if self.rng.random() < 0.6:
                        room[0] = second if room[0] == first else first
                        plan.extend([door, self.point(room[0])])
                    else:
                        plan.append(self.point(room[0]))
            return plan[0]

        return self._run(first, second, next_target)

    def straight_at_the_goal(self) -> tuple:
        return self._run("start", "goal", lambda state, desired: desired)

    @staticmethod
    def pack(episodes: list[tuple]) -> Episodes:
        states, actions, achieved, goals = map(np.array, zip(*episodes))
        return Episodes(states, actions, achieved, goals, np.zeros(actions.shape[:2]))


@pytest.fixture(scope="module")
def dataset():
    script = Scripted(seed=0)
    pairs = list(DOORS)
    old = script.pack([script.patrol(*pair[:: 1 if i % 2 else -1]) for pair in pairs for i in range(30)])
    stuck = [script.straight_at_the_goal() for _ in range(16)]
    # The dataset must not join the rooms: keep the start-room episodes that never left the start room.
    stuck = [e for e in stuck if in_room(e[2], "start").all() or not in_room(e[2], "goal").any()]
    recent = script.pack(stuck)
    assert not (
        in_room(old.achieved_goals, "start").any(axis=1) & in_room(old.achieved_goals, "goal").any(axis=1)
    ).any()
    assert not in_room(recent.achieved_goals, "goal").any()
    yield script.task, old, recent
    script.env.close()


def train(dataset, triangular: bool, calls: int = 30, sigma: float = 20.0) -> DistanceTrainer:
    """A DistanceTrainer on the whole dataset, the stuck episodes as D_last, ``calls`` distance phases."""
    torch.set_num_threads(1)
    _, old, recent = dataset
    settings = DistanceSettings(
        hidden=(256, 256),
        triangular=triangular,
        temporal_updates_per_episode=10,
        triangular_updates_per_episode=10,
    )
    counts = CountSettings(single_key_dim=64, pair_key_dim=32, sigma=sigma)
    trainer = DistanceTrainer(settings, counts, 4, 2, 2, 100, seed=0)
    trainer.add_episodes(old)
    trainer.add_episodes(recent)
    for _ in range(calls):
        trainer.train()  # one temporal phase, one d_old copy, one triangular phase
    return trainer


def evaluate(trainer: DistanceTrainer, dataset) -> dict[str, float]:
    """Rank correlations with the geodesic and the Euclidean distance, and d from each room to the goal room."""
    task, old, recent = dataset
    rng = np.random.default_rng(1)
    states = np.concatenate([old.observations[:, :-1].reshape(-1, 4), recent.observations[:, :-1].reshape(-1, 4)])
    actions = np.concatenate([old.actions.reshape(-1, 2), recent.actions.reshape(-1, 2)])
    goal_points = states[in_room(states[:, :2], "goal"), :2]
    function = trainer.model.function
    figures: dict[str, float] = {}
    # Every dataset state against goal-room goals (the task's question, Fig. 23's heat map).
    index = rng.integers(len(states), size=4000)
    goals = goal_points[rng.integers(len(goal_points), size=4000)]
    d = function(states[index], actions[index], goals)
    geodesic = task.maze_distance.distance(states[index, :2], goals)
    euclidean = np.linalg.norm(states[index, :2] - goals, axis=1)
    figures["rank_geodesic"] = float(spearmanr(d, geodesic)[0])
    figures["rank_euclidean"] = float(spearmanr(d, euclidean)[0])
    for room in ("start", "upper_left", "lower_right", "goal"):
        inside = in_room(states[index, :2], room)
        figures[f"d_{room}"] = float(d[inside].mean())
        figures[f"geodesic_{room}"] = float(geodesic[inside].mean())
    return figures


@pytest.mark.slow
def test_triangular_loss_closes_the_start_room_gap(dataset):
    temporal = evaluate(train(dataset, triangular=False), dataset)
    ours = evaluate(train(dataset, triangular=True), dataset)
    print("temporal only", {k: round(v, 3) for k, v in temporal.items()})
    print("both losses", {k: round(v, 3) for k, v in ours.items()})
    # The start room is twice as far from the goal room as the side rooms (geodesic).
    side = (ours["geodesic_upper_left"] + ours["geodesic_lower_right"]) / 2
    assert ours["geodesic_start"] > 1.5 * side

    def gap(figures):
        return figures["d_start"] / ((figures["d_upper_left"] + figures["d_lower_right"]) / 2)

    # Temporal only: nothing says the start room is farther than the side rooms.
    assert gap(temporal) < 1.2
    # Both losses: the start room is pushed out by the triangle through the side rooms.
    assert gap(ours) > gap(temporal) + 0.2
    # d ranks the states like the geodesic distance more than like the straight line.
    assert ours["rank_geodesic"] > ours["rank_euclidean"]
