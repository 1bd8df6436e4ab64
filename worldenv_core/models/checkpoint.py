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

FORMAT = 1
WEIGHTS, CONFIG = "model.safetensors", "config.json"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class CheckpointError(ValueError):
    """A checkpoint that is missing, incomplete, or made for another task contract."""


def save_model(path: str | Path, model: torch.nn.Module, model_config: dict, meta: dict | None = None) -> Path:
    return save_state(path, model.state_dict(), model_config, meta)


def save_state(path: str | Path, state: dict[str, torch.Tensor], model_config: dict, meta: dict | None = None) -> Path:
    """A checkpoint folder from a state dict (`save_model` without the module: weights edited as tensors)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    state = {k: v.detach().contiguous().cpu() for k, v in state.items()}
    save_file(state, str(tmp / WEIGHTS))
    os.chmod(tmp / WEIGHTS, 0o666 & ~_umask())  # safetensors writes 0600; checkpoints are shared like any output
    (tmp / CONFIG).write_text(json.dumps({"format": FORMAT, "model": model_config, "meta": meta or {}}, indent=2))
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
    model = instantiate(cfg["model"], _convert_="all")
    missing, unexpected = model.load_state_dict(load_weights(path / WEIGHTS, map_location), strict=False)
    if missing or unexpected:
        raise CheckpointError(f"{path}: weights do not fit the model (missing {missing[:5]}, unexpected {unexpected[:5]})")
    return model, cfg


def load_checkpoint(path: str | Path, kind: str, contract: TaskContract | None = None,
                    device: str = "cpu") -> tuple[torch.nn.Module, dict]:
    """A policy, world model or reflector from its folder alone, in eval mode on `device`: the
    folder must hold that `kind`, made for `contract`'s shapes (`TaskContract.check`). -> (model, meta)"""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    meta = read_config(path)["meta"]
    if meta.get("kind") != kind:
        raise CheckpointError(f"{path} holds a {meta.get('kind')!r} checkpoint, not a {kind}")
    if contract is not None:
        contract.check(meta, f"checkpoint {path}")
    model, cfg = load_model(path)
    return model.to(device).eval(), cfg["meta"]
