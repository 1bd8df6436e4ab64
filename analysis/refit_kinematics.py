"""A world model with its kinematic next-state model fitted anew, the learned weights unchanged.

The kinematic model (`worldenv_core.kinematics.next_state`) is fitted, not learned: it gives the
imagined proprioception the policy acts on and the states the action maps are drawn from. A model
trained before the kinematic model changed (the lagging gripper) keeps the old one in its
checkpoint, and `init_from=` carries it on; this refits it on the episodes given, the checkpoint's
held-out ones left out, writes a copy of the checkpoint with the new fit beside the old one's
open-loop state errors on the held-out episodes, and prints both.

    python -m analysis.refit_kinematics checkpoints/libero_goal/worldsim_open_loop \\
        'data/libero_goal/expert-73fe2c9a/task*/*.mcap' --out outputs/worldsim_open_loop_refit
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from worldenv_core.kinematics.next_state import NextStateModel, state_errors
from worldenv_core.models.checkpoint import CONFIG, WEIGHTS, read_config

HORIZONS = (8, 40, 100)


def refit(model_dir: str | Path, paths: list[Path], out: str | Path) -> dict:
    """Write `out`: `model_dir`'s weights, its kinematics refitted on `paths` less its held-out
    episodes. Returns {"kinematics": new fit, "errors": {"before"|"after": [state errors by horizon]}}."""
    from worldenv_core.data.mcap_io import read_episode
    from worldenv_core.data.selection import episode_key

    config = read_config(model_dir)
    meta = config["meta"]
    held_keys = set(meta.get("held_out", []))
    train = [p for p in paths if episode_key(p) not in held_keys]
    held = [p for p in paths if episode_key(p) in held_keys]
    if not train:
        raise ValueError(f"none of the {len(paths)} episodes is left to fit on: all are {model_dir}'s held-out ones")
    read = lambda ps: [read_episode(p, cameras=[], load_sim_state=False) for p in ps]  # noqa: E731 - proprio, actions
    fitted = NextStateModel.fit(read(train))
    held_eps = read(held)
    old = NextStateModel(**meta["kinematics"])
    errors = {name: [state_errors(m, held_eps, h) for h in HORIZONS] for name, m in (("before", old), ("after", fitted))
              } if held_eps else {}
    meta = {**meta, "kinematics": fitted.to_dict(),
            "kinematics_refit": {"from": str(model_dir), "episodes": len(train), "held_out_errors": errors}}
    out = Path(out)
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    shutil.copy2(Path(model_dir) / WEIGHTS, tmp / WEIGHTS)
    (tmp / CONFIG).write_text(json.dumps({**config, "meta": meta}, indent=2))
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return {"kinematics": fitted.to_dict(), "errors": errors}


def main(argv: list[str] | None = None) -> dict:
    from worldenv_core.data.selection import expand_episode_paths

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="the world model checkpoint folder")
    p.add_argument("episodes", nargs="+", help="episode files or glob patterns (its held-out ones score the fit)")
    p.add_argument("--out", required=True, help="the checkpoint folder to write")
    args = p.parse_args(argv)
    paths = expand_episode_paths(args.episodes)
    out = refit(args.model, paths, args.out)
    print(f"{args.out}: kinematics refitted: {out['kinematics']}")
    for name, rows in out["errors"].items():
        print(f"  {name}: " + "; ".join(f"{r['horizon']} steps: position {r['pos_mm_median']:.1f} mm (median), "
                                        f"gripper MAE {r['grip_mae']:.3f}" for r in rows))
    return out


if __name__ == "__main__":
    main()
