"""Writing files so that a reader (a resumed run, a report, a concurrent stage) never sees half of
one, and so that a full disk is one line naming the path and the free space, with nothing torn or
empty left behind."""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from worldenv_core.errors import ArtefactError

# What a failed write raises when the device is full: OSError's own errnos, or a library's
# RuntimeError (torch.save: "file write failed") while the file system has about nothing left.
OUT_OF_SPACE = (errno.ENOSPC, errno.EDQUOT)
NEARLY_FULL_BYTES = 1 << 20


class DiskFullError(ArtefactError):
    """A write ran out of space (or quota) on its device."""


def nearest_existing(path: str | os.PathLike) -> Path:
    """`path` itself if it exists, else its nearest existing ancestor: where a run that will create
    `path` can be asked about space and permissions before it creates anything."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def free_bytes(path: str | os.PathLike) -> int | None:
    """Free space on the file system holding `path` (its nearest existing ancestor)."""
    try:
        return shutil.disk_usage(nearest_existing(path)).free
    except OSError:
        return None


def human_bytes(n: int | None) -> str:
    if n is None:
        return "unknown"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"  # unreachable


def is_out_of_space(error: BaseException, path: str | os.PathLike) -> bool:
    """Whether `error`, raised by a write of `path`, is the device running full: its errno, or
    (libraries that raise their own types: torch.save, safetensors) its message or a device with
    about nothing left."""
    if isinstance(error, OSError) and error.errno in OUT_OF_SPACE:
        return True
    if not isinstance(error, Exception):
        return False
    free = free_bytes(path)
    return "No space left" in str(error) or (free is not None and free < NEARLY_FULL_BYTES)


def disk_full(path: str | os.PathLike) -> DiskFullError:
    return DiskFullError(f"no space left on the device writing {path} ({human_bytes(free_bytes(path))} free there): "
                         "free some space and run the same command again (finished work is kept)")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


@contextmanager
def writing(path: str | os.PathLike, *partial: str | os.PathLike):
    """Around a write of `path`: if it fails, the `partial` files or folders it was writing are
    removed (no empty `*.tmp` is left behind), and running out of space becomes `DiskFullError`,
    one line naming `path` and the free space."""
    try:
        yield
    except BaseException as e:  # an interrupt too: what it cut short is removed, not left half made
        for p in partial:
            _remove(Path(p))
        if isinstance(e, DiskFullError) or is_out_of_space(e, path):  # named by the outermost write: what was made
            raise disk_full(path) from None
        raise


def current_umask() -> int:
    """The process's umask (read by setting it and back: there is no getter)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_all(fd: int, data: bytes) -> None:
    """`os.write` until every byte is written: a write may be short (a nearly full device, a
    signal), and an unchecked short write is a torn record."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        if n <= 0:  # pragma: no cover - os.write raises rather than return 0 on a regular file
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        view = view[n:]


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write to a temporary file beside `path`, then rename over `path` (atomic on one file system); a failed write
    leaves `path` as it was and no temporary file."""
    path = Path(path)
    # a name of its own (`<name>.<random>.tmp`): two writers of one path never write into each other's file
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    tmp = Path(tmp)
    with writing(path, tmp):
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600: the file is shared like any output
        return tmp.replace(path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """`write_bytes_atomic` of `text`, UTF-8."""
    return write_bytes_atomic(path, text.encode())
