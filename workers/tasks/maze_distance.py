"""Ground-truth shortest-path distances in a gymnasium-robotics maze (for evaluating Point Maze, section 6.6).

The learned distance of chapter 6 approximates the number of steps along the
shortest path; to judge it (and to plot heat maps like Fig. 23) we need the
true geodesic distance between two points of the maze, walls included. The
maze map is rasterised into square cells of side ``resolution``; a cell is free
when the ball (radius ``clearance``) fits there. Dijkstra on the cells with
16 neighbours (the 8 king moves and the 8 knight moves, a move allowed only
when every cell it crosses is free) approximates Euclidean path lengths within
about 3 % (8-neighbour grids are off by up to 8 %), plus one cell of
discretisation. Distances are in world units, inf where a point cannot reach
the goal.

The coordinate convention is gymnasium-robotics' ``Maze.cell_rowcol_to_xy``:
cell (i, j) has its centre at x = (j + 1/2) s - W s / 2, y = H s / 2 - (i + 1/2) s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

MOVE_REACH = 3
"""Moves go to every cell (dr, dc) with max(|dr|, |dc|) <= 3 and gcd 1: 32 directions, path lengths within ~1 %."""


def _moves(reach: int) -> list[tuple[int, int]]:
    """One of each opposite pair of primitive moves (the graph is undirected)."""
    moves = []
    for dr in range(0, reach + 1):
        for dc in range(-reach, reach + 1):
            if (dr, dc) == (0, 0) or math.gcd(dr, abs(dc)) != 1 or (dr == 0 and dc < 0):
                continue
            moves.append((dr, dc))
    return moves


def _crossed_cells(dr: int, dc: int) -> list[tuple[int, int]]:
    """Offsets of the cells a straight move between two cell centres passes through (ends excluded).

    The segment is sampled densely; a sample exactly on a cell corner counts
    the cells on both sides, so a move never squeezes between two blocked
    cells that touch at a corner.
    """
    crossed: set[tuple[int, int]] = set()
    for t in np.linspace(0.0, 1.0, 64 * (abs(dr) + abs(dc)) + 1):
        r, c = 0.5 + t * dr, 0.5 + t * dc
        for rr in {math.floor(r - 1e-9), math.floor(r + 1e-9)}:
            for cc in {math.floor(c - 1e-9), math.floor(c + 1e-9)}:
                crossed.add((rr, cc))
    crossed.discard((0, 0))
    crossed.discard((dr, dc))
    return sorted(crossed)


class MazeDistance:
    """Geodesic distances in a maze map (1 = wall; anything else free).

    Args:
        maze_map: rows of the map, top row first, as given to gymnasium-robotics.
        scale: side of one map cell in world units (``maze_size_scaling``, 1 for Point Maze).
        resolution: side of a raster cell in world units.
        clearance: radius of the ball; cells closer than this to a wall are blocked (0.1 in PointMaze).
    """

    def __init__(
        self,
        maze_map: Sequence[Sequence[object]],
        scale: float = 1.0,
        resolution: float = 0.05,
        clearance: float = 0.1,
    ):
        walls = np.array([[cell == 1 for cell in row] for row in maze_map], dtype=bool)
        self.map_rows, self.map_cols = walls.shape
        self.scale = float(scale)
        self.subdivisions = max(1, int(round(scale / resolution)))
        self.resolution = self.scale / self.subdivisions
        self.x_center = self.map_cols * self.scale / 2
        self.y_center = self.map_rows * self.scale / 2
        fine_walls = np.kron(walls, np.ones((self.subdivisions, self.subdivisions), dtype=bool))
        # Distance from a cell centre to the nearest wall cell centre, minus half a cell: to the wall surface.
        to_wall = ndimage.distance_transform_edt(~fine_walls) * self.resolution - self.resolution / 2
        self.free = ~fine_walls & (to_wall >= clearance - 1e-9)
        self.shape = self.free.shape
        self.graph = self._build_graph()
        # Points that land on a blocked cell (inside the clearance band) snap to the nearest free cell.
        _, nearest = ndimage.distance_transform_edt(~self.free, return_indices=True)
        self._nearest_free = nearest

    def _build_graph(self):
        rows, cols = self.shape
        index = np.arange(rows * cols).reshape(rows, cols)
        sources, targets, weights = [], [], []
        for dr, dc in _moves(MOVE_REACH):
            # Source cells whose destination (r + dr, c + dc) lies inside the grid.
            r0, r1 = max(0, -dr), rows - max(0, dr)
            c0, c1 = max(0, -dc), cols - max(0, dc)
            ok = self.free[r0:r1, c0:c1] & self.free[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
            for cr, cc in _crossed_cells(dr, dc):
                ok &= self.free[r0 + cr : r1 + cr, c0 + cc : c1 + cc]
            sources.append(index[r0:r1, c0:c1][ok])
            targets.append(index[r0 + dr : r1 + dr, c0 + dc : c1 + dc][ok])
            weights.append(np.full(int(ok.sum()), np.hypot(dr, dc) * self.resolution))
        src, dst, w = np.concatenate(sources), np.concatenate(targets), np.concatenate(weights)
        size = rows * cols
        return coo_matrix((np.r_[w, w], (np.r_[src, dst], np.r_[dst, src])), shape=(size, size)).tocsr()

    # ------------------------------------------------------------ geometry
    def cells(self, points: np.ndarray) -> np.ndarray:
        """Flat raster index of world points (..., 2), snapped to the nearest free cell."""
        points = np.asarray(points, dtype=np.float64)
        col = np.floor((points[..., 0] + self.x_center) / self.resolution).astype(np.int64)
        row = np.floor((self.y_center - points[..., 1]) / self.resolution).astype(np.int64)
        row = np.clip(row, 0, self.shape[0] - 1)
        col = np.clip(col, 0, self.shape[1] - 1)
        row, col = self._nearest_free[0][row, col], self._nearest_free[1][row, col]
        return row * self.shape[1] + col

    def cell_centers(self) -> np.ndarray:
        """(rows, cols, 2) world coordinates of the raster cells (for heat maps)."""
        cols = (np.arange(self.shape[1]) + 0.5) * self.resolution - self.x_center
        rows = self.y_center - (np.arange(self.shape[0]) + 0.5) * self.resolution
        x, y = np.meshgrid(cols, rows)
        return np.stack([x, y], axis=-1)

    # ----------------------------------------------------------- distances
    def distance_field(self, goal: np.ndarray) -> np.ndarray:
        """(rows, cols) distance of every raster cell to one goal point (inf: blocked or unreachable)."""
        field = dijkstra(self.graph, indices=int(self.cells(goal)))
        field = field.reshape(self.shape)
        field[~self.free] = np.inf
        return field

    def distance(self, points: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Shortest-path distance from each point (N, 2) to its goal (N, 2) (or one goal (2,) for all)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        goals = np.broadcast_to(np.asarray(goals, dtype=np.float64), points.shape)
        sources = self.cells(points)
        goal_cells = self.cells(goals)
        unique, inverse = np.unique(goal_cells, return_inverse=True)
        # One Dijkstra per distinct goal cell (the graph is undirected: goal -> point = point -> goal).
        table = dijkstra(self.graph, indices=unique)
        return table[inverse.reshape(-1), sources]
