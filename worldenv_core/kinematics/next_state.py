"""s_{t+1} = FK(s_t, a_t): the next proprio state from a delta end-effector action.

robosuite's OSC_POSE controller (LIBERO's default, `control_delta=True`) reads a 7-D action in
[-1, 1]: it scales the first three entries by 0.05 m and the next three by 0.5 rad, sets the
goal position to `eef_pos + dp` and the goal orientation to `exp(dr) @ R_eef` (the rotation
error composed on the left, in the world frame), then tracks that goal with a PD law for one
20 Hz control period. The last entry closes (+1) or opens (-1) the gripper.

The controller does not reach its goal within one period, and what it carries over shows up
as velocity in the next step. So the model is a first-order lag per step:

    dp_t = g_pos * 0.05 * a_t[:3]  + m_pos * dp_{t-1}
    dr_t = g_rot * 0.5  * a_t[3:6] + m_rot * dr_{t-1}       (axis-angle, world frame)
    dg_t = k_grip * (target(a_t[6]) - p_t) + m_grip * dg_{t-1},  p_{t+1} = clip(p_t + dg_t, closed, open)

The gripper opening p (1 = open) moves toward its open level when commanded open and toward its
closed level when commanded closed, fast at first and then settling: a lag with momentum, fitted
on every step. (The first model, a constant rate p_{t+1} = clip(p_t - g_grip * a_t[6], 0, 1), fitted
on the steps that moved it, lagged the real gripper by about 40 steps on each open or close, so
an imagined state showed the gripper open long after it had closed: models saved with it, without
`grip_lag`, keep it.)

`NextStateModel()` with gains 1 and momentum 0 is the controller's own interpretation (where it
aims); `NextStateModel.fit(episodes)` estimates the gains by least squares on recorded episodes,
which is what the world simulator uses. Everything is batched torch.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from pytorch_kinematics.transforms import axis_angle_to_quaternion, matrix_to_axis_angle, quaternion_to_matrix

OSC_POS_SCALE = 0.05  # metres per unit action (robosuite OSC_POSE output_max)
OSC_ROT_SCALE = 0.5  # radians per unit action


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    return quaternion_to_matrix(axis_angle_to_quaternion(rotvec))


@dataclass
class NextStateModel:
    g_pos: float = 1.0
    g_rot: float = 1.0
    m_pos: float = 0.0
    m_rot: float = 0.0
    g_grip: float = 1.0  # the constant-rate gripper, used when grip_lag is None
    grip_lag: float | None = None  # k_grip: the fraction of the way to the target level moved per step
    grip_momentum: float = 0.0  # m_grip
    grip_closed: float = 0.0  # the opening's levels, commanded closed and open
    grip_open: float = 1.0

    def step(self, state: torch.Tensor, action: torch.Tensor, prev: tuple | None = None):
        """state (B, 7), action (B, 7) -> (next state (B, 7), carry). `carry` holds the last
        position, rotation and gripper deltas for the momentum terms; pass it back for the next step."""
        dp = self.g_pos * OSC_POS_SCALE * action[:, :3].clamp(-1, 1)
        dr = self.g_rot * OSC_ROT_SCALE * action[:, 3:6].clamp(-1, 1)
        if prev is not None:
            dp = dp + self.m_pos * prev[0]
            dr = dr + self.m_rot * prev[1]
        rot = axis_angle_to_matrix(dr) @ axis_angle_to_matrix(state[:, 3:6])
        if self.grip_lag is None:
            grip = (state[:, 6] - self.g_grip * action[:, 6].clamp(-1, 1)).clamp(0, 1)
        else:
            target = torch.where(action[:, 6] > 0, self.grip_closed, self.grip_open).to(state.dtype)
            dg = self.grip_lag * (target - state[:, 6])
            if prev is not None:
                dg = dg + self.grip_momentum * prev[2]
            grip = (state[:, 6] + dg).clamp(self.grip_closed, self.grip_open)
        nxt = torch.cat([state[:, :3] + dp, matrix_to_axis_angle(rot), grip[:, None]], dim=1)
        return nxt, (dp, dr, grip - state[:, 6])

    def rollout(self, state: torch.Tensor, actions: torch.Tensor, prev: tuple | None = None):
        """state (B, 7), actions (B, K, 7) -> states s_{t+1..t+K} (B, K, 7) and the final carry."""
        out = []
        for k in range(actions.shape[1]):
            state, prev = self.step(state, actions[:, k], prev)
            out.append(state)
        return torch.stack(out, dim=1), prev

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def fit(cls, episodes) -> NextStateModel:
        """Least-squares gains from recorded (proprio, actions) pairs, one regression per part.
        `episodes`: iterable of objects with `proprio` (T+1, 7) and `actions` (T, 7)."""
        episodes = [ep for ep in episodes if len(ep.actions) >= 2]
        if not episodes:
            raise ValueError("NextStateModel.fit needs at least one episode with 2 or more actions")
        xp, yp, xr, yr, xg, yg = [], [], [], [], [], []
        levels = torch.cat([torch.as_tensor(ep.proprio[:, 6], dtype=torch.float64) for ep in episodes])
        # the levels the opening settles at (robust to a few outliers): fully closed and fully open
        closed, opened = (float(torch.quantile(levels, q)) for q in (0.005, 0.995))
        for ep in episodes:
            s = torch.as_tensor(ep.proprio, dtype=torch.float64)
            a = torch.as_tensor(ep.actions, dtype=torch.float64).clamp(-1, 1)
            dp, dr, dg = observed_carry(s[:-1], s[1:])  # world-frame deltas per step
            # regress delta_t on (commanded delta_t, delta_{t-1}) for t >= 1
            xp.append(torch.stack([OSC_POS_SCALE * a[1:, :3], dp[:-1]], -1).reshape(-1, 2))
            yp.append(dp[1:].reshape(-1))
            xr.append(torch.stack([OSC_ROT_SCALE * a[1:, 3:6], dr[:-1]], -1).reshape(-1, 2))
            yr.append(dr[1:].reshape(-1))
            target = torch.where(a[1:, 6] > 0, closed, opened)
            xg.append(torch.stack([target - s[1:-1, 6], dg[:-1]], -1))
            yg.append(dg[1:])
        (g_pos, m_pos), (g_rot, m_rot) = (_lstsq(torch.cat(x), torch.cat(y)) for x, y in ((xp, yp), (xr, yr)))
        lag, momentum = _lstsq(torch.cat(xg).reshape(-1, 2), torch.cat(yg).reshape(-1))
        return cls(g_pos=g_pos, g_rot=g_rot, m_pos=m_pos, m_rot=m_rot, grip_lag=lag, grip_momentum=momentum,
                   grip_closed=closed, grip_open=opened)


def observed_carry(prev_state: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The (position, rotation, gripper) deltas between two observed states: the carry that starts
    a rollout mid-episode with the arm's current motion."""
    dp = state[:, :3] - prev_state[:, :3]
    dr = matrix_to_axis_angle(axis_angle_to_matrix(state[:, 3:6]) @ axis_angle_to_matrix(prev_state[:, 3:6]).transpose(1, 2))
    return dp, dr, state[:, 6] - prev_state[:, 6]


