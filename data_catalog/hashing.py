"""Content hashes of files and directory trees (zarr stores are directories)."""

from __future__ import annotations

import hashlib
from pathlib import Path

__all__ = ["sha256_file", "sha256_tree"]

_BLOCK = 1 << 20


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(_BLOCK):
            digest.update(block)
    return digest.hexdigest()


def sha256_tree(path: Path) -> str:
    """Hash of a file, or of a directory: its files' relative POSIX paths and contents, sorted.

    Symlinks are refused: a store must hold its own bytes.
    """
    path = Path(path)
    if path.is_symlink():
        raise ValueError(f"{path} is a symbolic link; refusing to hash through it")
    if path.is_file():
        return sha256_file(path)
    if not path.is_dir():
        raise FileNotFoundError(f"{path} does not exist")
    digest = hashlib.sha256()
    for item in sorted(p for p in path.rglob("*")):
        if item.is_symlink():
            raise ValueError(f"{item} is a symbolic link; refusing to hash through it")
        if item.is_dir():
            continue
        rel = item.relative_to(path).as_posix()
        digest.update(rel.encode("utf-8") + b"\0")
        digest.update(sha256_file(item).encode("ascii") + b"\n")
    return digest.hexdigest()
