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
           "sweep_leftovers", "replace_directory", "folder_lock", "fsync_tree", "check_can_create"]


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


def fsync_tree(folder: Path) -> None:
    """Flush every file in ``folder`` (one level) and the folder itself to the disk."""
    folder = Path(folder)
    for child in folder.iterdir():
        if child.is_file():
            fd = os.open(child, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the
    system or the filesystem cannot."""
    import ctypes
    import errno

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(code, f"cannot swap {a} and {b}: {os.strerror(code)}")


def replace_directory(new: Path, target: Path) -> None:
    """Put the complete folder ``new`` at ``target`` in one step, replacing the folder there:
    readers see the old folder whole or the new one whole, never a mix (a kill between any two
    instructions included). The old folder is removed afterwards. Where the filesystem cannot
    swap two folders at once, the old one is first renamed aside (a tagged ``.partial`` name, swept
    by the next run if this process dies before it is removed): ``target`` is then briefly absent,
    but never mixed."""
    new, target = Path(new), Path(target)
    if not target.exists():
        os.rename(new, target)
        return
    if _exchange(new, target):
        shutil.rmtree(new)  # now the old folder
        return
    aside = target.with_name(f".{target.name}.old.{owner_tag()}.partial")
    os.rename(target, aside)
    os.rename(new, target)
    shutil.rmtree(aside, ignore_errors=True)


@contextlib.contextmanager
def folder_lock(path: Path) -> Iterator[None]:
    """An exclusive lock (``flock``) on the file ``path`` (created if missing), held for the block:
    serialises what several processes do to one folder."""
    import fcntl

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+b") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def check_can_create(path: Path, what: str, *, hint: str = "give a folder you can write") -> None:
    """That ``path`` (a folder to be made or written into) can be: its nearest existing ancestor
    is a folder this process can create things in (tried, not only asked: root's ``access`` says
    yes on a read-only or virtual filesystem). ValueError naming ``what`` (``--out X``) and why,
    before any work is done; ``hint`` says what to do instead."""
    path = Path(path).absolute()
    existing = next((p for p in [path, *path.parents] if p.exists()), None)
    if existing is None:  # pragma: no cover - "/" always exists
        return
    if not existing.is_dir():
        raise ValueError(f"{what}: {existing} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=f".probe.{owner_tag()}.", suffix=".partial", dir=existing)
    except OSError as exc:
        raise ValueError(f"{what}: cannot create anything in {existing} ({exc.strerror or exc}); {hint}") from None
    os.close(fd)
    os.unlink(probe)
