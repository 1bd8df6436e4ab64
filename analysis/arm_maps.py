"""How well the arm's drawn skeleton stands for the real robot, on a suite's recorded episodes.

    python -m analysis.arm_maps data/libero_spatial/expert-86a021fb [--episodes 10] [--every 20] \
        [--out results/rl_recipes/arm_maps_libero_spatial.json] [--figure docs/img/arm_maps_libero_spatial.jpg]

Two figures of merit for `worldsim.arm_map` (docs/world_simulator.md):
* tracking: each episode's joints followed from its first frame by `arm.track` onto its recorded
  end-effector states alone (what imagination does), the skeleton's distance to the recorded joints'
  skeleton (mm; median, 90th percentile, max over all steps);
* coverage: at every `--every`-th frame, the drawn links against the simulator's segmentation of the robot
  (recall: the robot's pixels the drawing covers; precision: the drawn pixels on the robot).
The figure shows frames, their gripper-only maps, the maps with the arm, and the drawing over the frame.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from worldenv_core.cli import user_errors
from worldenv_core.data.mcap_io import list_episode_files, read_episode
from worldenv_core.errors import ConfigError


def robot_pixels(env, size: int) -> np.ndarray:
    """(size, size) bool: where the camera sees a robot or gripper geom (upright image)."""
    names = np.array([env.sim.model.geom_id2name(g) or "" for g in range(env.sim.model.ngeom)] + [""])
    robot = np.char.startswith(names, "robot0_") | np.char.startswith(names, "gripper0_")
    seg = env.sim.render(width=size, height=size, camera_name="agentview", segmentation=True)[::-1]
    return robot[np.where(seg[..., 1] >= 0, seg[..., 1], -1)]


def measure(paths: list[Path], every: int) -> tuple[dict, list[np.ndarray]]:
    from worldenv_core.envs.libero_env import LiberoEnv
    from worldenv_core.kinematics import PinholeCamera, draw_action_maps
    from worldenv_core.kinematics.arm import SerialArm, track

    errors, coverage, rows = [], [], []
    for path in paths:
        ep = read_episode(path, cameras=["agentview"])
        size = ep.images["agentview"].shape[1]  # scored at the recorded frames' resolution
        joints, proprio = torch.from_numpy(ep.joint_pos), torch.from_numpy(ep.proprio).double()
        with LiberoEnv(ep.meta.suite, ep.meta.task_id, cameras=(), render=False) as env:
            arm = SerialArm.from_env(env, env.reset(init_state=0))
            tracked = track(arm, joints[:1], proprio[None, 1:])[0]
            errors.append(((arm.points(tracked) - arm.points(joints[1:])).norm(dim=-1) * 1000).flatten())
            for t in range(0, ep.num_frames, every):
                env.set_sim_state(ep.sim_state[t])
                cam = PinholeCamera.from_sim(env.sim, "agentview", size)
                robot = robot_pixels(env, size)
                state = proprio[t:t + 1]
                plain = draw_action_maps(state, cam, size)[0]
                drawn_map = draw_action_maps(state, cam, size, arm_points=arm.points(joints[t:t + 1]).float())[0]
                drawn = (drawn_map.max(0).values > 0.1).numpy()
                both = (drawn & robot).sum()
                coverage.append((both / max(robot.sum(), 1), both / max(drawn.sum(), 1)))
                if len(rows) < 4 and t > 0:
                    image = ep.images["agentview"][t]
                    over = image.copy()
                    over[drawn] = (0.5 * over[drawn] + 0.5 * np.array([255, 0, 255])).astype(np.uint8)
                    rows.append(np.concatenate([image, *((m.permute(1, 2, 0).numpy() * 255).astype(np.uint8)
                                                         for m in (plain, drawn_map)), over], axis=1))
    err = torch.cat(errors)
    cov = np.asarray(coverage)
    return {"episodes": [str(p) for p in paths], "frames_scored": len(cov), "steps_tracked": len(err),
            "tracking_mm": {"median": float(err.median()), "p90": float(err.quantile(0.9)), "max": float(err.max())},
            "coverage": {"recall_mean": float(cov[:, 0].mean()), "recall_min": float(cov[:, 0].min()),
                         "precision_mean": float(cov[:, 1].mean()), "precision_min": float(cov[:, 1].min())}}, rows


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="a collection folder (MCAP episodes with sim states)")
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--every", type=int, default=20, help="score every n-th frame against the segmentation")
    ap.add_argument("--out", help="write the figures as JSON here")
    ap.add_argument("--figure", help="write the montage (JPEG) here")
    args = ap.parse_args(argv)
    with user_errors():
        paths = list_episode_files(args.data)
        paths = paths[:: max(1, len(paths) // max(args.episodes, 1))][: args.episodes]  # spread over the tasks
        if not paths:
            raise ConfigError(f"no episodes under {args.data}")
        if args.every < 1:
            raise ConfigError(f"--every must be >= 1, got {args.every}")
    result, rows = measure(paths, args.every)
    print(json.dumps({k: v for k, v in result.items() if k != "episodes"}, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    if args.figure and rows:
        from PIL import Image

        Image.fromarray(np.concatenate(rows, axis=0)).save(args.figure, quality=90)
    return result


if __name__ == "__main__":
    main()
