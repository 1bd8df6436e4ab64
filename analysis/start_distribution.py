"""Where a task's fresh placements start against where the benchmark's 50 init states start.

RL trains on fresh placements (`worldenv_core/envs/placements.py`) and is judged on the benchmark's init states, so
a difference between the two is a difference between training and test. This compares, per task, each free
object's position and heading (x / y / z and yaw: range, mean) and the arm's 7 joint angles (mean, standard deviation, and the gap of the
means in standard errors; the nominal start both are drawn around) over the benchmark's init states and `--fresh`
validation (or `--purpose train`) placements (their resets are real: ~3 s each).

    python -m analysis.start_distribution --suite libero_spatial --task 5 --fresh 40
"""

from __future__ import annotations

import argparse

import numpy as np

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.report import markdown_table


def mean_gap(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column: mean(b) - mean(a), and that gap in standard errors of the difference of the means."""
    gap = b.mean(0) - a.mean(0)
    se = np.sqrt(a.var(0, ddof=1) / len(a) + b.var(0, ddof=1) / len(b))
    return gap, np.divide(gap, se, out=np.zeros_like(gap), where=se > 0)


def yaw(quat: np.ndarray) -> np.ndarray:
    """MuJoCo quaternions (..., 4) as w, x, y, z -> the heading about the vertical axis (rad)."""
    w, x, y, z = np.moveaxis(quat, -1, 0)
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def compare(bench: np.ndarray, fresh: np.ndarray, objects: dict[str, int], arm: list[int]) -> list[list]:
    """Rows of the table: flat MuJoCo states ([time, qpos, qvel]) of the benchmark and of fresh placements;
    `objects`: a free joint's name -> its qpos address; `arm`: the arm joints' qpos addresses."""
    rows = []
    for name, a in objects.items():
        columns = [(axis, bench[:, 1 + a + k], fresh[:, 1 + a + k]) for axis, k in (("x", 0), ("y", 1), ("z", 2))]
        # the heading about the vertical (degrees), as an angle from the benchmark's circular mean, so that a
        # heading near +-180 does not read as two far-apart values
        yaw_b, yaw_f = (yaw(states[:, 1 + a + 3:1 + a + 7]) for states in (bench, fresh))
        centre = np.angle(np.exp(1j * yaw_b).mean())
        columns.append(("yaw (deg)", *(np.degrees(np.angle(np.exp(1j * (v - centre)))) for v in (yaw_b, yaw_f))))
        for axis, col_b, col_f in columns:
            gap, z = mean_gap(col_b[:, None], col_f[:, None])
            rows.append([f"{name} {axis}", f"[{col_b.min():.3f}, {col_b.max():.3f}]", f"[{col_f.min():.3f}, {col_f.max():.3f}]",
                         f"{gap[0]:+.4f}", f"{z[0]:+.1f}"])
    cols = [1 + a for a in arm]
    gap, z = mean_gap(bench[:, cols], fresh[:, cols])
    for i, c in enumerate(cols):
        rows.append([f"arm joint {i + 1}", f"{bench[:, c].mean():.3f} +- {bench[:, c].std(ddof=1):.3f}",
                     f"{fresh[:, c].mean():.3f} +- {fresh[:, c].std(ddof=1):.3f}", f"{gap[i]:+.4f}", f"{z[i]:+.1f}"])
    return rows


def measure(suite: str, task: int, n_fresh: int, purpose: str = "validation") -> str:
    from worldenv_core.envs.libero_env import LiberoEnv
    from worldenv_core.envs.placements import placement_seeds
    from worldenv_core.envs.tasks import init_states

    env = LiberoEnv(suite, task, render=False)
    model = env.sim.model
    objects = {}
    for j in range(model.njnt):
        name = model.joint_id2name(j)
        addr = model.get_joint_qpos_addr(name) if name else None
        if isinstance(addr, tuple) and addr[1] - addr[0] == 7:  # a free joint: an object placed by the sampler
            objects[name.removesuffix("_joint0")] = addr[0]
    arm = [model.get_joint_qpos_addr(f"robot0_joint{i}") for i in range(1, 8)]
    fresh = []
    for _, seed in placement_seeds(suite, [task], n_fresh, purpose):
        env.reset(seed=seed)
        fresh.append(env.sim.get_state().flatten())  # env.sim: a hard reset builds a new one
    nominal = env.raw.robots[0].init_qpos  # both sets' arms are drawn around it (the benchmark's noise)
    env.close()
    rows = compare(init_states(suite, task), np.array(fresh), objects, arm)
    for row in rows[-len(arm):]:
        row[0] += f" (nominal {nominal[int(row[0].split()[2]) - 1]:.3f})"
    return "\n".join(markdown_table(["", "benchmark (50 init states)", f"fresh {purpose} placements ({n_fresh})",
                                      "gap of the means", "gap / standard error"], rows))


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", default="libero_spatial")
    ap.add_argument("--task", type=int, required=True)
    ap.add_argument("--fresh", type=int, default=40, help="fresh placements to reset (~3 s each)")
    ap.add_argument("--purpose", choices=["validation", "train"], default="validation",
                    help="which fresh placements: the validation set's or those RL trains on")
    args = ap.parse_args(argv)
    with user_errors():
        if args.fresh < 2:
            raise ConfigError(f"--fresh must be at least 2 (a standard deviation), got {args.fresh}")
        out = measure(args.suite, args.task, args.fresh, args.purpose)
        print(out)
        return out


if __name__ == "__main__":
    main()
