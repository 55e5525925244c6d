"""gymnasium-robotics 1.4.2 on MuJoCo 3.12 and later: its joint helpers without the failing type check.

``gymnasium_robotics.utils.mujoco_utils`` reads and writes a joint's slice of
qpos / qvel in four helpers (``get_joint_qpos``, ``set_joint_qpos``,
``get_joint_qvel``, ``set_joint_qvel``). Each first asserts the joint type
with ``model.jnt_type[i] in (mjtJoint.mjJNT_HINGE, mjtJoint.mjJNT_SLIDE)``.
From MuJoCo 3.12 on, an ``mjtJoint`` member no longer compares equal to a
numpy integer when the enum is on the left of ``==`` (``mjJNT_HINGE ==
np.int32(3)`` is False; ``np.int32(3) == mjJNT_HINGE`` and ``mjJNT_HINGE ==
3`` are still True), so that assert fails and no Fetch environment can be
built: every reset places the object through these helpers.

:func:`patch_joint_helpers` replaces the four module attributes with
equivalents that compare plain ints. The environments call the helpers
through the module (``self._utils.get_joint_qpos``), so the replacements take
effect for environments built before or after. The installed library is not
edited. Behaviour is that of 1.4.2, including its quirk that
``get_joint_qvel`` returns four values for a ball joint (which has three
degrees of freedom); on MuJoCo before 3.12 the results are identical.
"""

from __future__ import annotations

import logging
from types import ModuleType

import mujoco
import numpy as np

FREE, BALL, SLIDE, HINGE = (int(t) for t in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL,
                                             mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE))  # fmt: skip

# Width of a joint's slice by joint type, as gymnasium-robotics 1.4.2 reads and writes it.
QPOS_WIDTH = {FREE: 7, BALL: 4, SLIDE: 1, HINGE: 1}
QVEL_WIDTH = {FREE: 6, BALL: 3, SLIDE: 1, HINGE: 1}
QVEL_READ_WIDTH = QVEL_WIDTH | {BALL: 4}  # 1.4.2's get_joint_qvel


def _joint_slice(model: mujoco.MjModel, name: str, addresses: np.ndarray, widths: dict[int, int]) -> slice:
    joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    if joint == -1:
        raise AssertionError(f"Joint with name '{name}' is not part of the model!")
    joint_type = int(model.jnt_type[joint])
    if joint_type not in widths:
        raise AssertionError(f"joint {name!r} has an unknown type {joint_type}")
    start = int(addresses[joint])
    return slice(start, start + widths[joint_type])


def _write(target: np.ndarray, span: slice, name: str, value) -> None:
    value = np.array(value)
    width = span.stop - span.start
    if width > 1 and value.shape != (width,):
        raise AssertionError(f"Value has incorrect shape {name}: {value}")
    target[span] = value


def get_joint_qpos(model, data, name):
    """The joint's positions (free: 7, ball: 4, hinge or slide: 1), a copy."""
    return data.qpos[_joint_slice(model, name, model.jnt_qposadr, QPOS_WIDTH)].copy()


def get_joint_qvel(model, data, name):
    """The joint's velocities (free: 6, ball: 4 as in 1.4.2, hinge or slide: 1), a copy."""
    return data.qvel[_joint_slice(model, name, model.jnt_dofadr, QVEL_READ_WIDTH)].copy()


def set_joint_qpos(model, data, name, value):
    """Write the joint's positions."""
    _write(data.qpos, _joint_slice(model, name, model.jnt_qposadr, QPOS_WIDTH), name, value)


def set_joint_qvel(model, data, name, value):
    """Write the joint's velocities."""
    _write(data.qvel, _joint_slice(model, name, model.jnt_dofadr, QVEL_WIDTH), name, value)


REPLACEMENTS = {
    "get_joint_qpos": get_joint_qpos,
    "get_joint_qvel": get_joint_qvel,
    "set_joint_qpos": set_joint_qpos,
    "set_joint_qvel": set_joint_qvel,
}


def patch_joint_helpers(utils: ModuleType | None = None) -> None:
    """Replace the four joint helpers of ``gymnasium_robotics.utils.mujoco_utils`` (idempotent)."""
    if utils is None:
        from gymnasium_robotics.utils import mujoco_utils as utils
    for name, function in REPLACEMENTS.items():
        setattr(utils, name, function)


def route_warnings_to_logging() -> None:
    """Send MuJoCo's warnings to Python's logging (logger ``mujoco``), each distinct text once per process.

    MuJoCo's own handler appends every warning to a MUJOCO_LOG.TXT in the working directory: a stray file in
    the user's project after any run on HalfCheetah, whose model from gymnasium uses ``settotalmass``, which
    MuJoCo 3.x and 4 warn is deprecated when they compile it.
    """
    logger = logging.getLogger("mujoco")
    seen: set[str] = set()

    def warn(message: str) -> None:
        if message not in seen:
            seen.add(message)
            logger.warning("MuJoCo: %s", message.strip())

    mujoco.set_mju_user_warning(warn)
