"""Reading and writing sample manifests (JSON), with errors that name the file and field."""

from __future__ import annotations

import json
import os
from pathlib import Path

from pydantic import ValidationError

from data_catalog.atomic import atomic_write_text
from data_catalog.hashing import sha256_file
from data_catalog.paths import path_inside
from data_catalog.textfiles import read_text_file
from schemas.manifest import DrawingSpecimen, SampleManifest, ScanEntry

__all__ = ["MANIFEST_NAME", "MAX_POINTS_PER_SAMPLE", "ManifestError", "load_manifest", "check_sample_files",
           "check_pass_file", "check_passes_distinct", "check_drawing_file", "write_manifest", "manifest_json_schema"]

MAX_POINTS_PER_SAMPLE = 4_000_000_000  # 12 times the paper's full-resolution plan

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
    text = read_text_file(path, "the sample's manifest file (JSON)", ManifestError, missing="no manifest file there")
    def each_key_once(pairs: list[tuple[str, object]]) -> dict:
        keys = [k for k, _ in pairs]
        twice = sorted({k for k in keys if keys.count(k) > 1})
        if twice:  # json.loads would keep the last silently
            raise ManifestError(f"{path}: field {', '.join(map(repr, twice))} given twice in one object; expected "
                                "each field once")
        return dict(pairs)

    try:
        raw = json.loads(text, object_pairs_hook=each_key_once)
    except json.JSONDecodeError as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from None
    try:
        return SampleManifest.model_validate(raw)
    except ValidationError as exc:
        raise ManifestError(f"{path}: does not follow the sample manifest schema:\n{_describe(exc)}") from None


def check_sample_files(sample_dir: Path, manifest: SampleManifest) -> None:
    """Refuse, before any work, a sample whose pass files are not its own or not what the
    manifest says: a path through a symbolic link (a sample must hold its own bytes; a link may
    lead anywhere), a pass store whose declared size differs from the manifest's, or a sample
    too large to be a scan (more than MAX_POINTS_PER_SAMPLE points); and a specimen drawing
    (``specimen.kind`` drawing) that is missing or not the file the manifest names
    (``check_drawing_file``). Missing pass files are left to the stages, which name every
    missing pass at once."""
    root = Path(sample_dir)
    total = sum(entry.n_points if isinstance(entry, ScanEntry)
                else entry.n_profiles * manifest.scanner.points_per_profile for _, entry in manifest.passes())
    if total > MAX_POINTS_PER_SAMPLE:
        raise ManifestError(f"{root}: the manifest's passes declare {total:,} points (n_profiles x "
                            f"points_per_profile, n_points), more than {MAX_POINTS_PER_SAMPLE:,}; that is not a scan of one specimen")
    for setup, entry in manifest.passes():
        check_pass_file(root, manifest, setup, entry)
    check_passes_distinct(root, manifest)
    if isinstance(manifest.specimen, DrawingSpecimen):
        check_drawing_file(root, manifest.specimen)


# the arrays that hold what a pass measured (not its attributes, intensities or times)
_MEASUREMENTS = {"profiles": ("x_mm", "z_mm"), "scan": ("points_mm",)}


def _measurement_files(store: Path, kind: str) -> list[Path]:
    files: list[Path] = []
    for name in _MEASUREMENTS[kind]:
        folder = store / name
        if folder.is_dir() and not folder.is_symlink():
            files += sorted(p for p in folder.rglob("*") if p.is_file() and not p.is_symlink())
    return files


