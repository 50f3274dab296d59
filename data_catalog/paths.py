"""The one gate for every path a description file names (a cell's CELL.yaml, a sample's
manifest.json, a drawing): the path is resolved inside the description's folder or refused.

Refused, each in one line naming the description, the field, the path as written and why:
an absolute path, one starting with ``~`` or holding a backslash, one that climbs (a ``..``
part), one reached through a symbolic link (a link may lead anywhere, and a sample must hold its
own bytes), and anything at the end that is not what was expected: a named pipe (FIFO), a device,
a socket, a folder where a file was expected (or a file where a folder was). Nothing outside the
folder is opened, and no message holds anything read from outside it (a link's target is not
followed, let alone named)."""

from __future__ import annotations

import os
import stat
from pathlib import Path, PurePosixPath

__all__ = ["PathRefused", "path_inside", "not_a_file_reason"]


class PathRefused(ValueError):
    """A path a description names that the gate refuses (one line)."""


_KINDS = ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a folder"), (stat.S_ISLNK, "a symbolic link"),
          (stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _kind(mode: int) -> str:
    """What a file of ``mode`` (``os.lstat``'s) is, in words."""
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def not_a_file_reason(path: str | Path) -> str | None:
    """Why ``path`` (given directly, e.g. on the command line) cannot be read as a file: "no such
    file", "a folder", "a named pipe (FIFO)", "a character device", ... (links followed); None when
    it is a regular file."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "no such file"
    except NotADirectoryError:
        return "no such file (a part of its path is a file, not a folder)"
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    return None if stat.S_ISREG(mode) else _kind(mode)


def path_inside(root: str | Path, name: str, *, where: str, what: str, folder: bool = False,
                error: type[Exception] = PathRefused) -> Path:
    """``root / name``, checked: ``name`` (as a description file writes it, POSIX, relative to
    ``root``) stays inside ``root`` through no symbolic link and ends on a regular file (``folder``:
    a folder). ``where``: the description and field, for the message (``"CELL.yaml: setups.0.passes.1.poses"``);
    ``what``: what the path should hold (``"the pose log of pass top-1"``). ``error`` (one line)
    otherwise; nothing is opened."""
    root = Path(root)
    text = str(name)
    pure = PurePosixPath(text)
    if not text or not pure.parts:
        raise error(f"{where}: an empty path; expected {what}, a path inside {root}")
    if "\\" in text or pure.is_absolute() or text.startswith("~"):
        raise error(f"{where}: {text!r} is not a relative POSIX path; expected {what} as a path inside {root}")
    if any(part == ".." for part in pure.parts):
        raise error(f"{where}: {text!r} climbs out of its folder ('..'); expected {what} as a path inside {root}")
    parts = [p for p in pure.parts if p != "."]
    here = root
    for k, part in enumerate(parts):
        here = here / part
        last = k == len(parts) - 1
        try:
            mode = os.lstat(here).st_mode
        except FileNotFoundError:
            raise error(f"{where}: {text!r}: no such {'folder' if folder and last else 'file'} in {root}; "
                        f"expected {what}") from None
        except NotADirectoryError:
            raise error(f"{where}: {text!r}: no such file in {root} (a part of the path is a file); "
                        f"expected {what}") from None
        except OSError as exc:
            raise error(f"{where}: {text!r} cannot be read ({exc.strerror or exc}); expected {what}") from None
        if stat.S_ISLNK(mode):
            raise error(f"{where}: {text!r}: {here.relative_to(root)} is a symbolic link; expected {what} held in "
                        f"{root} itself (a link may lead anywhere; it is not followed)")
        if not last and not stat.S_ISDIR(mode):
            raise error(f"{where}: {text!r}: {here.relative_to(root)} is {_kind(mode)}, not a folder; expected {what}")
        if last:
            ok = stat.S_ISDIR(mode) if folder else stat.S_ISREG(mode)
            if not ok:
                raise error(f"{where}: {text!r} is {_kind(mode)}; expected {what} as "
                            f"{'a folder' if folder else 'a regular file'}")
    real_root, real = root.resolve(), here.resolve()
    if real != real_root and real_root not in real.parents:  # no link and no '..': cannot happen; said if it does
        raise error(f"{where}: {text!r} resolves outside {root}; expected {what} as a path inside it")
    return here
