"""Reading and writing sample manifests (JSON), with errors that name the file and field."""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import ValidationError

from data_catalog.atomic import atomic_write_text
from schemas.manifest import SampleManifest

__all__ = ["MANIFEST_NAME", "ManifestError", "load_manifest", "write_manifest", "manifest_json_schema"]

MANIFEST_NAME = "manifest.json"


class ManifestError(ValueError):
    """A manifest could not be read or does not follow the schema."""


def _describe(error: ValidationError) -> str:
    lines = []
    for item in error.errors():
        where = ".".join(str(p) for p in item["loc"]) or "(top level)"
        lines.append(f"  {where}: {item['msg']}")
    return "\n".join(lines)


def load_manifest(path: Path) -> SampleManifest:
    """Load ``path`` (a manifest file, or a sample folder holding ``manifest.json``)."""
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ManifestError(f"{path}: no manifest file there") from None
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from None
    try:
        return SampleManifest.model_validate(raw)
    except ValidationError as exc:
        raise ManifestError(f"{path}: does not follow the sample manifest schema:\n{_describe(exc)}") from None


def write_manifest(path: Path, manifest: SampleManifest) -> None:
    atomic_write_text(Path(path), manifest.model_dump_json(indent=2) + "\n")


def manifest_json_schema() -> str:
    return json.dumps(SampleManifest.model_json_schema(), indent=2, sort_keys=True) + "\n"
