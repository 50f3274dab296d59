"""Text files a person writes or edits (manifests, settings), read with every failure named in
one line: the file, what is wrong with it and what was expected."""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from data_catalog.paths import not_a_file_reason

__all__ = ["read_text_file", "read_yaml_mapping", "read_yaml_model"]

M = TypeVar("M", bound=BaseModel)


def read_text_file(path: str | Path, expected: str, error: type[Exception] = ValueError,
                   missing: str | None = None) -> str:
    """The UTF-8 text of ``path``; ``error`` naming the file and ``expected`` (what it should be)
    when it is missing (``missing``: the words for that), a folder, not UTF-8 or unreadable."""
    reason = not_a_file_reason(path)
    if reason not in (None, "no such file", "a folder"):  # a FIFO or a device would block or never end
        raise error(f"{path}: {reason}, expected {expected} as a regular file")
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: {missing or f'no such file, expected {expected}'}") from None
    except IsADirectoryError:
        raise error(f"{path}: is a folder, expected {expected}") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text at byte {exc.start}, expected {expected}") from None
    except OSError as exc:
        raise error(f"{path}: cannot be read ({exc.strerror or exc})") from None


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (a second ``merge:``
    section would silently replace the first)."""

    def construct_mapping(self, node, deep=False):  # noqa: ANN001, ANN201 - PyYAML's signature
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"{key!r} given twice in one mapping",
                                                        key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml_mapping(path: str | Path, what: str) -> dict[str, Any]:
    """The mapping of fields in the YAML file ``path`` (empty file: no fields), read safely (no
    tags that build objects). ValueError in one line naming the file, ``what`` it should hold and,
    for bad YAML, the line and column."""
    text = read_text_file(path, f"a {what} file (YAML)")
    try:
        raw = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ValueError(f"{path}: the {what} is not valid YAML ({where}{problem})") from None
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: the {what} must be a mapping of fields (section: field: value), "
                         f"not a {type(raw).__name__}")
    return raw


def read_yaml_model(path: str | Path, model: type[M], what: str) -> M:
    """``model`` validated from the YAML file ``path`` (``read_yaml_mapping``). ValueError naming
    the file and ``what`` it should hold, then one indented line per wrong field (its dotted path
    and what is wrong)."""
    raw = read_yaml_mapping(path, what)
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        lines = "\n".join(f"  {'.'.join(str(p) for p in e['loc']) or '(top level)'}: {e['msg']}" for e in exc.errors())
        raise ValueError(f"{path}: invalid {what}:\n{lines}") from None
