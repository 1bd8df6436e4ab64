"""Writing files so that a reader (a resumed run, a report, a concurrent stage) never sees half of one."""

from __future__ import annotations

from pathlib import Path


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write to `<path>.tmp`, then rename over `path` (atomic on one file system)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    return tmp.replace(path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """`write_bytes_atomic` of `text`, UTF-8."""
    return write_bytes_atomic(path, text.encode())
