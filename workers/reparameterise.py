"""Re-expressing a network's first layer under a new input standardisation.

A network that is trained again on a moved dataset (APEX's policy window,
the MBRL ensemble's growing dataset) gets its input standardisation refitted.
With z = (x - m) / s the old and z' = (x - m') / s' the new standardised
input, z = r z' + c with r = s' / s and c = (m' - m) / s, so the first
layer's weights scaled by r (per input) and its bias shifted by W c compute
the same function of the raw input x as before.

Adam's moments belong to the old coordinates. Under W' = W r the gradient
of the same function becomes g' = g / r (the bias's gradient is unchanged),
so the first moment is carried to m / r and the second to v / r^2: the
moments of the same gradient history expressed in the new coordinates
(exactly for a pure rescale; the shift c has no counterpart in a diagonal
optimiser state). Left in the old coordinates, v would stay r^2 times too
large for the new gradients until Adam's second moment forgets it (beta2 =
0.999: about a thousand steps, a whole training), shrinking the first
layer's steps by up to r.
"""

from __future__ import annotations

import torch


def rescale_inputs_of(weight: torch.nn.Parameter, scale: torch.Tensor, optimiser: torch.optim.Optimizer) -> None:
    """Multiply ``weight`` by ``scale`` (broadcast over its input axis) and carry Adam's moments along.

    Args:
        weight: a first layer's weight matrix (any layout; ``scale`` is shaped to broadcast against it).
        scale: r = s' / s, the new input scale over the old one.
        optimiser: the Adam-family optimiser that holds ``weight``; a weight it has not stepped yet has no
            moments to carry.
    """
    with torch.no_grad():
        weight.mul_(scale)
        state = optimiser.state.get(weight)
        if not state:
            return
        state["exp_avg"].div_(scale)
        for key in ("exp_avg_sq", "max_exp_avg_sq"):
            if key in state:
                state[key].div_(scale.square())