def _lstsq(x: torch.Tensor, y: torch.Tensor) -> tuple[float, float]:
    sol = torch.linalg.lstsq(x, y[:, None]).solution[:, 0]
    return float(sol[0]), float(sol[1])


def state_errors(model: NextStateModel, episodes, horizon: int) -> dict:
    """Position (mm), rotation (deg) and gripper errors of open-loop prediction `horizon` steps
    ahead from every start step, against the simulator's recorded states."""
    pos, rot, grip = [], [], []
    for ep in episodes:
        s = torch.as_tensor(ep.proprio, dtype=torch.float64)
        a = torch.as_tensor(ep.actions, dtype=torch.float64)
        # start at every step t >= 1 (so the arm's motion from t-1 seeds the momentum terms)
        n = len(a) - horizon
        if n < 1:
            continue
        starts = s[1:n + 1]
        carry = observed_carry(s[:n], starts)
        windows = torch.stack([a[i:i + horizon] for i in range(1, n + 1)])
        pred, _ = model.rollout(starts, windows, carry)
        true = s[1 + horizon:1 + horizon + n]
        last = pred[:, -1]
        pos.append((last[:, :3] - true[:, :3]).norm(dim=1) * 1000)
        r_err = axis_angle_to_matrix(last[:, 3:6]) @ axis_angle_to_matrix(true[:, 3:6]).transpose(1, 2)
        rot.append(torch.rad2deg(matrix_to_axis_angle(r_err).norm(dim=1)))
        grip.append((last[:, 6] - true[:, 6]).abs())
    cat = lambda xs: torch.cat(xs).numpy()  # noqa: E731
    p, r, g = cat(pos), cat(rot), cat(grip)
    return {"horizon": horizon, "pos_mm_median": float(np.median(p)), "pos_mm_p90": float(np.percentile(p, 90)),
            "rot_deg_median": float(np.median(r)), "rot_deg_p90": float(np.percentile(r, 90)),
            "grip_mae": float(g.mean()), "samples": int(len(p))}
