"""The robot's contract, in one place: LIBERO's Panda with robosuite's OSC_POSE controller."""

import numpy as np

PROPRIO_DIM = 7  # eef pos (3), eef axis-angle (3), gripper opening (1)
JOINT_DIM = 7  # Panda arm joints
ACTION_DIM = 7  # OSC_POSE delta (pos 3, rot 3) + gripper command (-1 open, +1 close)
# Each Panda finger joint travels 0..0.04 m (the right one negatively); the gap spans 0..0.08 m.
FINGER_GAP_MAX = 0.08


def gripper_opening(q_left, q_right):
    """The paper's gripper state p in [0, 1] from the two finger joint positions."""
    return np.clip((np.asarray(q_left) - np.asarray(q_right)) / FINGER_GAP_MAX, 0.0, 1.0)