def check_passes_distinct(sample_dir: Path, manifest: SampleManifest) -> None:
    """Refuse a sample in which two passes hold the same measurements byte for byte (a pass store
    copied over another's and relabelled, one file exported twice): no two scans of a real
    surface agree to the bit, and a copy would be registered onto its original and counted as a
    second view of the part. Compared by each store's measurement files' sizes first (a stat, no
    read), and by their content only where those agree. ManifestError naming both passes."""
    root = Path(sample_dir)
    by_sizes: dict[tuple, list[tuple[str, str, str, list[Path]]]] = {}
    for setup, entry in manifest.passes():
        kind = "scan" if isinstance(entry, ScanEntry) else "profiles"
        store = root / entry.file
        files = _measurement_files(store, kind)
        if not files:
            continue  # a missing or emptied store: its own stage names it
        sizes = (kind,) + tuple((p.relative_to(store).as_posix(), p.stat().st_size) for p in files)
        by_sizes.setdefault(sizes, []).append((entry.pass_id, setup, entry.file, files))
    for same_sizes in by_sizes.values():
        seen: dict[tuple[str, ...], tuple[str, str]] = {}
        for pass_id, setup, file, files in same_sizes if len(same_sizes) > 1 else ():
            digest = tuple(sha256_file(p) for p in files)
            if digest in seen:
                first, first_setup = seen[digest]
                raise ManifestError(
                    f"pass {pass_id} (setup {setup}): its store {file} holds the same "
                    f"measurements, byte for byte, as pass {first} (setup {first_setup}); a copy of another pass's "
                    "store (relabelled or exported twice?): expected each pass its own scan")
            seen[digest] = (pass_id, setup)


def _gate(root: Path, file: str, where: str, what: str, *, folder: bool) -> None:
    """ManifestError (``data_catalog.paths.path_inside``'s line) when ``root / file`` climbs out, goes
    through a symbolic link or is not a regular file (``folder``: a folder). A missing path is
    left to the caller."""
    if not os.path.lexists(root / file):
        return
    path_inside(root, file, where=f"{root / MANIFEST_NAME}: {where}", what=what, folder=folder, error=ManifestError)


def check_pass_file(sample_dir: Path, manifest: SampleManifest, setup: str, entry) -> None:
    """One pass of ``check_sample_files``: no symbolic link on its path, its declared size."""
    root = Path(sample_dir)
    path = root / entry.file
    where = f"pass {entry.pass_id} (setup {setup})"
    _gate(root, entry.file, where, f"pass {entry.pass_id}'s store, held in the sample folder itself", folder=True)
    scan = isinstance(entry, ScanEntry)
    meta = path / ("points_mm" if scan else "x_mm") / "zarr.json"
    if meta.is_file() and scan:
        try:
            shape = tuple(json.loads(meta.read_text(encoding="utf-8"))["shape"])
        except (ValueError, KeyError, TypeError) as exc:
            raise ManifestError(f"{where}: {meta} is unreadable ({exc})") from None
        if shape != (entry.n_points, 3):
            raise ManifestError(f"{where}: {path} holds {shape[0]:,} points, the manifest declares n_points "
                                f"{entry.n_points:,}")
    elif meta.is_file():
        try:
            shape = tuple(json.loads(meta.read_text(encoding="utf-8"))["shape"])
        except (ValueError, KeyError, TypeError) as exc:
            raise ManifestError(f"{where}: {meta} is unreadable ({exc})") from None
        expected = (entry.n_profiles, manifest.scanner.points_per_profile)
        if shape != expected:
            raise ManifestError(f"{where}: {path} holds {shape[0]:,} x {shape[1]:,} points, the manifest "
                                f"declares n_profiles {expected[0]:,} x points_per_profile {expected[1]:,}")


def check_drawing_file(sample_dir: Path, specimen: DrawingSpecimen) -> None:
    """The specimen's drawing (``specimen.file``): a regular file in the sample folder, reached
    through no symbolic link, whose content is the ``specimen.sha256`` the manifest states."""
    root = Path(sample_dir)
    path = root / specimen.file
    where = f"specimen.file {specimen.file}"
    _gate(root, specimen.file, where, "the part's drawing (STL or PLY), held in the sample folder itself", folder=False)
    if not path.is_file():
        raise ManifestError(f"{where}: {path} does not exist; expected the part's drawing (STL or PLY) the manifest "
                            "names, inside the sample folder")
    digest = sha256_file(path)
    if digest != specimen.sha256:
        raise ManifestError(f"{where}: {path} has sha256 {digest}, the manifest states specimen.sha256 "
                            f"{specimen.sha256}; expected the drawing the manifest was written for")


def write_manifest(path: Path, manifest: SampleManifest) -> None:
    atomic_write_text(Path(path), manifest.model_dump_json(indent=2) + "\n")


def manifest_json_schema() -> str:
    return json.dumps(SampleManifest.model_json_schema(), indent=2, sort_keys=True) + "\n"
