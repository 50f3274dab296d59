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
            if key_node.tag == "tag:yaml.org,2002:merge":  # <<: *name: its keys may be overridden here
                continue
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"{key!r} given twice in one mapping",
                                                        key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


MAX_YAML_BYTES = 4 << 20  # a settings or description file: never megabytes
MAX_YAML_VALUES = 100_000  # scalars, sequences and mappings once every alias is expanded


def _expanded_size(node: yaml.Node, memo: dict[int, int]) -> int:
    """How many values ``node`` stands for with every alias expanded (an alias is the node it names,
    so shared nodes are counted each time they are used; ``memo`` keeps it linear in the text)."""
    key = id(node)
    if key in memo:
        return memo[key]
    memo[key] = 1  # a node reaching itself (a recursive alias) counts once
    if isinstance(node, yaml.MappingNode):
        size = 1 + sum(_expanded_size(k, memo) + _expanded_size(v, memo) for k, v in node.value)
    elif isinstance(node, yaml.SequenceNode):
        size = 1 + sum(_expanded_size(v, memo) for v in node.value)
    else:
        size = 1
    memo[key] = min(size, 1 << 62)
    return memo[key]


def read_yaml_mapping(path: str | Path, what: str) -> dict[str, Any]:
    """The mapping of fields in the YAML file ``path``, read safely (no tags that build objects).
    ValueError in one line naming the file, ``what`` it should hold and, for bad YAML, the line
    and column. A file with no document at all (empty, or comments only) is refused: a file named
    on purpose that sets nothing is a mistake (a truncated copy, the wrong file) that would
    otherwise run every default without a word; ``{}`` says "no fields" on purpose."""
    text = read_text_file(path, f"a {what} file (YAML)")
    if len(text) > MAX_YAML_BYTES:
        raise ValueError(f"{path}: {len(text):,} characters; expected a {what} file of at most {MAX_YAML_BYTES:,}")
    try:
        loader = _UniqueKeyLoader(text)
        try:
            node = loader.get_single_node()
            if node is not None:
                values = _expanded_size(node, {})
                if values > MAX_YAML_VALUES:
                    raise ValueError(f"{path}: the {what} expands to {values:,} values through its aliases (*name); "
                                     f"expected at most {MAX_YAML_VALUES:,} (nested aliases multiply)")
            raw = loader.construct_document(node) if node is not None else None
        finally:
            loader.dispose()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ValueError(f"{path}: the {what} is not valid YAML ({where}{problem})") from None
    if node is None:
        raise ValueError(f"{path}: the {what} file is empty (no fields, only blank lines or comments); expected "
                         f"its fields (section: field: value), or {{}} to set none on purpose")
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: the {what} must be a mapping of fields (section: field: value), "
                         f"not {'null' if raw is None else 'a ' + type(raw).__name__}")
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
