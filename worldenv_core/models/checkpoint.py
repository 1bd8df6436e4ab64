"""Self-describing checkpoints (robomimic/lerobot style): a folder with

  model.safetensors   the weights (normalisation stats included, as buffers)
  config.json         {"model": <_target_ config that rebuilds the module>, "meta": {...}, "format": 1}

`load_model(path)` needs that folder alone: no Hydra run, no dataset, no network. Folders are
written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import torch
from hydra.utils import instantiate
from safetensors.torch import load_file, save_file

from worldenv_core.contract import TaskContract
from worldenv_core.files import current_umask, writing

FORMAT = 1
WEIGHTS, CONFIG = "model.safetensors", "config.json"


class CheckpointError(ValueError):
    """A checkpoint that is missing, incomplete, or made for another task contract."""


def save_model(path: str | Path, model: torch.nn.Module, model_config: dict, meta: dict | None = None,
               native: bool = False) -> Path:
    """`native`: a LeRobot policy (`save_lerobot`) also in LeRobot's own layout inside the folder
    (`lerobot/`), for its loaders (a released or final policy; not every resumable checkpoint)."""
    also = model.save_lerobot if native and hasattr(model, "save_lerobot") else None
    return save_state(path, model.state_dict(), model_config, meta,
                      also=None if also is None else (lambda tmp: also(tmp / "lerobot")))


def save_state(path: str | Path, state: dict[str, torch.Tensor], model_config: dict, meta: dict | None = None,
               also=None) -> Path:
    """A checkpoint folder from a state dict (`save_model` without the module: weights edited as tensors).
    `also(folder)` writes more files into it before it is renamed into place."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    with writing(path, tmp):  # a full disk: one line naming the folder, and no half-written tmp left
        tmp.mkdir(parents=True)
        state = {k: v.detach().contiguous().cpu() for k, v in state.items()}
        save_file(state, str(tmp / WEIGHTS))
        os.chmod(tmp / WEIGHTS, 0o666 & ~current_umask())  # safetensors writes 0600; checkpoints are shared like any output
        (tmp / CONFIG).write_text(json.dumps({"format": FORMAT, "model": model_config, "meta": meta or {}}, indent=2))
        if also is not None:
            also(tmp)
        if path.exists():
            shutil.rmtree(path)
        tmp.rename(path)
    return path


def load_weights(file: str | Path, map_location: str = "cpu") -> dict[str, torch.Tensor]:
    """A safetensors file, verified: its header and every tensor readable, every float finite.
    A truncated or overwritten file is an error naming it, never weights with NaN in them."""
    file = Path(file)
    try:
        state = load_file(str(file), device=map_location)
    except Exception as e:  # noqa: BLE001 - safetensors raises its own error types for bad bytes
        raise CheckpointError(f"{file} is not a readable safetensors file ({type(e).__name__}: {e}); the checkpoint "
                              "is damaged: re-run the stage that wrote it, or give another checkpoint") from None
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(f"{file} holds non-finite values (NaN or inf) in {len(bad)} tensor(s), e.g. {bad[:3]}: "
                              "the file is damaged or the training diverged; re-run the stage that wrote it")
    return state


def verify_checkpoint(path: str | Path) -> Path:
    """A checkpoint folder given by hand (not found through the manifest): its config readable and
    its weights verified (`load_weights`). Returns the folder."""
    path = Path(path)
    read_config(path)
    load_weights(path / WEIGHTS)
    return path


def read_config(path: str | Path) -> dict:
    path = Path(path)
    if path.is_file() and path.name in (WEIGHTS, CONFIG):
        path = path.parent
    if not (path / CONFIG).exists() or not (path / WEIGHTS).exists():
        raise CheckpointError(f"{path} is not a checkpoint folder (needs {CONFIG} and {WEIGHTS})")
    try:
        cfg = json.loads((path / CONFIG).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path / CONFIG} is not readable JSON ({e}): the checkpoint is damaged; re-run the "
                              "stage that wrote it") from None
    if cfg.get("format") != FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {cfg.get('format')!r}, this code reads {FORMAT}")
    return cfg


KINDS = ("policy", "worldsim", "reflector")


def load_model(path: str | Path, map_location: str = "cpu") -> tuple[torch.nn.Module, dict]:
    """Rebuild the module from its config and load its weights (no kind or contract check: use
    `load_checkpoint` for the pipeline's models)."""
    path = Path(path)
    if path.is_file():
        path = path.parent
    cfg = read_config(path)
    check_model_config(cfg, path)
    model = instantiate(cfg["model"], _convert_="all")
    weights = load_weights(path / WEIGHTS, map_location)
    own = model.state_dict()
    reshaped = [k for k, v in weights.items() if k in own and tuple(own[k].shape) != tuple(v.shape)]
    if reshaped:
        k = reshaped[0]
        raise CheckpointError(f"{path}: the weights do not fit the model its {CONFIG} builds: {len(reshaped)} tensor(s) "
                              f"of another shape, e.g. {k} {tuple(weights[k].shape)} in {WEIGHTS} against "
                              f"{tuple(own[k].shape)} in the model (another width?); the folder's files do not "
                              "belong together: re-run the stage that wrote it")
    missing, unexpected = model.load_state_dict(weights, strict=False)
    if missing or unexpected:
        raise CheckpointError(f"{path}: weights do not fit the model (missing {missing[:5]}, unexpected {unexpected[:5]})")
    return model, cfg


# What a model's config and its checkpoint's meta both say, and must say alike: the meta is what the
# contract check reads, the config is what runs, so a disagreement would run one thing checked as another.
AGREEING_KEYS = ("cameras", "camera", "image_size", "chunk", "action_dim", "proprio_dim")


def check_model_config(cfg: dict, where) -> None:
    """Every `AGREEING_KEYS` value found anywhere in the model config (its backbone included)
    equals the meta's, where the meta records it."""
    meta = cfg.get("meta", {})

    def walk(node, trail):
        if isinstance(node, dict):
            for k, v in node.items():
                if k in AGREEING_KEYS and k in meta and v != meta[k]:
                    raise CheckpointError(f"{where}: its model config has {'.'.join([*trail, k])}={v!r} but its meta "
                                          f"{k}={meta[k]!r}: the checkpoint contradicts itself (edited by hand?); "
                                          "re-run the stage that wrote it")
                walk(v, [*trail, k])

    walk(cfg.get("model", {}), ["model"])


def load_checkpoint(path: str | Path, kind: str, contract: TaskContract | None = None,
                    device: str = "cpu") -> tuple[torch.nn.Module, dict]:
    """A policy, world model or reflector from its folder alone, in eval mode on `device`: the
    folder must hold that `kind`, made for `contract`'s shapes (`TaskContract.check`). -> (model, meta)"""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    cfg = read_config(path)
    check_model_config(cfg, path)  # a folder that contradicts itself is named as such before any other check
    meta = cfg["meta"]
    if meta.get("kind") != kind:
        raise CheckpointError(f"{path} holds a {meta.get('kind')!r} checkpoint, not a {kind}")
    if contract is not None:
        contract.check(meta, f"checkpoint {path}")
    model, cfg = load_model(path)
    return model.to(device).eval(), cfg["meta"]
