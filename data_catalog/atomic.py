"""Atomic writes: write beside the target, then rename, so nobody ever trusts a half file."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_directory", "default_mode", "owner_tag",
           "sweep_leftovers"]


def owner_tag() -> str:
    """``~<host>~<pid>~``: put in the names of temporary files and folders, so that what a dead
    process left behind can be told from what a live one is still writing (``sweep_leftovers``)."""
    return f"~{socket.gethostname()}~{os.getpid()}~"


_TAGGED = re.compile(r"~(?P<host>[^~/]+)~(?P<pid>\d+)~")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_leftovers(root: Path, *, depth: int = 3) -> list[Path]:
    """Remove the temporary files and folders (``.build-*``, ``.scratch-*``, ``*.partial``) under
    ``root`` (``depth`` levels down) that a process of this host left behind when it died; what a
    live process, or another host, is writing is left alone. Returns what was removed."""
    host = socket.gethostname()
    removed: list[Path] = []

    def walk(folder: Path, level: int) -> None:
        try:
            children = sorted(folder.iterdir())
        except OSError:
            return
        for child in children:
            match = _TAGGED.search(child.name) if child.name.startswith(".") else None
            if match and match["host"] == host and not _alive(int(match["pid"])):
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child, ignore_errors=True)
                else:
                    with contextlib.suppress(FileNotFoundError):
                        child.unlink()
                removed.append(child)
            elif level < depth and child.is_dir() and not child.is_symlink() and not child.name.startswith("."):
                walk(child, level + 1)

    walk(Path(root), 1)
    return removed


def _umask() -> int:
    """The process's umask, read without changing it (``os.umask`` would set it, for a moment,
    for every thread of the flow)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return _UMASK_AT_START


_UMASK_AT_START = os.umask(0o022)
os.umask(_UMASK_AT_START)  # imported before any thread writes: set back at once


def default_mode(path: Path) -> None:
    """Give ``path`` the permissions a plain ``open``/``mkdir`` would have (0666/0777 less the
    umask): temporary files and folders start private (0600/0700), and a result the lab group
    cannot read is no deliverable."""
    os.chmod(path, (0o777 if Path(path).is_dir() else 0o666) & ~_umask())


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{owner_tag()}.", suffix=".partial", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        default_mode(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


@contextlib.contextmanager
def atomic_directory(path: Path) -> Iterator[Path]:
    """Yield a fresh temporary directory beside ``path``; rename it to ``path`` on success.

    ``path`` must not exist (nothing is overwritten). On any error the temporary directory is
    removed and ``path`` stays absent.
    """
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} already exists; refusing to overwrite it")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.{owner_tag()}.", suffix=".partial", dir=path.parent))
    try:
        default_mode(tmp)
        yield tmp
        os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
