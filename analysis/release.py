"""Release a checkpoint folder into the repository (`checkpoints/<suite>/<name>`), or export it for LeRobot.

Why: a run that spans sessions must start from weights that outlive the machine. A policy that costs hours to
retrain on a CPU (LeRobot's ACT: 15.8 M parameters, 1.5-3 hours) and whose training is not bit-for-bit repeatable
across machines and thread counts would otherwise start a new campaign on every fresh machine. `--half` stores the
floating weights in float16 (half the bytes; whatever loads the folder gets float32 back, as trained models are
loaded everywhere here), after checking that no weight overflows float16 and reporting the largest rounding
error. The released weights are a new starting point: evaluate them before pairing anything with them.

    python -m analysis.release outputs/libero_spatial-small/train_policy/<work>/policy checkpoints/libero_spatial/act_sft --half
    python -m analysis.release checkpoints/libero_spatial/act_sft <folder> --lerobot   # + LeRobot's own layout
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from worldenv_core.cli import user_errors
from worldenv_core.errors import ConfigError
from worldenv_core.models.checkpoint import WEIGHTS, load_model, load_weights, read_config, save_state

HALF_MAX = float(torch.finfo(torch.float16).max)


def halve(state: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], float]:
    """Floating tensors as float16 (others as they are) -> (state, largest relative rounding error of a weight
    whose magnitude is above float16's normal range's floor). Raises ConfigError on a value float16 cannot hold."""
    out, worst = {}, 0.0
    tiny = float(torch.finfo(torch.float16).tiny)
    for key, value in state.items():
        if not value.is_floating_point():
            out[key] = value
            continue
        big = value.abs().max().item() if value.numel() else 0.0
        if big > HALF_MAX:
            raise ConfigError(f"{key} holds {big:.3g}, beyond float16's {HALF_MAX:.0f}: release it without --half")
        half = value.to(torch.float16)
        normal = value.abs() > tiny
        if normal.any():
            rel = ((half.float() - value.float()).abs()[normal] / value.float().abs()[normal]).max().item()
            worst = max(worst, rel)
        out[key] = half
    return out, worst


def release(src: str | Path, dst: str | Path, half: bool = False, lerobot: bool = False) -> dict:
    """Copy the checkpoint folder `src` to `dst` (written under a temporary name, renamed when complete).
    Its config and meta are kept, with `released_from` (the source folder's name) and `stored_dtype` added."""
    src, dst = Path(src), Path(dst)
    cfg = read_config(src)
    state = load_weights(src / WEIGHTS)
    worst = 0.0
    if half:
        state, worst = halve(state)
    meta = {**cfg.get("meta", {}), "released_from": src.name, "stored_dtype": "float16" if half else "as trained"}
    also = None
    if lerobot:
        model, _ = load_model(src)
        if not hasattr(model, "save_lerobot"):
            raise ConfigError(f"{src} holds {type(model).__name__}, which has no LeRobot layout (--lerobot is for "
                              "LeRobot policies, e.g. policy=lerobot_act)")
        if half:  # LeRobot's copy from the same rounded weights as the folder's own
            model.load_state_dict(state)

        def also(tmp: Path) -> None:
            model.save_lerobot(tmp / "lerobot")
    save_state(dst, state, cfg["model"], meta, also=also)
    load_model(dst)  # the released folder loads into its model, or this fails before anyone relies on it
    size = sum(f.stat().st_size for f in dst.rglob("*") if f.is_file())
    return {"folder": str(dst), "megabytes": round(size / 1e6, 1), "stored_dtype": meta["stored_dtype"],
            "largest_relative_rounding": worst, "lerobot": lerobot}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("src", help="a checkpoint folder (model.safetensors + config.json)")
    parser.add_argument("dst", help="where the released folder goes (e.g. checkpoints/<suite>/<name>)")
    parser.add_argument("--half", action="store_true", help="store floating weights as float16")
    parser.add_argument("--lerobot", action="store_true", help="also write LeRobot's own layout (lerobot/)")
    args = parser.parse_args()
    with user_errors():
        print(json.dumps(release(args.src, args.dst, half=args.half, lerobot=args.lerobot), indent=2))


if __name__ == "__main__":
    main()
