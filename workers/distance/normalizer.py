"""Running input normalisation of the goal-conditioned networks (Table 19, "normalize input").

Table 19 repeats the defaults of OpenAI baselines' HER: observations and goals
are clipped to +-200, standardised with running statistics of everything seen
so far, and the result clipped to +-5; the standard deviation is floored at
0.01 so constant inputs (a fixed gripper joint) do not blow up.
"""

from __future__ import annotations

import numpy as np
import torch

from workers.distance.state import State


class RunningNormalizer:
    """Mean and standard deviation of a stream of vectors, applied with clipping.

    Args:
        size: vector dimension.
        clip_input: inputs are clipped to +-clip_input before the statistics and the normalisation.
        clip_output: normalised values are clipped to +-clip_output.
        eps: floor of the standard deviation.
    """

    def __init__(self, size: int, clip_input: float = 200.0, clip_output: float = 5.0, eps: float = 0.01):
        self.size = size
        self.clip_input = clip_input
        self.clip_output = clip_output
        self.eps = eps
        self.total = np.zeros(size)
        self.total_sq = np.zeros(size)
        self.count = 0
        self._refresh()

    def _refresh(self) -> None:
        if self.count == 0:
            self.mean, self.std = np.zeros(self.size), np.ones(self.size)
            return
        self.mean = self.total / self.count
        variance = self.total_sq / self.count - self.mean**2
        self.std = np.sqrt(np.maximum(self.eps**2, variance))

    def update(self, values: np.ndarray) -> None:
        """Add a batch (..., size) to the statistics."""
        values = np.clip(np.asarray(values, dtype=np.float64).reshape(-1, self.size), -self.clip_input, self.clip_input)
        self.total += values.sum(axis=0)
        self.total_sq += np.square(values).sum(axis=0)
        self.count += len(values)
        self._refresh()

    def normalize(self, values: np.ndarray) -> np.ndarray:
        """Clip, standardise and clip again (float32, ready for torch)."""
        values = np.clip(np.asarray(values, dtype=np.float64), -self.clip_input, self.clip_input)
        return np.clip((values - self.mean) / self.std, -self.clip_output, self.clip_output).astype(np.float32)

    def normalize_tensor(self, values: np.ndarray) -> torch.Tensor:
        """:meth:`normalize` as a torch tensor."""
        return torch.from_numpy(self.normalize(values))

    def state(self) -> State:
        """Exportable statistics."""
        return State({"total": self.total.copy(), "total_sq": self.total_sq.copy()}, {"count": self.count})

    def load(self, state: State) -> None:
        """Restore statistics exported by :meth:`state`."""
        self.total = np.array(state.arrays["total"], dtype=np.float64)
        self.total_sq = np.array(state.arrays["total_sq"], dtype=np.float64)
        self.count = int(state.meta["count"])
        self._refresh()
