"""Settings files in YAML, read safely (no tags that build objects) and named in every error."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

__all__ = ["read_yaml_mapping"]


def read_yaml_mapping(path: str | Path, what: str) -> dict[str, Any]:
    """The mapping of fields in the YAML file ``path`` (empty file: no fields). ValueError in one
    line naming the file, ``what`` it should hold and, for bad YAML, the line and column."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except IsADirectoryError:
        raise ValueError(f"{path}: is a folder, not a {what} file") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: cannot read the {what} (not UTF-8 text: byte {exc.start})") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    try:
        raw = yaml.safe_load(text)
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
