"""What the packs for a GPU host share (a context pack, a latent pack): one safetensors file,
written to a temporary name and renamed when complete, whose metadata names its format, checked
on reading before any tensor is read, with one line saying how to make the pack if it is missing."""

from __future__ import annotations

import uuid
from contextlib import contextmanager
from pathlib import Path

from safetensors import safe_open
from safetensors.torch import save_file

from worldenv_core.errors import ConfigError
from worldenv_core.files import writing


def write_pack(path: str | Path, tensors: dict, metadata: dict[str, str]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    with writing(path, tmp):
        save_file(tensors, str(tmp), metadata=metadata)
        tmp.replace(path)
    return path


@contextmanager
def open_pack(path: str | Path, fmt: str, what: str, make: str, wrong=ConfigError):
    """-> (the open file, its metadata). `what`: "a context pack"; `make`: the command that writes one;
    `wrong`: the error class for a file of another format."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"no {what.split(' ', 1)[1]} at {path}: write one with `{make}` where the episodes are")
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
        if meta.get("format") != fmt:
            raise wrong(f"{path} is not {what} (format {meta.get('format')!r}, expected {fmt!r})")
        yield f, meta
