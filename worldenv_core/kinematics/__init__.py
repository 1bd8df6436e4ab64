"""Kinematics without the simulator: the next proprio state from an action (OSC_POSE),
the Panda chain (pytorch-kinematics), camera projection and the action maps drawn from them."""

from worldenv_core.kinematics.action_map import draw_action_maps
from worldenv_core.kinematics.camera import PinholeCamera
from worldenv_core.kinematics.next_state import OSC_POS_SCALE, OSC_ROT_SCALE, NextStateModel

__all__ = ["NextStateModel", "OSC_POS_SCALE", "OSC_ROT_SCALE", "PinholeCamera", "draw_action_maps"]
