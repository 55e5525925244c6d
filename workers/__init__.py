"""What runs inside the service's actors: tasks, batched rollouts, planners, the MPC loop.

Nothing here imports Ray or MLflow.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

MAX_SEED = 2**31 - 1
"""The largest trial seed: every library a trial seeds (numpy, torch, MuJoCo tasks, gymnasium) takes it, and the
offsets a trial adds to it (per episode, per model version) stay far inside 64 bits."""


@functools.cache
def code_fingerprint() -> str:
    """Hash of this package's source: driver and actors must run the same code.

    Results travel between them pickled; a node with another version of the
    code would fail obscurely (or silently compute something else).
    """
    digest = hashlib.sha256()
    root = Path(__file__).parent
    for path in sorted(root.rglob("*.py")) + sorted(root.rglob("*.xml")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
