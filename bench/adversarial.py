#!/usr/bin/env python
"""Adversarial benchmark: weldrecon used as a hostile and careless user would, through the real
command line (one subprocess per command), each case tallied into exactly one outcome.

    python bench/adversarial.py [--only GROUP[,GROUP/CASE...]] [--list] [--out DIR] [--keep]

Outcomes (what the terminal, the exit status and the files say; see ``judge``):

- ``refused``   non-zero exit, the terminal names the problem (the case's expected substring: the
                file, pass, field or path concerned), no Python traceback;
- ``flagged``   exit 0, but the problem is reported (a warning line, a flagged entry in
                report.json's "checks", ``audit verify`` saying NOT intact), where finishing is
                acceptable;
- ``ok``        the right behaviour was to succeed, and it did (counted apart);
- ``unclear``   refused, but the message does not name what the case expects (or a valid request
                was refused);
- ``traceback`` "Traceback (most recent call last)" on the terminal;
- ``silent``    exit 0 (or still working when the case gave up waiting) and nothing says anything
                is wrong;
- ``damaged``   something that existed before the case (the sample, a previous run's results and
                audit trail, the catalog, the settings recorded with the results) changed or
                disappeared when it should not have: sha256 of every protected file before and
                after the case, compared automatically.

Each case states the RIGHT behaviour (what a QA auditor would want), not necessarily today's:
some cases come out silent or damaged, and that is what the report is for. The script always
exits 0 (a report, not a test).

Speed: the ``ci`` preset is simulated once; a 6-pass subset of it is reconstructed once (through
``weldrecon batch``, so that a catalog knows it) and every case that needs a sample or a finished
run restores or copies that template. Flow runs report to one Prefect API server started for the
whole benchmark (``--temporary-api``: each run starts its own, as a plain ``weldrecon reconstruct``
does; slower by about 10 s a run). The table goes to ``bench/results/adversarial.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the project's own tree hash (the manifest's content_sha256)

CI_CONFIG = REPO / "deploy" / "configs" / "ci.yaml"
RESULTS_MD = REPO / "bench" / "results" / "adversarial.md"
SIX = ["top-L02", "top-L04", "top-L05", "bottom-L02", "bottom-L04", "bottom-L05"]  # tests/conftest.py SIX
SAMPLE_ID = "sim-ci-0011"  # the ci preset's sample id
VICTIM = "top-L04"  # the pass the pass-store cases damage
TRACEBACK = "Traceback (most recent call last)"
OUTCOMES = ("refused", "flagged", "ok", "unclear", "traceback", "silent", "damaged")
USUAL_TRAIL_KINDS = {"run-started", "stage", "run-finished", "leftovers-swept"}
CALL_TIMEOUT_S = 240.0


# ------------------------------------------------------------------------------------------------
# processes


@dataclass
class Proc:
    """One finished command: its argv, exit status, output, and whether it ran out of time."""

    argv: list[str]
    rc: int | None
    stdout: str
    stderr: str
    seconds: float
    timed_out: bool = False
    timeout: float = 0.0

    @property
    def terminal(self) -> str:
        return self.stderr + "\n" + self.stdout

    def lines(self) -> list[str]:
        """The terminal's lines that say something: not progress ("[  1.2 s] ..."), not blank,
        not the pointer to the log file."""
        out = []
        for line in self.terminal.splitlines():
            text = line.strip()
            if not text or line.startswith("[") or text.startswith("(the details"):
                continue
            out.append(line.rstrip())
        return out

    def says(self, needle: str | None) -> bool:
        if needle is None:
            return True
        return needle.lower() in "\n".join(self.lines()).lower()

    def first(self) -> str:
        """The line that best says what happened: a traceback's last line, else the first error,
        warning or verdict line, else the first line."""
        if TRACEBACK in self.terminal:
            tail = [line for line in self.stderr.splitlines() if line.strip()]
            return "Traceback ... " + (tail[-1].strip() if tail else "")
        lines = self.lines()
        for k, line in enumerate(lines):
            low = line.lower()
            if any(w in low for w in ("error", "warning", "intact", "not registered", "failed", "refus")):
                more = f" {lines[k + 1].strip()}" if line.rstrip().endswith(":") and k + 1 < len(lines) else ""
                return line.strip() + more
        return lines[0].strip() if lines else "(nothing on the terminal)"


class Cli:
    """Runs ``python -m flows.cli`` the way a user does: a separate process in a scratch working
    directory, this repository first on the path, its own environment."""

    def __init__(self, root: Path, api_url: str | None) -> None:
        self.cwd = root / "cwd"
        self.cwd.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ)
        for name in ("PREFECT_API_URL", "WELDRECON_DASK", "WELDRECON_WORKSPACE"):
            env.pop(name, None)
        env.update(PYTHONPATH=str(REPO), PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_LOGGING_LEVEL="WARNING",
                   PREFECT_HOME=str(root / "prefect-home"), WELDRECON_LOG_DIR=str(root / "logs"),
                   WELDRECON_WORKSPACE=str(root / "ws-default"), NUMBA_CACHE_DIR=str(root / "numba-cache"),
                   PYTHONDONTWRITEBYTECODE="1", MPLCONFIGDIR=str(root / "mpl"))
        if api_url:
            env["PREFECT_API_URL"] = api_url
        self.env = env

    def argv(self, args) -> list[str]:
        return [sys.executable, "-m", "flows.cli", *[str(a) for a in args]]

    def start(self, args, env: dict[str, str] | None = None, cwd: Path | None = None) -> subprocess.Popen:
        return subprocess.Popen(self.argv(args), cwd=cwd or self.cwd, env={**self.env, **(env or {})},
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)

    def finish(self, proc: subprocess.Popen, args, started: float, timeout: float) -> Proc:
        try:
            out, err = proc.communicate(timeout=timeout)
            timed_out = False
        except subprocess.TimeoutExpired:
            kill_group(proc)
            out, err = proc.communicate()
            timed_out = True
        except BaseException:  # interrupted: nothing we started outlives the benchmark
            kill_group(proc)
            raise
        return Proc(self.argv(args)[2:], None if timed_out else proc.returncode, out.decode("utf-8", "replace"),
                    err.decode("utf-8", "replace"), time.monotonic() - started, timed_out, timeout)

    def run(self, *args, env: dict[str, str] | None = None, timeout: float = CALL_TIMEOUT_S,
            cwd: Path | None = None) -> Proc:
        started = time.monotonic()
        return self.finish(self.start(args, env, cwd), args, started, timeout)


def kill_group(proc: subprocess.Popen) -> None:
    """Kill a command we started and everything it started (its own session)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)


# ------------------------------------------------------------------------------------------------
# what must not change


def result_digest(path: Path) -> str:
    """A published result's sha256; the QA page's without its audit section, which is each run
    folder's own (its trail's head and length: a rerun adds entries), as flows.stages.qa_audit
    compares two runs' pages."""
    if path.name != "report.html":
        return sha256_file(path)
    from flows.stages.qa_audit import strip_audit

    return hashlib.sha256(strip_audit(path.read_text(encoding="utf-8")).encode()).hexdigest()


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()


def snapshot(path: Path) -> dict[str, str] | None:
    """sha256 of every file under ``path`` (symbolic links by target, never followed; a FIFO,
    socket or device by its mode, never opened); None when ``path`` does not exist."""
    if path.is_symlink():
        return {".": "link:" + os.readlink(path)}
    if path.is_file():
        return {".": sha256_file(path)}
    if not path.is_dir():
        return None
    found: dict[str, str] = {}
    for folder, dirs, files in os.walk(path):
        for name in files + [d for d in dirs if (Path(folder) / d).is_symlink()]:
            item = Path(folder) / name
            rel = item.relative_to(path).as_posix()
            try:
                if item.is_symlink():
                    found[rel] = "link:" + os.readlink(item)
                elif not item.is_file():  # a FIFO, a socket, a device: never opened (a FIFO blocks)
                    found[rel] = f"special: mode {oct(item.lstat().st_mode)}"
                else:
                    found[rel] = sha256_file(item)
            except OSError as exc:
                found[rel] = f"unreadable: {exc}"
    return found


@dataclass
class Guard:
    """Something a case must leave as it was: ``same`` (every file unchanged and present; with
    ``strict`` no new file either), ``append`` (a file that may only grow: its old bytes stay its
    prefix), or ``check`` (a function returning what is wrong, run at the end). ``when``:
    ``always``, or ``failed`` (only when the case's command failed: a refused run must leave the
    previous results as they were; a successful one may replace them)."""

    kind: str
    path: Path | None
    label: str
    when: str = "always"
    strict: bool = False
    before: object = None
    check: Callable[[], list[str]] | None = None

    def problems(self) -> list[str]:
        if self.kind == "check":
            return self.check()
        if self.kind == "append":
            if not self.path.is_file():
                return [f"{self.label}: disappeared"]
            now = self.path.read_bytes()
            if not now.startswith(self.before):
                return [f"{self.label}: rewritten (its earlier {len(self.before)} bytes are no longer its start)"]
            return []
        now = snapshot(self.path)
        if self.before is None:
            return [f"{self.label}: appeared"] if self.strict and now is not None else []
        if now is None:
            return [f"{self.label}: disappeared"]
        out = []
        for rel, digest in sorted(self.before.items()):
            where = self.label if rel == "." else f"{self.label}/{rel}"
            if rel not in now:
                out.append(f"{where}: disappeared")
            elif now[rel] != digest:
                out.append(f"{where}: changed")
        if self.strict:
            out += [f"{self.label}/{rel}: appeared" for rel in sorted(set(now) - set(self.before))]
        return out


# ------------------------------------------------------------------------------------------------
# cases


@dataclass
class Case:
    group: str
    name: str
    expect: tuple[str, ...]  # the right behaviours: refused / flagged / ok
    needle: str | None  # what the message must name
    what: str  # one line: what the hostile or careless user does
    fn: Callable[["Trial"], None]
    timeout: float = CALL_TIMEOUT_S

    @property
    def id(self) -> str:
        return f"{self.group}/{self.name}"


CASES: list[Case] = []
GROUPS = ["manifest", "passes", "config", "cli", "tamper", "identity", "simulate", "doors"]

# Run only with --all (or named with --only GROUP/CASE): variations of a default case, or already
# covered by the test suite; the default set fits in about 25 minutes on 2 cores.
EXTENDED = {
    "manifest/json-array", "manifest/json-null", "manifest/missing-scanner", "manifest/missing-schema-version",
    "manifest/extra-pass-field", "manifest/pass-id-slash", "manifest/file-backslash", "manifest/file-empty",
    "manifest/n-profiles-zero", "manifest/n-profiles-fraction", "manifest/points-per-profile",
    "manifest/sha-not-hex", "manifest/setups-object", "manifest/setup-no-passes", "manifest/setup-duplicate-name",
    "manifest/flange-sensor-nan", "manifest/flange-sensor-mirror", "manifest/flange-sensor-3x4",
    "manifest/direction-not-unit", "manifest/created-garbage", "manifest/z-range-reversed",
    "manifest/intensity-12-bit", "manifest/manifest-is-folder", "manifest/created-naive",
    "passes/chunk-missing-stale-hash", "passes/chunk-truncated", "passes/chunk-zeroed", "passes/dtype-float16",
    "passes/dtype-intensity-float", "passes/dtype-timestamp-int", "passes/shape-columns",
    "passes/array-missing-timestamp", "passes/complete-missing", "passes/format-other", "passes/format-version-2",
    "passes/group-json-garbage", "passes/times-zero", "passes/flange-not-rigid", "passes/flange-nan",
    "passes/intensity-saturated",
    "config/tab-indent", "config/section-case", "config/k-negative", "config/section-list", "config/python-name",
    "config/top-level-list", "config/top-level-scalar",
    "cli/out-in-pass-store", "cli/out-under-manifest", "cli/sample-is-run-folder", "cli/verify-empty-folder",
    "cli/verify-unknown-id", "cli/register-missing", "cli/dask-local-word", "cli/batch-samples-missing",
    "cli/catalog-garbage-verify",
    "tamper/trail-entry-rehashed", "tamper/trail-file-deleted", "tamper/trail-line-duplicated",
    "tamper/result-planted", "tamper/stage-folder-deleted", "tamper/stage-chunk-flipped",
    "tamper/stage-folder-planted",
    "simulate/config-wrong-type", "simulate/config-bad-yaml", "simulate/config-list",
    "simulate/config-reconstruction", "simulate/pace-negative", "simulate/demo-sample-is-file",
}


def case(group: str, name: str, expect: str | tuple[str, ...], needle: str | None, what: str,
         timeout: float = CALL_TIMEOUT_S):
    def register(fn: Callable[["Trial"], None]) -> Callable[["Trial"], None]:
        CASES.append(Case(group, name, (expect,) if isinstance(expect, str) else tuple(expect), needle, what, fn,
                          timeout))
        return fn

    return register


class Skip(Exception):
    """The case cannot be set up on this machine (e.g. no read-only mount without root)."""


@dataclass
class Trial:
    """One case being run: its folder, its commands, what it protects, what flags it."""

    ctx: "Context"
    case: Case
    dir: Path
    main: Proc | None = None
    needle: str | None = None  # what the message must name (the case's, or made more precise by the case)
    guards: list[Guard] = field(default_factory=list)
    flags: list[str] = field(default_factory=list)  # problems reported elsewhere than the terminal
    notes: list[str] = field(default_factory=list)
    verdict: tuple[str, str] | None = None  # set by cases that judge several commands themselves

    def cli(self, *args, **kwargs) -> Proc:
        kwargs.setdefault("timeout", self.case.timeout)
        return self.ctx.cli.run(*args, **kwargs)

    def label(self, path: Path) -> str:
        try:
            return Path(path).relative_to(self.ctx.root).as_posix()
        except ValueError:
            return str(path)

    def protect(self, path: Path, *, strict: bool = False, when: str = "always", label: str | None = None) -> None:
        self.guards.append(Guard("same", Path(path), label or self.label(path), when, strict, snapshot(Path(path))))

    def protect_append(self, path: Path, *, when: str = "always") -> None:
        path = Path(path)
        self.guards.append(Guard("append", path, self.label(path), when, before=path.read_bytes()))

    def require(self, label: str, check: Callable[[], list[str]], *, when: str = "always") -> None:
        self.guards.append(Guard("check", None, label, when, check=check))

    def failed(self) -> bool:
        return self.main is None or self.main.timed_out or self.main.rc != 0


def classify(proc: Proc, expect: tuple[str, ...], needle: str | None, flags: list[str] = ()) -> tuple[str, str]:
    """One command's outcome against what the case expects."""
    if proc.timed_out:
        outcome = "unclear" if expect == ("ok",) else "silent"
        return outcome, f"still working after {proc.timeout:.0f} s, nothing refused (killed)"
    if TRACEBACK in proc.terminal:
        return "traceback", proc.first()
    if proc.rc != 0:
        if expect == ("ok",):
            return "unclear", f"refused a valid request: {proc.first()}"
        if not proc.says(needle):
            return "unclear", proc.first()
        return "refused", proc.first()
    warnings = [line.strip() for line in proc.lines() if "warning" in line.lower()] + list(flags)
    if "ok" in expect:
        return "ok", proc.first() if not warnings else f"ok, with: {warnings[0]}"
    if warnings:
        named = [w for w in warnings if needle is None or needle.lower() in w.lower()]
        return ("flagged", named[0]) if named else ("unclear", warnings[0])
    return "silent", proc.first()


def judge(trial: Trial) -> tuple[str, str]:
    """The case's one outcome: damage first, then what the commands said."""
    if trial.verdict is not None:
        outcome, message = trial.verdict
    elif trial.main is None:
        outcome, message = "unclear", "the case ran no command"
    else:
        outcome, message = classify(trial.main, trial.case.expect, trial.needle, trial.flags)
    damage = []
    for guard in trial.guards:
        if guard.when == "failed" and not trial.failed():
            continue
        damage += guard.problems()
    if damage:
        more = f" (+{len(damage) - 3} more)" if len(damage) > 3 else ""
        return "damaged", f"{'; '.join(damage[:3])}{more} [was {outcome}: {message}]"
    if trial.notes:
        message += " [" + "; ".join(trial.notes) + "]"
    return outcome, message


# ------------------------------------------------------------------------------------------------
# the scratch space: the ci sample, the 6-pass subset, its finished run (the template)


def copy_sample(source: Path, dst: Path, keep: list[str], sample_id: str | None = None) -> Path:
    """A copy of the ci sample with only the passes ``keep`` (setups left empty dropped)."""
    dst.mkdir(parents=True)
    manifest = json.loads((source / "manifest.json").read_text())
    for setup in manifest["setups"]:
        setup["passes"] = [p for p in setup["passes"] if p["pass_id"] in keep]
    manifest["setups"] = [s for s in manifest["setups"] if s["passes"]]
    for setup in manifest["setups"]:
        for p in setup["passes"]:
            shutil.copytree(source / p["file"], dst / p["file"])
    if sample_id is not None:
        manifest["sample_id"] = sample_id
    (dst / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return dst


class Context:
    """The scratch space, prepared once, and the fixed places every case restores from it.

    ``sample`` (samples/six) is always the same path, the one the template run and the template
    catalog recorded: a case edits it after restoring it, so that a run folder copied from the
    template sees the sample it was made from."""

    def __init__(self, root: Path, cli: Cli) -> None:
        self.root = root
        self.cli = cli
        self.base = root / "base" / "ci"  # the ci preset, simulated once
        self.samples = root / "samples"
        self.sample = self.samples / "six"
        self.ws = root / "ws"
        self.run = self.ws / "runs" / SAMPLE_ID
        self.pristine = root / "pristine"
        self.cases = root / "cases"
        self.ready = False
        self.prep_seconds = 0.0

    def prepare(self) -> None:
        if self.ready:
            return
        t0 = time.monotonic()
        if not self.base.is_dir():
            done = self.cli.run("simulate", "--preset", "ci", "--no-preview", self.base, timeout=600)
            if done.rc != 0:
                raise SystemExit(f"adversarial: could not simulate the ci sample: {done.first()}\n{done.stderr[-3000:]}")
        if not (self.pristine / "ws").is_dir():
            shutil.rmtree(self.samples, ignore_errors=True)
            shutil.rmtree(self.ws, ignore_errors=True)
            copy_sample(self.base, self.sample, SIX)
            done = self.cli.run("batch", "--samples", self.samples, "--workspace", self.ws, "--config", CI_CONFIG,
                                timeout=900)
            verify = self.cli.run("audit", "verify", SAMPLE_ID, "--workspace", self.ws)
            if done.rc != 0 or not (self.run / "results" / "report.json").is_file() or verify.rc != 0:
                raise SystemExit(f"adversarial: the template run failed: {done.first()} / {verify.first()}\n"
                                 f"{done.stdout[-2000:]}{done.stderr[-3000:]}")
            self.pristine.mkdir(parents=True, exist_ok=True)
            shutil.copytree(self.sample, self.pristine / "six", symlinks=True)
            shutil.copytree(self.ws, self.pristine / "ws", symlinks=True)
        self.results = {p.name: result_digest(p) for p in sorted((self.pristine / "ws" / "runs" / SAMPLE_ID /
                                                                   "results").iterdir()) if p.is_file()}
        self.ready = True
        self.prep_seconds = time.monotonic() - t0

    # restoring the fixed places, copying the template
    def fresh_sample(self) -> Path:
        self.prepare()
        shutil.rmtree(self.sample, ignore_errors=True)
        if self.sample.is_symlink() or self.sample.is_file():
            self.sample.unlink()
        shutil.copytree(self.pristine / "six", self.sample, symlinks=True)
        return self.sample

    def fresh_ws(self) -> Path:
        self.prepare()
        shutil.rmtree(self.ws, ignore_errors=True)
        shutil.copytree(self.pristine / "ws", self.ws, symlinks=True)
        return self.ws

    def run_copy(self, dst: Path) -> Path:
        self.prepare()
        shutil.copytree(self.pristine / "ws" / "runs" / SAMPLE_ID, dst, symlinks=True)
        return dst

    def other_sample(self, dst: Path, keep: list[str] = SIX, sample_id: str | None = None) -> Path:
        self.prepare()
        return copy_sample(self.base, dst, keep, sample_id)


@contextlib.contextmanager
def read_only(folder: Path) -> Iterator[Path]:
    """``folder`` (made and filled by the caller) mounted read-only over itself for the block;
    as root a chmod does not stop writes, a read-only mount does."""
    folder.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        os.chmod(folder, 0o555)
        try:
            yield folder
        finally:
            os.chmod(folder, 0o755)
        return
    bind = subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True)
    if bind.returncode != 0:
        raise Skip(f"cannot bind-mount {folder}: {bind.stderr.decode(errors='replace').strip()}")
    try:
        ro = subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], capture_output=True)
        if ro.returncode != 0:
            raise Skip(f"cannot remount {folder} read-only: {ro.stderr.decode(errors='replace').strip()}")
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True)


# ------------------------------------------------------------------------------------------------
# editing samples: manifest and pass stores


def read_manifest(sample: Path) -> dict:
    return json.loads((sample / "manifest.json").read_text())


def write_manifest(sample: Path, manifest: dict) -> None:
    (sample / "manifest.json").write_text(json.dumps(manifest, indent=1))


def entry(manifest: dict, pass_id: str = VICTIM) -> dict:
    return next(p for s in manifest["setups"] for p in s["passes"] if p["pass_id"] == pass_id)


def store(sample: Path, pass_id: str = VICTIM) -> Path:
    return sample / "passes" / f"{pass_id}.zarr"


def rehash(sample: Path, pass_id: str = VICTIM) -> None:
    """Give the manifest the pass's new content_sha256, as an exporter that hashes what it wrote
    would: the damage must then be found in the data, not by the hash."""
    from data_catalog.hashing import sha256_tree

    manifest = read_manifest(sample)
    entry(manifest, pass_id)["content_sha256"] = sha256_tree(store(sample, pass_id))
    write_manifest(sample, manifest)


def no_hash(sample: Path, pass_id: str = VICTIM) -> None:
    manifest = read_manifest(sample)
    entry(manifest, pass_id)["content_sha256"] = None
    write_manifest(sample, manifest)


def edit_manifest(fn: Callable[[dict], object]) -> Callable[[Path], None]:
    def edit(sample: Path) -> None:
        manifest = read_manifest(sample)
        replaced = fn(manifest)
        write_manifest(sample, manifest if replaced is None else replaced)

    return edit


def manifest_bytes(fn: Callable[[bytes], bytes]) -> Callable[[Path], None]:
    def edit(sample: Path) -> None:
        path = sample / "manifest.json"
        path.write_bytes(fn(path.read_bytes()))

    return edit


def set_path(manifest: dict, dotted: str, value) -> None:
    """``setups.0.passes.1.n_profiles``-style assignment (a value of DELETE removes the key)."""
    *parents, last = dotted.split(".")
    node = manifest
    for part in parents:
        node = node[int(part)] if isinstance(node, list) else node[part]
    if value is DELETE:
        del node[int(last) if isinstance(node, list) else last]
    elif isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value


DELETE = object()
VICTIM_AT = "setups.0.passes.1"  # VICTIM in the 6-pass subset


def field_edit(dotted: str, value) -> Callable[[Path], None]:
    return edit_manifest(lambda m: set_path(m, dotted, value))


def array_edit(name: str, fn, *, hashed: str = "rehash") -> Callable[[Path], None]:
    """Change an array's values in place (same dtype and shape)."""

    def edit(sample: Path) -> None:
        import numpy as np
        import zarr

        with zarr.config.set({"array.write_empty_chunks": True}):  # every chunk stays on disk, as a cell writes it
            array = zarr.open_array(str(store(sample) / name), mode="r+")
            array[...] = fn(np.asarray(array[...]))
        _hash(sample, hashed)

    return edit


def array_replace(name: str, fn, *, hashed: str = "rehash") -> Callable[[Path], None]:
    """Replace an array by ``fn(old values)`` (any dtype or shape), chunked as a cell writes it;
    ``fn`` returning None deletes the array."""

    def edit(sample: Path) -> None:
        import numpy as np
        import zarr

        group = zarr.open_group(str(store(sample)), mode="r+")
        old_array = group[name]
        old = np.asarray(old_array[...])
        chunks, fill = old_array.chunks, old_array.fill_value
        new = fn(old)
        del group[name]
        if new is not None:
            rows = max(1, min(chunks[0], new.shape[0])) if new.ndim else 1
            same_kind = np.dtype(new.dtype).kind == old.dtype.kind
            group.create_array(name, data=new, chunks=(rows,) + new.shape[1:], config={"write_empty_chunks": True},
                               **({"fill_value": fill} if same_kind else {}))
        _hash(sample, hashed)

    return edit


def attrs_edit(fn: Callable[[dict], None], *, hashed: str = "rehash") -> Callable[[Path], None]:
    def edit(sample: Path) -> None:
        meta = store(sample) / "zarr.json"
        body = json.loads(meta.read_text())
        fn(body["attributes"])
        meta.write_text(json.dumps(body, indent=2))
        _hash(sample, hashed)

    return edit


def chunk_edit(array: str, chunk: str, fn: Callable[[Path], None], *, hashed: str = "rehash") -> Callable[[Path], None]:
    def edit(sample: Path) -> None:
        fn(store(sample) / array / "c" / chunk)
        _hash(sample, hashed)

    return edit


def _hash(sample: Path, how: str) -> None:
    if how == "rehash":
        rehash(sample)
    elif how == "none":
        no_hash(sample)


def write_yaml(trial: Trial, name: str, text: str | bytes) -> Path:
    path = trial.dir / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path


# ------------------------------------------------------------------------------------------------
# the usual shape of a case: edit the sample, reconstruct it into a copy of its finished run


def report_flags(trial: Trial, run: Path) -> None:
    """A successful run's report.json "checks" that are not ok count as flagged."""
    if trial.main is None or trial.main.rc != 0:
        return
    from flows.stages.outputs import REPORT

    with contextlib.suppress(OSError, ValueError):
        report = REPORT.read_path(run / "results" / "report.json")
        trial.flags += [f"report.json: pass {c.pass_}: {c.check}: {c.what}" for c in report.checks if c.result != "ok"]


def reconstruct_edited(trial: Trial, edit: Callable[[Path], None] | None = None, *, config: Path | str | None = None,
                       extra: tuple = (), env: dict | None = None) -> Path:
    """Restore the sample, ``edit`` it, copy its finished run, reconstruct the sample into that
    copy. Protected: the sample (nothing changed or added), the run's audit trail (append only),
    and its results/ when the run is refused (a refused run leaves the last results as they
    were)."""
    sample = trial.ctx.fresh_sample()
    if edit is not None:
        edit(sample)
    run = trial.ctx.run_copy(trial.dir / "run")
    trial.protect(sample, strict=True)
    trial.protect_append(run / "audit" / "trail.jsonl")
    trial.protect(run / "results", strict=True, when="failed")
    trial.main = trial.cli("reconstruct", sample, "--out", run, "--config", config or CI_CONFIG, *extra, env=env)
    report_flags(trial, run)
    return run


# --- manifest ----------------------------------------------------------------------------------

def _manifest_case(name: str, needle: str | None, what: str, edit: Callable[[Path], None],
                   expect: str | tuple[str, ...] = "refused") -> None:
    case("manifest", name, expect, needle, what, timeout=90)(lambda t: reconstruct_edited(t, edit))


def _bump_rotation(scale: float):
    def fn(pose):
        return [[v * scale if i < 3 and j < 3 else v for j, v in enumerate(row)] for i, row in enumerate(pose)]
    return fn


def _pose_edit(dotted: str, fn) -> Callable[[Path], None]:
    def edit(sample: Path) -> None:
        manifest = read_manifest(sample)
        node = manifest
        parts = dotted.split(".")
        for part in parts[:-1]:
            node = node[int(part)] if isinstance(node, list) else node[part]
        node[parts[-1]] = fn(node[parts[-1]])
        write_manifest(sample, manifest)

    return edit


def _dup_pass_id(m: dict) -> None:
    m["setups"][1]["passes"][0]["pass_id"] = m["setups"][0]["passes"][0]["pass_id"]


def _dup_file(m: dict) -> None:
    m["setups"][0]["passes"][1]["file"] = m["setups"][0]["passes"][0]["file"]


def _swap_files(m: dict) -> None:
    a, b = m["setups"][0]["passes"][0], m["setups"][0]["passes"][1]
    a["file"], b["file"] = b["file"], a["file"]
    a["content_sha256"], b["content_sha256"] = b["content_sha256"], a["content_sha256"]


def _dup_key(raw: bytes) -> bytes:
    """The same key twice in one object: JSON readers keep the last one, silently."""
    text = raw.decode("utf-8")
    return text.replace('"sample_id": "sim-ci-0011"', '"sample_id": "other-0001", "sample_id": "sim-ci-0011"', 1).encode()


def _latin1(raw: bytes) -> bytes:
    manifest = json.loads(raw)
    manifest["material"] = "Baustahl S355 geschweißt"
    return json.dumps(manifest, ensure_ascii=False).encode("latin-1")


def _file_not_store(sample: Path) -> None:
    shutil.rmtree(store(sample))
    store(sample).write_bytes(b"not a zarr store\n")
    no_hash(sample)


def _symlink_out(sample: Path) -> None:
    outside = sample.parent.parent / f"outside-{VICTIM}.zarr"
    shutil.rmtree(outside, ignore_errors=True)
    shutil.move(str(store(sample)), outside)
    store(sample).symlink_to(outside)


def _huge(m: dict) -> None:
    m["scanner"]["points_per_profile"] = 4096
    for s in m["setups"]:
        for p in s["passes"]:
            p["n_profiles"] = 10_000_000


for _name, _needle, _what, _edit, *_expect in [
    ("json-cut-short", "manifest.json", "the manifest cut off half way (a copy interrupted)",
     manifest_bytes(lambda b: b[: len(b) // 2])),
    ("not-utf8", "manifest.json", "the manifest saved as Latin-1 (a German material name)", manifest_bytes(_latin1)),
    ("utf8-bom", "manifest.json", "the manifest saved with a UTF-8 byte order mark (Windows editor): read it or "
     "name it", manifest_bytes(lambda b: b"\xef\xbb\xbf" + b), ("refused", "ok")),
    ("empty-file", "manifest.json", "the manifest is an empty file", manifest_bytes(lambda b: b"")),
    ("json-array", "manifest.json", "the manifest is a JSON array, not an object", manifest_bytes(lambda b: b"[]")),
    ("json-null", "manifest.json", "the manifest is JSON null", manifest_bytes(lambda b: b"null")),
    ("duplicate-key", "sample_id", "the manifest names sample_id twice (JSON keeps the last, silently)",
     manifest_bytes(_dup_key)),
    ("missing-sample-id", "sample_id", "no sample_id", field_edit("sample_id", DELETE)),
    ("missing-scanner", "scanner", "no scanner section", field_edit("scanner", DELETE)),
    ("missing-units", "units", "no units field (docs/file-formats.md says it is required)", field_edit("units", DELETE)),
    ("missing-schema-version", "schema_version", "no schema_version field",
     field_edit("schema_version", DELETE)),
    ("extra-field", "operator", "an extra top-level field 'operator'", field_edit("operator", "bob")),
    ("extra-pass-field", "gain_db", "an extra field in a pass entry", field_edit(f"{VICTIM_AT}.gain_db", 3)),
    ("units-inch", "units", "units 'inch'", field_edit("units", "inch")),
    ("schema-version-2", "schema_version", "schema_version '2.0' (a newer exporter)",
     field_edit("schema_version", "2.0")),
    ("sample-id-path", "sample_id", "sample_id '../../evil' (it names the run folder and the result files)",
     field_edit("sample_id", "../../evil")),
    ("pass-id-space", "pass_id", "a pass_id with a space", field_edit(f"{VICTIM_AT}.pass_id", VICTIM.replace("-", " "))),
    ("pass-id-slash", "pass_id", "a pass_id with a slash", field_edit(f"{VICTIM_AT}.pass_id", VICTIM.replace("-", "/"))),
    ("pass-id-duplicate", "top-L02", "two passes share a pass_id (top-L02 in both setups)",
     edit_manifest(_dup_pass_id)),
    ("file-duplicate", "top-L02.zarr", "two passes point at the same pass file", edit_manifest(_dup_file)),
    ("file-swapped", "top-L0", "two passes' files swapped (with their hashes): each store holds the other pass",
     edit_manifest(_swap_files)),
    ("file-dotdot", "passes.1.file", "a pass file '../../etc/passwd'", field_edit(f"{VICTIM_AT}.file", "../../etc/passwd")),
    ("file-absolute", "passes.1.file", "an absolute pass file path", field_edit(f"{VICTIM_AT}.file", "/etc/passwd")),
    ("file-backslash", "passes.1.file", f"a Windows path 'passes\\{VICTIM}.zarr'",
     field_edit(f"{VICTIM_AT}.file", f"passes\\{VICTIM}.zarr")),
    ("file-empty", "passes.1.file", "an empty pass file path", field_edit(f"{VICTIM_AT}.file", "")),
    ("file-missing", VICTIM, "a pass file that does not exist", field_edit(f"{VICTIM_AT}.file", "passes/nope.zarr")),
    ("file-not-a-store", VICTIM, "a pass file that is a plain file, not a zarr store", _file_not_store),
    ("file-symlink-out", VICTIM, "a pass store that is a symbolic link leading out of the sample", _symlink_out),
    ("n-profiles-off-by-one", VICTIM, "n_profiles one more than the store holds",
     edit_manifest(lambda m: entry(m).update(n_profiles=entry(m)["n_profiles"] + 1))),
    ("n-profiles-zero", "n_profiles", "n_profiles 0", field_edit(f"{VICTIM_AT}.n_profiles", 0)),
    ("n-profiles-fraction", "n_profiles", "n_profiles 939.5", field_edit(f"{VICTIM_AT}.n_profiles", 939.5)),
    ("points-per-profile", "points_per_profile", "points_per_profile 256 (the stores hold 128)",
     field_edit("scanner.points_per_profile", 256)),
    ("too-many-points", "points", "10 million profiles x 4096 points per pass declared", edit_manifest(_huge)),
    ("sha-mismatch", VICTIM, "content_sha256 of another pass", edit_manifest(
        lambda m: entry(m).update(content_sha256=entry(m, "top-L02")["content_sha256"]))),
    ("sha-not-hex", "content_sha256", "content_sha256 'TODO'", field_edit(f"{VICTIM_AT}.content_sha256", "TODO")),
    ("setups-empty", "setups", "setups []", field_edit("setups", [])),
    ("setups-object", "setups", "setups as an object keyed by name, not a list", edit_manifest(
        lambda m: m.update(setups={s["name"]: s for s in m["setups"]}))),
    ("setup-no-passes", "passes", "a setup with no passes", field_edit("setups.1.passes", [])),
    ("setup-duplicate-name", "setup", "both setups named 'top'", field_edit("setups.1.name", "top")),
    ("flange-sensor-scaled", "T_flange_sensor", "T_flange_sensor not rigid (rotation scaled by 1.01)",
     _pose_edit("scanner.T_flange_sensor", _bump_rotation(1.01))),
    ("flange-sensor-nan", "T_flange_sensor", "T_flange_sensor holding NaN",
     _pose_edit("scanner.T_flange_sensor", lambda p: [[float("nan") if (i, j) == (0, 3) else v
                                                        for j, v in enumerate(r)] for i, r in enumerate(p)])),
    ("flange-sensor-mirror", "T_flange_sensor", "T_flange_sensor a reflection (determinant -1)",
     _pose_edit("scanner.T_flange_sensor", lambda p: [[-v if j == 0 and i < 3 else v for j, v in enumerate(r)]
                                                       for i, r in enumerate(p)])),
    ("flange-sensor-3x4", "T_flange_sensor", "T_flange_sensor with 3 rows",
     _pose_edit("scanner.T_flange_sensor", lambda p: p[:3])),
    ("flange-start-scaled", "T_world_flange_start", "a pass's T_world_flange_start not rigid",
     _pose_edit(f"{VICTIM_AT}.nominal_motion.T_world_flange_start", _bump_rotation(1.05))),
    ("direction-not-unit", "direction_world", "direction_world [2, 0, 0]",
     field_edit(f"{VICTIM_AT}.nominal_motion.direction_world", [2.0, 0.0, 0.0])),
    ("created-naive", "created", "created without a timezone", field_edit("created", "2026-01-05T08:00:00")),
    ("created-garbage", "created", "created 'yesterday'", field_edit("created", "yesterday")),
    ("z-range-reversed", "z_range_mm", "z_range_mm [300, 150]", field_edit("scanner.z_range_mm", [300.0, 150.0])),
    ("intensity-12-bit", "intensity_bits", "intensity_bits 12", field_edit("scanner.intensity_bits", 12)),
    ("sticker-in-metres", "sticker", "sticker_diameter_mm 0.005 (metres, not mm)",
     field_edit("sticker_diameter_mm", 0.005)),
    ("specimen-in-metres", "length_mm", "the specimen's dimensions in metres (0.24 x 0.06 x 0.02): the scans "
     "show a 240 mm part", edit_manifest(lambda m: m["specimen"].update(
         length_mm=0.24, grip_width_mm=0.06, gauge_width_mm=0.044, gauge_length_mm=0.06,
         transition_radius_mm=0.04, thickness_mm=0.02)), ("refused", "flagged")),
]:
    _manifest_case(_name, _needle, _what, _edit, *_expect)


@case("manifest", "manifest-is-folder", "refused", "manifest.json", "manifest.json is a folder")
def _(t: Trial) -> None:
    def edit(sample: Path) -> None:
        (sample / "manifest.json").unlink()
        (sample / "manifest.json").mkdir()

    reconstruct_edited(t, edit)


# --- pass stores -------------------------------------------------------------------------------

def _pass_case(name: str, needle: str | None, what: str, edit: Callable[[Path], None],
               expect: str | tuple[str, ...] = "refused") -> None:
    case("passes", name, expect, needle, what, timeout=90)(lambda t: reconstruct_edited(t, edit))


def _cut(n: int):
    return lambda p: p.write_bytes(p.read_bytes()[:n])


def _zero_pass(sample: Path) -> None:
    import numpy as np

    for name in ("x_mm", "z_mm", "intensity", "timestamp_s", "T_world_flange"):
        array_replace(name, lambda a: np.zeros((0,) + a.shape[1:], a.dtype), hashed="keep")(sample)
    attrs_edit(lambda a: a.update(n_profiles=0), hashed="rehash")(sample)


def _all_nan(sample: Path) -> None:
    import numpy as np

    array_edit("x_mm", lambda a: np.full_like(a, np.nan), hashed="keep")(sample)
    array_edit("z_mm", lambda a: np.full_like(a, np.nan), hashed="keep")(sample)
    array_edit("intensity", lambda a: np.zeros_like(a), hashed="rehash")(sample)


def _swap_chunks(sample: Path) -> None:
    """Chunks 2 and 3 of the grids swapped on disk (a chunk written to the wrong key)."""
    for name in ("x_mm", "z_mm", "intensity"):
        a, b = store(sample) / name / "c" / "2" / "0", store(sample) / name / "c" / "3" / "0"
        da, db = a.read_bytes(), b.read_bytes()
        a.write_bytes(db)
        b.write_bytes(da)
    rehash(sample)


def _copy_of_neighbour(sample: Path) -> None:
    """VICTIM's store replaced by a copy of top-L02's, relabelled (a copy-paste in the export)."""
    shutil.rmtree(store(sample))
    shutil.copytree(store(sample, "top-L02"), store(sample))
    attrs_edit(lambda a: a.update(pass_id=VICTIM), hashed="rehash")(sample)


def _delete(name: str):
    return lambda sample: (shutil.rmtree(store(sample) / name), rehash(sample))


def _extra_array(sample: Path) -> None:
    import numpy as np
    import zarr

    zarr.open_group(str(store(sample)), mode="r+").create_array("operator_notes", data=np.zeros(4, np.float32))
    rehash(sample)


def _swap_times(a):
    a = a.copy()
    a[100], a[101] = a[101], a[100]
    return a


def _nan_at(index):
    def fn(a):
        a = a.copy()
        a[index] = float("nan")
        return a
    return fn


def _scale_pose(a):
    a = a.copy()
    a[300, :3, :3] *= 1.01
    return a


def _jump_pose(a):
    a = a.copy()
    a[400:, 0, 3] += 5.0
    return a


def _frozen(a):
    import numpy as np

    return np.repeat(a[:1], len(a), axis=0)


for _name, _needle, _what, _edit, *_expect in [
    ("chunk-missing", VICTIM, "the last chunk of x_mm deleted (content_sha256 updated to match)",
     lambda s: ((store(s) / "x_mm" / "c" / "7" / "0").unlink(), rehash(s))),
    ("chunk-missing-stale-hash", VICTIM, "the last chunk of x_mm deleted, the manifest's hash left as it was",
     lambda s: (store(s) / "x_mm" / "c" / "7" / "0").unlink()),
    ("chunk-truncated", VICTIM, "a z_mm chunk cut to 100 bytes (hash updated)", chunk_edit("z_mm", "3/0", _cut(100))),
    ("chunk-truncated-no-hash", VICTIM, "a z_mm chunk cut to 100 bytes, no content_sha256 in the manifest",
     chunk_edit("z_mm", "3/0", _cut(100), hashed="none")),
    ("chunk-zeroed", VICTIM, "an intensity chunk overwritten with zero bytes (same size; hash updated)",
     chunk_edit("intensity", "2/0", lambda p: p.write_bytes(bytes(len(p.read_bytes()))))),
    ("dtype-int32", "x_mm", "x_mm stored as int32 micrometres",
     array_replace("x_mm", lambda a: __import__("numpy").nan_to_num(a * 1000).astype("int32"))),
    ("dtype-float16", "z_mm", "z_mm stored as float16", array_replace("z_mm", lambda a: a.astype("float16"))),
    ("dtype-intensity-float", "intensity", "intensity stored as float32 0..1",
     array_replace("intensity", lambda a: (a / 1023).astype("float32"))),
    ("dtype-timestamp-int", "timestamp_s", "timestamp_s stored as int64 milliseconds",
     array_replace("timestamp_s", lambda a: (a * 1000).astype("int64"))),
    ("shape-columns", "z_mm", "z_mm one column short of x_mm", array_replace("z_mm", lambda a: a[:, :-1].copy())),
    ("shape-transposed", VICTIM, "x_mm stored transposed (columns x profiles)",
     array_replace("x_mm", lambda a: a.T.copy())),
    ("all-nan", VICTIM, "a pass with no returns at all (all NaN, intensity 0)", _all_nan),
    ("intensity-12-bit", "intensity", "intensity 2000 at one point (a 12-bit sensor)",
     array_edit("intensity", lambda a: (a.__setitem__((3, 7), 2000), a)[1])),
    ("intensity-saturated", VICTIM, "every return's intensity saturated at 1023 (gain too high)",
     array_edit("intensity", lambda a: __import__("numpy").where(a > 0, 1023, 0).astype(a.dtype))),
    ("array-missing-intensity", "intensity", "the intensity array deleted", _delete("intensity")),
    ("array-missing-timestamp", "timestamp_s", "the timestamp_s array deleted", _delete("timestamp_s")),
    ("poses-missing", VICTIM, "T_world_flange deleted while the manifest says has_profile_poses",
     _delete("T_world_flange")),
    ("complete-false", "complete", "attribute complete false (the writer did not finish)",
     attrs_edit(lambda a: a.update(complete=False))),
    ("complete-missing", "complete", "attribute complete missing", attrs_edit(lambda a: a.pop("complete"))),
    ("format-other", "format", "attribute format 'laser-line-v2'", attrs_edit(lambda a: a.update(format="laser-line-v2"))),
    ("format-version-2", "format_version", "attribute format_version 2",
     attrs_edit(lambda a: a.update(format_version=2))),
    ("units-inch", "units", "attribute units 'inch' in the store", attrs_edit(lambda a: a.update(units="inch"))),
    ("pass-id-other", VICTIM, "the store's pass_id attribute says top-L02",
     attrs_edit(lambda a: a.update(pass_id="top-L02"))),
    ("group-json-garbage", VICTIM, "the store's zarr.json is not JSON",
     lambda s: ((store(s) / "zarr.json").write_text("{garbage"), rehash(s))),
    ("zero-profiles", VICTIM, "a store with zero profiles", _zero_pass),
    ("times-unordered", "timestamp_s", "two profiles' times swapped", array_edit("timestamp_s", _swap_times)),
    ("times-nan", "timestamp_s", "a NaN profile time", array_edit("timestamp_s", _nan_at(200))),
    ("times-zero", "timestamp_s", "every profile time 0", array_edit("timestamp_s", lambda a: a * 0)),
    ("times-in-ms", "timestamp_s", "profile times in milliseconds (the manifest says 20 s, the times 20000)",
     array_edit("timestamp_s", lambda a: a * 1000), ("refused", "flagged")),
    ("flange-not-rigid", "flange", "one logged flange pose scaled by 1.01", array_edit("T_world_flange", _scale_pose)),
    ("flange-jump", "flange", "logged flange poses jump 5 mm at profile 400", array_edit("T_world_flange", _jump_pose)),
    ("flange-nan", "flange", "a logged flange pose holding NaN", array_edit("T_world_flange", _nan_at((500, 0, 3)))),
    ("flange-frozen", "flange", "every logged flange pose the first one (the logger stuck; the sweep says 15 mm/s)",
     array_edit("T_world_flange", _frozen), ("refused", "flagged")),
    ("poses-undeclared", "has_profile_poses", "the store logs flange poses, the manifest says has_profile_poses "
     "false", field_edit(f"{VICTIM_AT}.has_profile_poses", False), ("refused", "flagged")),
    ("chunk-out-of-place", VICTIM, "two chunks of the grids swapped on disk (hash updated)", _swap_chunks,
     ("flagged", "refused")),
    ("copy-of-neighbour", VICTIM, "the store is a relabelled copy of top-L02's", _copy_of_neighbour,
     ("refused", "flagged")),
    ("extra-array", None, "an extra array 'operator_notes' in the store (hash updated): harmless",
     _extra_array, "ok"),
]:
    _pass_case(_name, _needle, _what, _edit, *_expect)


# --- reconstruction configs --------------------------------------------------------------------

def _config_case(name: str, needle: str | None, what: str, text: str | bytes | None,
                 expect: str | tuple[str, ...] = "refused", filename: str = "settings.yaml") -> None:
    def run(t: Trial) -> None:
        path = write_yaml(t, filename, text) if text is not None else t.dir / filename
        reconstruct_edited(t, config=path)

    case("config", name, expect, needle, what, timeout=45)(run)


CI_TEXT = CI_CONFIG.read_text()
for _name, _needle, _what, _text, *_expect in [
    ("bad-yaml", "settings.yaml", "unclosed bracket", "merge: {cell_mm: 0.3\nmesh: [\n"),
    ("tab-indent", "settings.yaml", "tab-indented YAML", "merge:\n\tcell_mm: 0.3\n"),
    ("unknown-section", "mesher", "an unknown section 'mesher'", CI_TEXT + "mesher:\n  depth: 8\n"),
    ("unknown-field", "cell_size", "merge.cell_size (a misspelt cell_mm)", CI_TEXT.replace("cell_mm", "cell_size")),
    ("section-case", "Merge", "section 'Merge' (capitalised)", CI_TEXT.replace("merge:", "Merge:")),
    ("cell-zero", "merge.cell_mm", "merge.cell_mm 0", CI_TEXT.replace("cell_mm: 0.3", "cell_mm: 0")),
    ("cell-nan", "merge.cell_mm", "merge.cell_mm .nan", CI_TEXT.replace("cell_mm: 0.3", "cell_mm: .nan")),
    ("depth-20", "mesh.poisson_depth", "mesh.poisson_depth 20",
     CI_TEXT.replace("poisson_depth: 8", "poisson_depth: 20")),
    ("k-negative", "denoise.k", "denoise.k -1", CI_TEXT.replace("normal_window_mm: 1.5", "normal_window_mm: 1.5\n  k: -1")),
    ("k-fraction", "denoise.k", "denoise.k 8.5", "denoise:\n  normal_window_mm: 1.5\n  k: 8.5\n"),
    ("cell-text", "merge.cell_mm", "merge.cell_mm 'fine'", CI_TEXT.replace("cell_mm: 0.3", "cell_mm: fine")),
    ("section-list", "merge", "merge given as a list", "merge: [0.3, 2]\n"),
    ("gates-crossed", "final_distance_mm", "refine.final_distance_mm above max_distance_mm",
     CI_TEXT + "refine:\n  max_distance_mm: 0.2\n  final_distance_mm: 0.4\n"),
    ("schema-version-2", "schema_version", "schema_version '2.0'", CI_TEXT + "schema_version: '2.0'\n"),
    ("duplicate-section", "merge", "the merge section twice (YAML keeps the last, silently)",
     CI_TEXT + "merge:\n  cell_mm: 0.3\n  coarse_factor: 2\n"),
    ("python-object", "settings.yaml", "a !!python/object/apply tag that would run a command",
     "merge: !!python/object/apply:os.system ['touch SENTINEL']\n"),
    ("python-name", "settings.yaml", "a !!python/name tag", "merge: !!python/name:os.system\n"),
    ("anchor-bomb", "settings.yaml", "a YAML alias bomb (billion laughs)",
     "a: &a ['x','x','x','x','x','x','x','x','x']\n" + "".join(
         f"{chr(98 + i)}: &{chr(98 + i)} [" + ",".join([f"*{chr(97 + i)}"] * 9) + "]\n" for i in range(8))),
    ("empty-file", "settings.yaml", "an empty settings file (the defaults would run silently)", ""),
    ("top-level-list", "settings.yaml", "a YAML list at the top", "- merge\n- mesh\n"),
    ("top-level-scalar", "settings.yaml", "a YAML scalar at the top", "42\n"),
    ("not-utf8", "settings.yaml", "the settings file in Latin-1 (a comment with an umlaut)",
     "# Einstellungen für den CI-Lauf\n".encode("latin-1") + CI_TEXT.encode()),
    ("simulation-config", "weld", "a simulation config given to reconstruct",
     "weld:\n  treatment: burr-ground\nrobot:\n  pose_error_translation_mm: 0.4\n"),
    ("missing-file", "nope.yaml", "--config naming a file that does not exist", None, "refused", "nope.yaml"),
]:
    _config_case(_name, _needle, _what, _text, *_expect)


@case("config", "is-a-folder", "refused", "settings.d", "--config naming a folder", timeout=120)
def _(t: Trial) -> None:
    (t.dir / "settings.d").mkdir()
    reconstruct_edited(t, config=t.dir / "settings.d")


# python-object: nothing may have run
_python_object = next(c for c in CASES if c.id == "config/python-object")
_python_object_fn = _python_object.fn


def _python_object_guarded(t: Trial) -> None:
    t.require("no command run from the YAML", lambda: ["SENTINEL: a command in the YAML ran"]
              if (t.ctx.cli.cwd / "SENTINEL").exists() else [])
    _python_object_fn(t)


_python_object.fn = _python_object_guarded


# --- command line paths ------------------------------------------------------------------------

def _refused_before_work(t: Trial, *args, env: dict | None = None, cwd: Path | None = None) -> None:
    t.main = t.cli(*args, env=env, cwd=cwd)


@case("cli", "sample-missing", "refused", "no-such-sample", "reconstruct a sample folder that does not exist")
def _(t: Trial) -> None:
    _refused_before_work(t, "reconstruct", t.dir / "no-such-sample", "--out", t.dir / "run")


@case("cli", "sample-is-file", "refused", "notes.txt", "reconstruct a file")
def _(t: Trial) -> None:
    (t.dir / "notes.txt").write_text("not a sample\n")
    _refused_before_work(t, "reconstruct", t.dir / "notes.txt", "--out", t.dir / "run")


@case("cli", "sample-empty-folder", "refused", "manifest.json", "reconstruct an empty folder")
def _(t: Trial) -> None:
    (t.dir / "empty").mkdir()
    _refused_before_work(t, "reconstruct", t.dir / "empty", "--out", t.dir / "run")


@case("cli", "sample-is-run-folder", "refused", "manifest.json", "reconstruct a run folder (confused with the sample)")
def _(t: Trial) -> None:
    run = t.ctx.run_copy(t.dir / "run")
    t.protect(run)
    _refused_before_work(t, "reconstruct", run, "--out", t.dir / "run2")


def _out_case(name: str, needle: str, what: str, where: Callable[[Path, Path], Path]) -> None:
    @case("cli", name, "refused", needle, what)
    def run(t: Trial) -> None:
        sample = t.ctx.fresh_sample()
        out = where(sample, t.dir)
        t.protect(sample, strict=True)
        t.main = t.cli("reconstruct", sample, "--out", out, "--config", CI_CONFIG)


_out_case("out-is-sample", "--out", "--out the sample folder itself", lambda s, d: s)
_out_case("out-in-passes", "--out", "--out inside the sample's passes/", lambda s, d: s / "passes" / "run")
_out_case("out-in-pass-store", "--out", "--out inside a pass store", lambda s, d: store(s) / "run")
_out_case("out-under-manifest", "--out", "--out under manifest.json", lambda s, d: s / "manifest.json" / "run")


@case("cli", "out-is-file", "refused", "results.txt", "--out an existing file")
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    (t.dir / "results.txt").write_text("keep me\n")
    t.protect(t.dir / "results.txt")
    t.protect(sample, strict=True)
    t.main = t.cli("reconstruct", sample, "--out", t.dir / "results.txt", "--config", CI_CONFIG)


@case("cli", "out-parent-is-file", "refused", "results.txt", "--out under an existing file")
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    (t.dir / "results.txt").write_text("keep me\n")
    t.protect(t.dir / "results.txt")
    t.main = t.cli("reconstruct", sample, "--out", t.dir / "results.txt" / "run", "--config", CI_CONFIG)


@case("cli", "out-read-only", "refused", "readonly-disk", "--out in a read-only folder")
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    with read_only(t.dir / "readonly-disk"):
        t.main = t.cli("reconstruct", sample, "--out", t.dir / "readonly-disk" / "run", "--config", CI_CONFIG)


@case("cli", "default-out-read-only", "refused", "--out", "no --out, the sample on a read-only disk")
def _(t: Trial) -> None:
    disk = t.dir / "disk"
    disk.mkdir()
    shutil.copytree(t.ctx.pristine / "six", disk / "six", symlinks=True)
    with read_only(disk):
        t.main = t.cli("reconstruct", disk / "six", "--config", CI_CONFIG)


@case("cli", "out-foreign-folder", "refused", "--out", "--out a folder of someone else's files (a home folder)",
      timeout=40)
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    home = t.dir / "home"
    (home / "photos").mkdir(parents=True)
    (home / "thesis.tex").write_text("\\documentclass{article}\n")
    (home / "photos" / "weld.jpg").write_bytes(b"\xff\xd8\xff" + bytes(100))
    t.protect(home)
    t.protect(sample, strict=True)
    t.main = t.cli("reconstruct", sample, "--out", home, "--config", CI_CONFIG)


@case("cli", "path-with-spaces", "ok", None, "a sample and run folder with spaces and umlauts in their names")
def _(t: Trial) -> None:
    sample = t.dir / "Probe Nr 1 (geschweißt)"
    shutil.copytree(t.ctx.pristine / "six", sample)
    run = t.ctx.run_copy(t.dir / "Lauf ü 1")
    t.protect(sample, strict=True)
    t.main = t.cli("reconstruct", sample, "--out", run, "--config", CI_CONFIG)


@case("cli", "concurrent-same-out", ("ok", "refused"), "--out",
      "two reconstructions of the sample into the same run folder at once")
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    run = t.ctx.run_copy(t.dir / "run")
    t.protect(sample, strict=True)
    t.protect_append(run / "audit" / "trail.jsonl")
    args = ("reconstruct", sample, "--out", run, "--config", CI_CONFIG)
    started = time.monotonic()
    procs = [t.ctx.cli.start(args) for _ in range(2)]
    done = [t.ctx.cli.finish(p, args, started, t.case.timeout) for p in procs]
    verify = t.cli("audit", "verify", run)
    t.main = done[0]
    refusals = [d for d in done if d.rc != 0]
    if any(TRACEBACK in d.terminal for d in done):
        t.verdict = ("traceback", next(d.first() for d in done if TRACEBACK in d.terminal))
    elif verify.rc != 0:
        t.verdict = ("damaged", f"after two runs at once the trail does not verify: {_first_problem(verify)}")
    elif not refusals:
        changed = _results_changed(t.ctx, run)
        t.verdict = (("damaged", f"results differ from the single run's: {changed}") if changed else
                     ("ok", "both finished; the trail verifies; the results are the single run's bytes"))
    elif len(refusals) == 1 and (refusals[0].says("--out") or refusals[0].says("in use")):
        t.verdict = ("refused", refusals[0].first())
    else:
        t.verdict = ("unclear", " / ".join(d.first() for d in done))


@case("cli", "ws-read-only", "refused", "readonly-disk", "catalog register into a workspace on a read-only disk")
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    with read_only(t.dir / "readonly-disk"):
        t.main = t.cli("catalog", "register", sample, "--workspace", t.dir / "readonly-disk" / "ws")


@case("cli", "ws-is-file", "refused", "ws.txt", "--workspace naming a file")
def _(t: Trial) -> None:
    (t.dir / "ws.txt").write_text("x\n")
    t.protect(t.dir / "ws.txt")
    t.main = t.cli("catalog", "list", "--workspace", t.dir / "ws.txt")


def _catalog_damage(name: str, what: str, damage: Callable[[Path], None], command: tuple) -> None:
    @case("cli", name, "refused", "catalog.sqlite", what)
    def run(t: Trial) -> None:
        ws = t.ctx.fresh_ws()
        sample = t.ctx.fresh_sample()
        damage(ws / "catalog.sqlite")
        t.protect(ws / "catalog.sqlite")
        t.protect(ws / "runs")
        t.protect(sample, strict=True)
        t.main = t.cli(*[ws if a == "WS" else (sample if a == "SAMPLE" else a) for a in command])


def _garbage(path: Path) -> None:
    for extra in ("-wal", "-shm"):
        Path(str(path) + extra).unlink(missing_ok=True)
    path.write_bytes(b"this is not an SQLite database" * 100)


def _halve(path: Path) -> None:
    for extra in ("-wal", "-shm"):
        Path(str(path) + extra).unlink(missing_ok=True)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2 + 100])


def _page_garbage(path: Path) -> None:
    for extra in ("-wal", "-shm"):
        Path(str(path) + extra).unlink(missing_ok=True)
    data = bytearray(path.read_bytes())
    data[4096:8192] = b"\xa5" * 4096
    path.write_bytes(bytes(data))


def _folder(path: Path) -> None:
    for extra in ("", "-wal", "-shm"):
        Path(str(path) + extra).unlink(missing_ok=True)
    path.mkdir()


_catalog_damage("catalog-garbage-list", "catalog.sqlite overwritten with text; catalog list", _garbage,
                ("catalog", "list", "--workspace", "WS"))
_catalog_damage("catalog-halved-list", "catalog.sqlite cut in half; catalog list", _halve,
                ("catalog", "list", "--workspace", "WS"))
_catalog_damage("catalog-page-garbage-show", "a page of catalog.sqlite overwritten; catalog show", _page_garbage,
                ("catalog", "show", SAMPLE_ID, "--workspace", "WS"))
_catalog_damage("catalog-garbage-register", "catalog.sqlite overwritten with text; catalog register", _garbage,
                ("catalog", "register", "SAMPLE", "--workspace", "WS"))
_catalog_damage("catalog-garbage-verify", "catalog.sqlite overwritten with text; audit verify SAMPLE_ID", _garbage,
                ("audit", "verify", SAMPLE_ID, "--workspace", "WS"))
_catalog_damage("catalog-is-folder", "catalog.sqlite is a folder; catalog list", _folder,
                ("catalog", "list", "--workspace", "WS"))


@case("cli", "register-file", "refused", "notes.txt", "catalog register a file")
def _(t: Trial) -> None:
    (t.dir / "notes.txt").write_text("x\n")
    t.main = t.cli("catalog", "register", t.dir / "notes.txt", "--workspace", t.dir / "ws")


@case("cli", "register-empty-folder", "refused", "empty", "catalog register an empty folder")
def _(t: Trial) -> None:
    (t.dir / "empty").mkdir()
    t.main = t.cli("catalog", "register", t.dir / "empty", "--workspace", t.dir / "ws")


@case("cli", "register-missing", "refused", "gone", "catalog register a path that does not exist")
def _(t: Trial) -> None:
    t.main = t.cli("catalog", "register", t.dir / "gone", "--workspace", t.dir / "ws")


@case("cli", "show-unknown", "refused", "no-such-id", "catalog show an unknown sample id")
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    t.protect(ws / "catalog.sqlite")
    t.main = t.cli("catalog", "show", "no-such-id", "--workspace", ws)


@case("cli", "verify-empty-folder", "refused", "trail", "audit verify an empty folder")
def _(t: Trial) -> None:
    (t.dir / "empty").mkdir()
    t.main = t.cli("audit", "verify", t.dir / "empty")


@case("cli", "verify-sample-folder", "refused", "trail", "audit verify the sample folder instead of its run")
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    t.protect(sample, strict=True)
    t.main = t.cli("audit", "verify", sample)


@case("cli", "verify-unknown-id", "refused", "no-such-id", "audit verify an unknown sample id")
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    t.main = t.cli("audit", "verify", "no-such-id", "--workspace", ws)


def _dask_case(name: str, needle: str, what: str, address: str | None, env: dict | None = None) -> None:
    @case("cli", name, "refused", needle, what, timeout=120)
    def run(t: Trial) -> None:
        reconstruct_edited(t, extra=("--dask", address) if address else (), env=env)


_dask_case("dask-unreachable", "127.0.0.1:1", "--dask tcp://127.0.0.1:1 (nothing listens)", "tcp://127.0.0.1:1")
_dask_case("dask-local-0", "local:0", "--dask local:0", "local:0")
_dask_case("dask-local-word", "local:many", "--dask local:many", "local:many")
_dask_case("dask-http", "http://127.0.0.1:1", "--dask http://127.0.0.1:1 (not a scheduler address)",
           "http://127.0.0.1:1")
_dask_case("dask-env-unreachable", "127.0.0.1:1", "WELDRECON_DASK=tcp://127.0.0.1:1 in the environment", None,
           {"WELDRECON_DASK": "tcp://127.0.0.1:1"})


@case("cli", "follow-timeout-negative", "refused", "follow-timeout", "--follow --follow-timeout -5", timeout=120)
def _(t: Trial) -> None:
    reconstruct_edited(t, extra=("--follow", "--follow-timeout", "-5"))


@case("cli", "follow-pass-never-comes", "refused", VICTIM, "--follow, one pass never lands (timeout 3 s)",
      timeout=120)
def _(t: Trial) -> None:
    reconstruct_edited(t, lambda s: shutil.rmtree(store(s)), extra=("--follow", "--follow-timeout", "3"))


@case("cli", "batch-max-concurrent-0", "refused", "concurrent", "batch --max-concurrent 0", timeout=120)
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    t.protect(ws / "runs")
    t.main = t.cli("batch", "--workspace", ws, "--max-concurrent", "0", "--config", CI_CONFIG)


@case("cli", "batch-samples-missing", "refused", "no-such-folder", "batch --samples naming a missing folder",
      timeout=120)
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    t.protect(ws / "runs")
    t.main = t.cli("batch", "--samples", t.dir / "no-such-folder", "--workspace", ws, "--config", CI_CONFIG)


# --- audit tampering on a finished run ---------------------------------------------------------

def trail_path(ws: Path) -> Path:
    return ws / "runs" / SAMPLE_ID / "audit" / "trail.jsonl"


def trail_lines(ws: Path) -> list[bytes]:
    return trail_path(ws).read_bytes().splitlines(keepends=True)


def digest(entry_: dict) -> str:
    body = {k: v for k, v in entry_.items() if k != "hash"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


def rechain(entries: list[dict]) -> list[bytes]:
    """Every entry's prev and hash recomputed: a forger who read audit.py."""
    prev = "0" * 64
    out = []
    for e in entries:
        e["prev"] = prev
        e["hash"] = digest(e)
        prev = e["hash"]
        out.append((json.dumps(e, sort_keys=True, default=str) + "\n").encode())
    return out


def stage_folder(ws: Path, stage: str) -> Path:
    from flows.stages.outputs import REPORT

    key = REPORT.read_path(ws / "runs" / SAMPLE_ID / "results" / "report.json").stage_keys[stage]
    return ws / "runs" / SAMPLE_ID / "stages" / stage / (key if isinstance(key, str) else key[0])


def _results_changed(ctx: Context, run: Path) -> list[str]:
    """results/ files that differ from the untampered template run's (or are missing)."""
    out = []
    for name, digest_ in ctx.results.items():
        path = run / "results" / name
        if not path.is_file():
            out.append(f"results/{name} missing")
        elif result_digest(path) != digest_:
            out.append(f"results/{name} differs")
    return out


def tamper_case(name: str, needle: str | None, what: str, evidence: bool = False,
                expect: str | tuple[str, ...] = "flagged"):
    """A finished run (the template workspace: catalog + run folder), tampered by ``fn``; then
    ``audit verify`` (must say NOT intact, naming ``needle``), a rerun of the sample into the
    run folder (must not publish tampered data) and ``audit verify`` again. ``evidence``: the
    tampering hit the trail itself, so after the rerun it must still show (verify NOT intact, or
    an entry that records it, or the rerun refused), not be laundered into a clean-looking
    trail."""

    def register(fn: Callable[[Path], str | None]):
        @case("tamper", name, expect, needle, what)
        def run(t: Trial) -> None:
            ws = t.ctx.fresh_ws()
            sample = t.ctx.fresh_sample()
            run_dir = ws / "runs" / SAMPLE_ID
            precise = fn(ws)  # a tamper may say more precisely what verify must name (the line)
            if precise is not None:
                t.needle = precise
            t.protect(sample, strict=True)
            before = t.cli("audit", "verify", SAMPLE_ID, "--workspace", ws)
            t.main = before
            rerun = t.cli("reconstruct", sample, "--out", run_dir, "--config", CI_CONFIG,
                          env={"WELDRECON_WORKSPACE": str(ws)})
            after = t.cli("audit", "verify", SAMPLE_ID, "--workspace", ws)
            t.verdict = _tamper_verdict(t, before, rerun, after, run_dir, evidence)

        return run

    return register


def _tamper_verdict(t: Trial, before: Proc, rerun: Proc, after: Proc, run_dir: Path, evidence: bool) -> tuple[str, str]:
    expect, needle = t.case.expect, t.needle
    for proc in (before, rerun, after):
        if TRACEBACK in proc.terminal:
            return "traceback", f"{' '.join(proc.argv[:2])}: {proc.first()}"
    tail = (f"; rerun: {'exit 0' if rerun.rc == 0 else 'refused: ' + rerun.first()}; "
            f"verify after: {'intact' if after.rc == 0 else 'NOT intact: ' + _first_problem(after)}")
    published = _results_changed(t.ctx, run_dir) if rerun.rc == 0 else []
    if expect == ("ok",):
        if before.rc != 0 or after.rc != 0:
            return "unclear", f"an intact run did not verify: {_first_problem(before if before.rc else after)}"
        if rerun.rc != 0:
            return "unclear", f"refused a valid rerun: {rerun.first()}"
        if published:
            return "damaged", f"the rerun changed the results: {', '.join(published)}"
        return "ok", f"verify intact; rerun exit 0, results unchanged{tail[tail.index('; verify'):]}"
    if before.rc == 0:
        return "silent", f"audit verify: {before.first()}{tail}"
    if needle is not None and not any(needle.lower() in line.lower() for line in _problems(before)):
        return "unclear", f"audit verify: {_first_problem(before)}{tail}"
    if published:
        return "damaged", f"the rerun published data that is not the untampered run's: {', '.join(published)}{tail}"
    if rerun.rc != 0 and "unexpected" in rerun.first():
        return "unclear", f"verify named it ({_first_problem(before)}), but the rerun failed with: {rerun.first()}"
    if evidence and rerun.rc == 0 and after.rc == 0:
        kinds = [e.get("kind") for e in _entries(run_dir)]
        unusual = sorted({k for k in kinds if k not in USUAL_TRAIL_KINDS})
        if not unusual:
            return "silent", (f"laundered: verify flagged it ({_first_problem(before)}), but after the rerun the trail "
                              f"verifies and no entry records the tampering{tail}")
    return "flagged", f"{_first_problem(before)}{tail}"


def _problems(proc: Proc) -> list[str]:
    """What ``audit verify`` names: its lines without the "RUN: audit trail NOT intact" header."""
    return [line.strip() for line in proc.lines() if "audit trail NOT intact" not in line]


def _first_problem(proc: Proc) -> str:
    problems = _problems(proc)
    return problems[0] if problems else proc.first()


def _entries(run_dir: Path) -> list[dict]:
    out = []
    with contextlib.suppress(OSError):
        for line in (run_dir / "audit" / "trail.jsonl").read_bytes().splitlines():
            with contextlib.suppress(ValueError):
                out.append(json.loads(line))
    return out


@case("tamper", "untouched", "ok", None, "rerun an intact finished run: nothing to say, nothing recomputed")
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    sample = t.ctx.fresh_sample()
    run_dir = ws / "runs" / SAMPLE_ID
    t.protect(sample, strict=True)
    t.protect_append(trail_path(ws))
    before = t.cli("audit", "verify", SAMPLE_ID, "--workspace", ws)
    t.main = rerun = t.cli("reconstruct", sample, "--out", run_dir, "--config", CI_CONFIG,
                           env={"WELDRECON_WORKSPACE": str(ws)})
    after = t.cli("audit", "verify", SAMPLE_ID, "--workspace", ws)
    t.verdict = _tamper_verdict(t, before, rerun, after, run_dir, False)
    if t.verdict[0] == "ok":
        recomputed = [e for e in _entries(run_dir)[len(trail_lines(t.ctx.pristine / "ws")):]
                      if e.get("kind") == "stage" and not e.get("cached")]
        if recomputed:
            t.verdict = ("unclear", f"an intact rerun recomputed {len(recomputed)} stage(s), e.g. "
                                    f"{recomputed[0].get('stage')}")


@tamper_case("stage-record-metrics", "stages/registration", "a stage's record.json metrics edited (a nicer "
             "residual), hashes left as they were")
def _(ws: Path) -> None:
    path = stage_folder(ws, "registration") / "record.json"
    record = json.loads(path.read_text())
    record["metrics"]["residual_max_mm"] = 0.001
    path.write_text(json.dumps(record, indent=1))


@tamper_case("stage-output-with-hash", "stages/registration", "a stage output replaced together with its hash "
             "in record.json")
def _(ws: Path) -> None:
    from data_catalog.hashing import sha256_tree

    folder = stage_folder(ws, "registration")
    summary = folder / "registration.json"
    body = json.loads(summary.read_text())
    body["pairs_below_min_common"] = []
    body["forged"] = True
    summary.write_text(json.dumps(body))
    record = json.loads((folder / "record.json").read_text())
    record["outputs"]["registration.json"] = sha256_tree(summary)
    (folder / "record.json").write_text(json.dumps(record, indent=1))


@tamper_case("forged-stage-and-trail", "trail", "a stage output, its record and the trail all edited and the "
             "trail re-chained (only a head hash kept elsewhere can tell)", evidence=True)
def _(ws: Path) -> None:
    folder = stage_folder(ws, "registration")
    rel = folder.relative_to(ws / "runs" / SAMPLE_ID).as_posix()
    path = folder / "record.json"
    record = json.loads(path.read_text())
    record["metrics"]["residual_max_mm"] = 0.001
    path.write_text(json.dumps(record, indent=1))
    new = sha256_file(path)
    entries = [json.loads(line) for line in trail_lines(ws)]
    for e in entries:
        if f"{rel}/record.json" in (e.get("artefacts") or {}):
            e["artefacts"][f"{rel}/record.json"] = new
            if isinstance(e.get("record"), dict):
                e["record"]["metrics"]["residual_max_mm"] = 0.001
    trail_path(ws).write_bytes(b"".join(rechain(entries)))


@tamper_case("trail-entry-edited", "trail line", "a stage entry of the trail edited (metrics), its hash left",
             evidence=True)
def _(ws: Path) -> None:
    lines = trail_lines(ws)
    k = next(i for i, line in enumerate(lines) if json.loads(line).get("stage") == "registration")
    e = json.loads(lines[k])
    e["record"]["metrics"]["residual_max_mm"] = 0.001
    lines[k] = (json.dumps(e, sort_keys=True) + "\n").encode()
    trail_path(ws).write_bytes(b"".join(lines))
    return f"trail line {k + 1} "


@tamper_case("trail-entry-rehashed", "trail line", "a trail entry edited and its own hash recomputed (the next "
             "entry's prev left)", evidence=True)
def _(ws: Path) -> None:
    lines = trail_lines(ws)
    k = next(i for i, line in enumerate(lines) if json.loads(line).get("stage") == "registration")
    e = json.loads(lines[k])
    e["record"]["metrics"]["residual_max_mm"] = 0.001
    e["hash"] = digest(e)
    lines[k] = (json.dumps(e, sort_keys=True) + "\n").encode()
    trail_path(ws).write_bytes(b"".join(lines))


@tamper_case("trail-last-line-deleted", "results/", "the trail's last line (run-finished) deleted", evidence=True)
def _(ws: Path) -> None:
    trail_path(ws).write_bytes(b"".join(trail_lines(ws)[:-1]))


@tamper_case("trail-last-3-deleted", "results/", "the trail's last 3 lines deleted", evidence=True)
def _(ws: Path) -> None:
    trail_path(ws).write_bytes(b"".join(trail_lines(ws)[:-3]))


@tamper_case("trail-emptied", "results/", "every line of the trail deleted (an empty file)", evidence=True)
def _(ws: Path) -> None:
    trail_path(ws).write_bytes(b"")


@tamper_case("trail-file-deleted", "trail", "the trail file deleted", evidence=True)
def _(ws: Path) -> None:
    trail_path(ws).unlink()


@tamper_case("trail-cut-mid-line", "line", "the trail cut in the middle of its last line", evidence=True)
def _(ws: Path) -> None:
    data = trail_path(ws).read_bytes()
    last = data.rstrip(b"\n").rfind(b"\n") + 1
    trail_path(ws).write_bytes(data[: last + (len(data) - last) // 2])
    return f"line {len(data.splitlines())}"


@tamper_case("trail-non-utf8-tail", "UTF-8", "bytes that are not UTF-8 appended to the trail", evidence=True)
def _(ws: Path) -> None:
    with open(trail_path(ws), "ab") as f:
        f.write(b'{"kind": "stage", "note": "\xff\xfe\xfd"}\n')


@tamper_case("trail-lines-swapped", "trail line", "two trail lines swapped", evidence=True)
def _(ws: Path) -> None:
    lines = trail_lines(ws)
    lines[3], lines[4] = lines[4], lines[3]
    trail_path(ws).write_bytes(b"".join(lines))
    return "trail line 4 "


@tamper_case("trail-line-duplicated", "trail line", "a trail line repeated", evidence=True)
def _(ws: Path) -> None:
    lines = trail_lines(ws)
    lines.insert(6, lines[5])
    trail_path(ws).write_bytes(b"".join(lines))
    return "trail line 7 "


@tamper_case("result-stl-edited", f"{SAMPLE_ID}.stl", "one byte of the published STL changed")
def _(ws: Path) -> None:
    path = ws / "runs" / SAMPLE_ID / "results" / f"{SAMPLE_ID}.stl"
    data = bytearray(path.read_bytes())
    data[200] ^= 0xFF
    path.write_bytes(bytes(data))


@tamper_case("result-report-edited", "report.json", "the published report.json edited (a nicer residual)")
def _(ws: Path) -> None:
    path = ws / "runs" / SAMPLE_ID / "results" / "report.json"
    report = json.loads(path.read_text())
    report["stages"]["registration"]["residual_max_mm"] = 0.001
    path.write_text(json.dumps(report, indent=2))


@tamper_case("result-deleted", f"{SAMPLE_ID}.ply", "a published result (the PLY) deleted")
def _(ws: Path) -> None:
    (ws / "runs" / SAMPLE_ID / "results" / f"{SAMPLE_ID}.ply").unlink()


@tamper_case("result-planted", "final.stl", "an extra file planted in results/")
def _(ws: Path) -> None:
    shutil.copyfile(ws / "runs" / SAMPLE_ID / "results" / f"{SAMPLE_ID}.stl",
                    ws / "runs" / SAMPLE_ID / "results" / f"{SAMPLE_ID}-final.stl")


@tamper_case("forged-report-and-trail", "trail", "the published report.json edited, its run-finished hash "
             "updated and the trail re-chained", evidence=True)
def _(ws: Path) -> None:
    path = ws / "runs" / SAMPLE_ID / "results" / "report.json"
    report = json.loads(path.read_text())
    report["stages"]["registration"]["residual_max_mm"] = 0.001
    path.write_text(json.dumps(report, indent=2))
    entries = [json.loads(line) for line in trail_lines(ws)]
    for e in entries:
        if "results/report.json" in (e.get("artefacts") or {}):
            e["artefacts"]["results/report.json"] = sha256_file(path)
    trail_path(ws).write_bytes(b"".join(rechain(entries)))


@tamper_case("settings-edited", "config.json", "the settings recorded with the results (config.json) edited to "
             "claim the paper's Poisson depth")
def _(ws: Path) -> None:
    run_dir = ws / "runs" / SAMPLE_ID
    path = run_dir / "results" / "config.json"
    path = path if path.is_file() else run_dir / "config.json"
    body = json.loads(path.read_text())
    body["mesh"]["poisson_depth"] = 12
    path.write_text(json.dumps(body, indent=2) + "\n")


@tamper_case("stage-folder-deleted", "stages/merge", "a stage's folder (merge) deleted")
def _(ws: Path) -> None:
    shutil.rmtree(stage_folder(ws, "merge"))


@tamper_case("stage-chunk-flipped", "stages/merge", "one byte of a merged-cloud chunk flipped")
def _(ws: Path) -> None:
    chunk = next(p for p in sorted((stage_folder(ws, "merge") / "merged.zarr").rglob("*"))
                 if p.is_file() and p.name != "zarr.json")
    data = bytearray(chunk.read_bytes())
    data[min(40, len(data) - 1)] ^= 0xFF
    chunk.write_bytes(bytes(data))


@tamper_case("stage-record-deleted", "stages/mesh", "a stage's record.json (mesh) deleted")
def _(ws: Path) -> None:
    (stage_folder(ws, "mesh") / "record.json").unlink()


@tamper_case("stage-folder-planted", "stages/mesh", "a copy of a stage folder planted under another key")
def _(ws: Path) -> None:
    folder = stage_folder(ws, "mesh")
    shutil.copytree(folder, folder.parent / ("0" * 64))


# --- folder identity ---------------------------------------------------------------------------

def _results_settings_agree(run: Path) -> list[str]:
    """The settings recorded with results/ (results/config.json, or the run folder's config.json)
    must be the settings of the report in results/."""
    report_path = run / "results" / "report.json"
    settings = run / "results" / "config.json"
    settings = settings if settings.is_file() else run / "config.json"
    try:
        report = json.loads(report_path.read_text())
        recorded = json.loads(settings.read_text())
    except (OSError, ValueError) as exc:
        return [f"results and their settings cannot be compared ({exc})"]
    if report.get("config") != recorded:
        return [f"{settings.relative_to(run)} no longer holds the settings of results/report.json"]
    return []


def _settings_file(run: Path) -> Path:
    return run / "results" / "config.json" if (run / "results" / "config.json").is_file() else run / "config.json"


@case("identity", "renamed-into-its-run", "refused", SAMPLE_ID, "the sample renamed in its manifest "
      "(sample_id renamed-0001), reconstructed into its old run folder")
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    field_edit("sample_id", "renamed-0001")(sample)
    run = t.ctx.run_copy(t.dir / "run")
    t.protect(sample, strict=True)
    t.protect(run / "results", strict=True)
    t.protect_append(run / "audit" / "trail.jsonl", when="failed")
    t.main = t.cli("reconstruct", sample, "--out", run, "--config", CI_CONFIG)


@case("identity", "other-sample-into-run", "refused", SAMPLE_ID, "--out of sample A (sim-ci-0011) given to "
      "sample B (other-0002, another folder)")
def _(t: Trial) -> None:
    other = t.ctx.other_sample(t.dir / "other", SIX, "other-0002")
    run = t.ctx.run_copy(t.dir / "run")
    t.protect(other, strict=True)
    t.protect(run / "results", strict=True)
    t.protect_append(run / "audit" / "trail.jsonl", when="failed")
    t.main = t.cli("reconstruct", other, "--out", run, "--config", CI_CONFIG)


@case("identity", "trail-of-another-sample", "refused", SAMPLE_ID, "a fresh run folder holding only sample A's "
      "audit trail, given to sample B")
def _(t: Trial) -> None:
    other = t.ctx.other_sample(t.dir / "other", SIX, "other-0003")
    run = t.dir / "run"
    (run / "audit").mkdir(parents=True)
    shutil.copyfile(t.ctx.pristine / "ws" / "runs" / SAMPLE_ID / "audit" / "trail.jsonl", run / "audit" / "trail.jsonl")
    t.protect_append(run / "audit" / "trail.jsonl", when="failed")
    t.main = t.cli("reconstruct", other, "--out", run, "--config", CI_CONFIG)


@case("identity", "reused-folder-register", "refused", SAMPLE_ID, "the registered sample's folder reused for "
      "another sample (other passes, sample_id reused-0004); catalog register it")
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    sample = t.ctx.fresh_sample()
    shutil.rmtree(sample)
    t.ctx.other_sample(sample, ["top-L01", "top-L05", "bottom-L01", "bottom-L05"], "reused-0004")
    t.protect(ws / "runs")
    t.protect(ws / "catalog.sqlite", when="failed")
    t.main = t.cli("catalog", "register", sample, "--workspace", ws)


@case("identity", "renamed-then-batch", "refused", SAMPLE_ID, "the registered, reconstructed sample renamed in "
      "its manifest (renamed-0005); batch", timeout=300)
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    sample = t.ctx.fresh_sample()
    field_edit("sample_id", "renamed-0005")(sample)
    run = ws / "runs" / SAMPLE_ID
    t.protect(run / "results", strict=True)
    t.main = t.cli("batch", "--workspace", ws, "--config", CI_CONFIG)


@case("identity", "same-id-two-folders", "refused", SAMPLE_ID, "a copy of the registered sample in another "
      "folder (same sample_id); catalog register the copy")
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    copy = t.dir / "copy"
    shutil.copytree(t.ctx.pristine / "six", copy)
    t.protect(ws / "runs")
    t.protect(ws / "catalog.sqlite", when="failed")
    t.main = t.cli("catalog", "register", copy, "--workspace", ws)


@case("identity", "same-id-scan", "refused", "same id", "two sample folders with the same sample_id under "
      "one folder; catalog register the folder")
def _(t: Trial) -> None:
    root = t.dir / "samples"
    t.ctx.other_sample(root / "a", ["top-L02"])
    t.ctx.other_sample(root / "b", ["top-L03"])
    t.main = t.cli("catalog", "register", root, "--workspace", t.dir / "ws")


@case("identity", "moved-sample-register", ("refused", "ok"), SAMPLE_ID, "the registered sample moved to another "
      "folder; catalog register the new folder")
def _(t: Trial) -> None:
    ws = t.ctx.fresh_ws()
    sample = t.ctx.fresh_sample()
    moved = t.dir / "moved"
    shutil.move(str(sample), moved)
    t.protect(ws / "runs")
    t.protect(ws / "catalog.sqlite", when="failed")
    t.main = t.cli("catalog", "register", moved, "--workspace", ws)


@case("identity", "out-is-another-sample", "refused", "--out", "--out naming another sample's folder (a "
      "sample with its manifest and passes)", timeout=40)
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    other = t.ctx.other_sample(t.dir / "other", ["top-L02", "top-L03"], "other-0006")
    t.protect(other, strict=True)
    t.protect(sample, strict=True)
    t.main = t.cli("reconstruct", sample, "--out", other, "--config", CI_CONFIG)


def _settings_yaml(t: Trial, extra: str) -> Path:
    return write_yaml(t, "other-settings.yaml", CI_TEXT + extra)


@case("identity", "failed-run-other-settings", "refused", "registration", "a run with other settings fails "
      "(registration) after a finished one: results/ and the settings recorded with them must still agree")
def _(t: Trial) -> None:
    config = _settings_yaml(t, "registration:\n  min_common_targets: 40\n")
    sample = t.ctx.fresh_sample()
    run = t.ctx.run_copy(t.dir / "run")
    t.protect(sample, strict=True)
    t.protect(run / "results", strict=True)
    t.protect(_settings_file(run), label="the settings recorded with results/")
    t.protect_append(run / "audit" / "trail.jsonl")
    t.require("results/ and their settings agree", lambda: _results_settings_agree(run))
    t.main = t.cli("reconstruct", sample, "--out", run, "--config", config)


@case("identity", "killed-run-other-settings", "ok", None, "a run with other settings killed (kill -9) right "
      "after it started, after a finished one: results/ and the settings recorded with them must still agree")
def _(t: Trial) -> None:
    config = _settings_yaml(t, "")
    config.write_text(CI_TEXT.replace("poisson_depth: 8", "poisson_depth: 7"))
    sample = t.ctx.fresh_sample()
    run = t.ctx.run_copy(t.dir / "run")
    t.protect(sample, strict=True)
    t.protect(run / "results", strict=True)
    t.require("results/ and their settings agree", lambda: _results_settings_agree(run))
    trail = run / "audit" / "trail.jsonl"
    n = len(trail.read_bytes().splitlines())
    args = ("reconstruct", sample, "--out", run, "--config", config)
    started = time.monotonic()
    proc = t.ctx.cli.start(args)
    while time.monotonic() - started < 120 and proc.poll() is None and len(trail.read_bytes().splitlines()) <= n:
        time.sleep(0.05)
    kill_group(proc)
    t.main = t.ctx.cli.finish(proc, args, started, 30)
    t.verdict = ("ok", f"killed after the run started (exit {t.main.rc}); results/ and their settings agree")


@case("identity", "other-settings-finished", "ok", None, "a run with other settings (Poisson depth 7) finishes "
      "after a finished one: results/ and the settings recorded with them agree")
def _(t: Trial) -> None:
    config = _settings_yaml(t, "")
    config.write_text(CI_TEXT.replace("poisson_depth: 8", "poisson_depth: 7"))
    run = reconstruct_edited(t, config=config)
    t.require("results/ and their settings agree", lambda: _results_settings_agree(run))


# --- simulate and demo -------------------------------------------------------------------------

def _simulate_case(name: str, needle: str, what: str, args: Callable[[Trial], list], timeout: float = 120,
                   expect: str | tuple[str, ...] = "refused") -> None:
    @case("simulate", name, expect, needle, what, timeout=timeout)
    def run(t: Trial) -> None:
        t.main = t.cli("simulate", *args(t))


def _sim_config(text: str | bytes, name: str = "sim.yaml"):
    def args(t: Trial) -> list:
        return ["--preset", "ci", "--no-preview", "--config", write_yaml(t, name, text), t.dir / "sample"]

    return args


_simulate_case("bad-preset", "bogus", "--preset bogus", lambda t: ["--preset", "bogus", t.dir / "sample"])
_simulate_case("config-unknown-field", "sped_mm_s", "robot.sped_mm_s (misspelt)",
               _sim_config("robot:\n  sped_mm_s: 20\n"))
_simulate_case("config-out-of-range", "robot.speed_mm_s", "robot.speed_mm_s 0", _sim_config("robot:\n  speed_mm_s: 0\n"))
_simulate_case("config-wrong-type", "weld.treatment", "weld.treatment 5", _sim_config("weld:\n  treatment: 5\n"))
_simulate_case("config-bad-yaml", "sim.yaml", "unclosed bracket", _sim_config("robot: {speed_mm_s: 20\n"))
_simulate_case("config-list", "sim.yaml", "a YAML list", _sim_config("- robot\n"))
_simulate_case("config-not-utf8", "sim.yaml", "Latin-1 bytes in a comment",
               _sim_config("# Schweißnaht\nrobot:\n  speed_mm_s: 20\n".encode("latin-1")))
_simulate_case("config-python-tag", "sim.yaml", "a !!python/object/apply tag",
               _sim_config("robot: !!python/object/apply:os.system ['touch SENTINEL']\n"))
_simulate_case("config-reconstruction", "merge", "a reconstruction settings file given to simulate",
               _sim_config(CI_TEXT))
_simulate_case("config-missing", "nope.yaml", "--config naming a missing file",
               lambda t: ["--preset", "ci", "--no-preview", "--config", t.dir / "nope.yaml", t.dir / "sample"])
_simulate_case("pace-word", "--pace", "--pace fast", lambda t: ["--preset", "ci", "--pace", "fast", t.dir / "s"])
_simulate_case("pace-zero", "--pace", "--pace x0", lambda t: ["--preset", "ci", "--pace", "x0", t.dir / "s"])
_simulate_case("pace-negative", "--pace", "--pace x-5", lambda t: ["--preset", "ci", "--pace", "x-5", t.dir / "s"])
_simulate_case("pace-empty", "--pace", "--pace '' (an unset shell variable)",
               lambda t: ["--preset", "ci", "--no-preview", "--pace", "", t.dir / "s"])
_simulate_case("seed-negative", "seed", "--seed -1", lambda t: ["--preset", "ci", "--no-preview", "--seed", "-1",
                                                                t.dir / "s"])
_simulate_case("sample-id-path", "sample_id", "--sample-id ../../evil",
               lambda t: ["--preset", "ci", "--no-preview", "--sample-id", "../../evil", t.dir / "s"])


@case("simulate", "out-exists", "refused", "existing", "OUT_DIR an existing folder with someone's files")
def _(t: Trial) -> None:
    (t.dir / "existing").mkdir()
    (t.dir / "existing" / "keep.txt").write_text("keep me\n")
    t.protect(t.dir / "existing", strict=True)
    t.main = t.cli("simulate", "--preset", "ci", "--no-preview", t.dir / "existing")


@case("simulate", "out-is-file", "refused", "existing.txt", "OUT_DIR an existing file")
def _(t: Trial) -> None:
    (t.dir / "existing.txt").write_text("keep me\n")
    t.protect(t.dir / "existing.txt")
    t.main = t.cli("simulate", "--preset", "ci", "--no-preview", t.dir / "existing.txt")


@case("simulate", "out-under-file", "refused", "notes.txt", "OUT_DIR under an existing file (refused before the "
      "simulation, not after)", timeout=120)
def _(t: Trial) -> None:
    (t.dir / "notes.txt").write_text("keep me\n")
    t.protect(t.dir / "notes.txt")
    t.main = t.cli("simulate", "--preset", "ci", "--no-preview", t.dir / "notes.txt" / "sample")
    if t.main.rc != 0 and t.main.seconds > 15:
        t.notes.append(f"refused only after {t.main.seconds:.0f} s of simulation")


@case("simulate", "out-read-only", "refused", "readonly-disk", "OUT_DIR on a read-only disk", timeout=120)
def _(t: Trial) -> None:
    with read_only(t.dir / "readonly-disk"):
        t.main = t.cli("simulate", "--preset", "ci", "--no-preview", t.dir / "readonly-disk" / "sample")
    if t.main.rc != 0 and t.main.seconds > 15:
        t.notes.append(f"refused only after {t.main.seconds:.0f} s of simulation")


@case("simulate", "demo-out-is-file", "refused", "demo.txt", "demo --out naming a file", timeout=120)
def _(t: Trial) -> None:
    (t.dir / "demo.txt").write_text("keep me\n")
    t.protect(t.dir / "demo.txt")
    t.main = t.cli("demo", "--out", t.dir / "demo.txt")


@case("simulate", "demo-sample-empty", "refused", "manifest.json", "demo --out DIR where DIR/sample is an empty "
      "folder (a demo interrupted before)")
def _(t: Trial) -> None:
    (t.dir / "demo" / "sample").mkdir(parents=True)
    t.main = t.cli("demo", "--out", t.dir / "demo")


@case("simulate", "demo-sample-is-file", "refused", "demo/sample", "demo --out DIR where DIR/sample is a file")
def _(t: Trial) -> None:
    (t.dir / "demo").mkdir()
    (t.dir / "demo" / "sample").write_text("x\n")
    t.protect(t.dir / "demo" / "sample")
    t.main = t.cli("demo", "--out", t.dir / "demo")


@case("simulate", "demo-reconstruction-is-file", "refused", "reconstruction", "demo --out DIR where "
      "DIR/reconstruction is a file")
def _(t: Trial) -> None:
    (t.dir / "demo").mkdir()
    t.ctx.prepare()
    shutil.copytree(t.ctx.pristine / "six", t.dir / "demo" / "sample")
    (t.dir / "demo" / "reconstruction").write_text("x\n")
    t.protect(t.dir / "demo")
    t.main = t.cli("demo", "--out", t.dir / "demo")


# python tags in the simulation config must not run anything either
for _c in CASES:
    if _c.id == "simulate/config-python-tag":
        _inner = _c.fn

        def _guarded(t: Trial, inner=_inner) -> None:
            t.require("no command run from the YAML", lambda: ["SENTINEL: a command in the YAML ran"]
                      if (t.ctx.cli.cwd / "SENTINEL").exists() else [])
            inner(t)

        _c.fn = _guarded


# --- the newer doors (issue 28): imports, files a description names, resources, weld evidence ----

CELL_EXAMPLE = REPO / "tests" / "data" / "cell"
SECRET = "SECRET-OUTSIDE-THE-FOLDER"


def _cell(t: Trial) -> Path:
    """A copy of the example cell logs (tests/data/cell), a file beside it that must never be read."""
    cell = t.dir / "cell"
    shutil.copytree(CELL_EXAMPLE, cell, ignore=shutil.ignore_patterns("README.md"))
    (t.dir / "secret.csv").write_text(f"{SECRET},1,2,3\n")
    return cell


def _cell_yaml(cell: Path, fn) -> None:
    import yaml

    raw = yaml.safe_load((cell / "CELL.yaml").read_text())
    fn(raw)
    (cell / "CELL.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))


def _import(t: Trial, cell: Path) -> None:
    t.protect(cell)
    t.main = t.cli("import", cell / "CELL.yaml", t.dir / "out" / "sample")
    if SECRET in t.main.terminal or "root:" in t.main.terminal:
        t.verdict = ("unclear", "a file outside the folder was read and echoed: " + t.main.first())
    elif (t.dir / "out").exists() and any((t.dir / "out").iterdir()):
        t.verdict = ("damaged", f"the refused import left {sorted(p.name for p in (t.dir / 'out').iterdir())}")


def _cell_case(name: str, needle: str, what: str, spoil) -> None:
    @case("doors", name, "refused", needle, what)
    def run(t: Trial) -> None:
        cell = _cell(t)
        spoil(cell)
        _import(t, cell)


def _first_profiles(value):
    return lambda raw: raw["setups"][0]["passes"][0].update(profiles=value)


def _link_out(cell: Path) -> None:
    (cell / "profiles" / "top-A.csv").unlink()
    (cell / "profiles" / "top-A.csv").symlink_to(cell.parent / "secret.csv")


def _fifo(cell: Path) -> None:
    (cell / "profiles" / "top-A.csv").unlink()
    os.mkfifo(cell / "profiles" / "top-A.csv")


def _far_pose(cell: Path) -> None:
    path = cell / "poses" / "top-A.txt"
    lines = path.read_text().splitlines()
    fields = lines[2].split()
    fields[1] = "1e300"
    lines[2] = " ".join(fields)
    path.write_text("\n".join(lines) + "\n")


def _no_return(cell: Path) -> None:
    path = cell / "profiles" / "top-A.csv"
    path.write_text("".join(line.split(",")[0] + ",0,0,0" * 8 + "\n" for line in path.read_text().splitlines()))


def _alias_bomb(cell: Path) -> None:
    bomb = ['l0: &l0 ["x","x","x","x","x","x","x","x","x"]']
    bomb += [f"l{k}: &l{k} [{', '.join([f'*l{k - 1}'] * 9)}]" for k in range(1, 9)]
    (cell / "CELL.yaml").write_text("\n".join(bomb) + "\n" + (cell / "CELL.yaml").read_text())


def _gz_zeros(cell: Path) -> None:
    import gzip

    with gzip.open(cell / "profiles" / "top-B.csv.gz", "wb", compresslevel=1) as handle:
        for _ in range(64):
            handle.write(b"\0" * (1 << 20))


for _name, _needle, _what, _spoil in [
    ("cell-climbing", "../secret.csv", "CELL.yaml names a profile file '../secret.csv' beside the cell folder",
     lambda c: _cell_yaml(c, _first_profiles("../secret.csv"))),
    ("cell-passwd", "climbs out", "CELL.yaml names 'profiles/../../../../../../etc/passwd' as a profile file",
     lambda c: _cell_yaml(c, _first_profiles("profiles/../../../../../../etc/passwd"))),
    ("cell-symlink-out", "symbolic link", "a profile file that is a link to a file outside the folder", _link_out),
    ("cell-fifo", "FIFO", "a profile file that is a named pipe (reading it would block)", _fifo),
    ("cell-pose-1e300", "1e+300", "a pose log with a coordinate of 1e300 mm", _far_pose),
    ("cell-time-offset-nan", "time_offset_s", "time_offset_s: .nan",
     lambda c: _cell_yaml(c, lambda raw: raw.update(time_offset_s=float("nan")))),
    ("cell-profiles-twice", "profile file", "the same profile file listed for two passes",
     lambda c: _cell_yaml(c, lambda raw: raw["setups"][0]["passes"][1].update(profiles="profiles/top-A.csv"))),
    ("cell-no-return", "no-return", "a pass whose every profile is 'no return'", _no_return),
    ("cell-alias-bomb", "aliases", "a CELL.yaml with nested aliases expanding to 490 million values", _alias_bomb),
    ("cell-gz-zeros", "longer than", "a profile .gz of 64 MiB of zeros (one endless line)", _gz_zeros),
]:
    _cell_case(_name, _needle, _what, _spoil)


def _scans_import(t: Trial, files: list[Path], *extra) -> None:
    for f in files:
        t.protect(f)
    t.main = t.cli("import-scans", "--units", "mm", *extra, t.dir / "imported", *files)
    if t.main.rc != 0 and (t.dir / "imported").exists():
        t.verdict = ("damaged", "the refused import left its folder behind")


def _ply(path: Path, n: int = 500, claim: int | None = None, text: bool = False) -> Path:
    import numpy as np
    import plyfile

    rng = np.random.default_rng(1)
    v = np.zeros(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = rng.uniform(0, 50, (3, n))
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")], text=text).write(str(path))
    if claim is not None:
        data = path.read_bytes()
        path.write_bytes(data.replace(f"element vertex {n}".encode(), f"element vertex {claim}".encode(), 1))
    return path


@case("doors", "ply-header-short", "refused", "element vertex 400", "a PLY whose header counts 400 of its 500 points")
def _(t: Trial) -> None:
    _scans_import(t, [_ply(t.dir / "scan.ply", claim=400)])


@case("doors", "pcd-header-long", "refused", "POINTS 900", "a PCD whose header claims 900 of its 500 points")
def _(t: Trial) -> None:
    import numpy as np
    import pypcd4

    pc = pypcd4.PointCloud.from_xyz_points(np.random.default_rng(2).uniform(0, 50, (500, 3)).astype(np.float32))
    pc.save(t.dir / "scan.pcd", encoding=pypcd4.Encoding.BINARY)
    data = (t.dir / "scan.pcd").read_bytes().replace(b"POINTS 500", b"POINTS 900", 1).replace(b"WIDTH 500", b"WIDTH 900", 1)
    (t.dir / "scan.pcd").write_bytes(data)
    _scans_import(t, [t.dir / "scan.pcd"])


@case("doors", "xyz-gz-repeated", "refused", "decompresses", "a .xyz.gz of one line repeated 4 million times")
def _(t: Trial) -> None:
    import gzip

    with gzip.open(t.dir / "scan.xyz.gz", "wb") as handle:
        block = b"1.000 2.000 3.000\n" * 100_000
        for _ in range(40):
            handle.write(block)
    _scans_import(t, [t.dir / "scan.xyz.gz"])


@case("doors", "conf-far", "refused", "translation", "a .conf pose with a translation of 1e30")
def _(t: Trial) -> None:
    scan = _ply(t.dir / "a.ply")
    (t.dir / "scans.conf").write_text("bmesh a.ply 1e30 0 0 0 0 0 1\n")
    _scans_import(t, [scan], "--poses", t.dir / "scans.conf")



@case("doors", "scan-fifo", "refused", "FIFO", "measure-weld on a named pipe")
def _(t: Trial) -> None:
    os.mkfifo(t.dir / "scan.xyz")
    t.main = t.cli("measure-weld", t.dir / "scan.xyz", "--units", "mm", "--out", t.dir / "out", timeout=60)
    if (t.dir / "out").exists():
        t.verdict = ("damaged", "the refused measurement left its folder behind")


@case("doors", "dask-not-a-scheduler", "refused", "not a Dask scheduler",
      "--dask at a port where an HTTP server listens")
def _(t: Trial) -> None:
    sample = t.ctx.fresh_sample()
    server = subprocess.Popen([sys.executable, "-m", "http.server", "0", "--bind", "127.0.0.1"], cwd=t.dir,
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, start_new_session=True, text=True)
    try:
        line = server.stdout.readline()  # "Serving HTTP on 127.0.0.1 port N ..."
        port = int(line.split(" port ")[1].split()[0])
        t.main = t.cli("reconstruct", sample, "--out", t.dir / "run", "--config", CI_CONFIG, "--dask",
                       f"tcp://127.0.0.1:{port}", timeout=120)
    finally:
        kill_group(server)
        server.wait()


def _config_case(name: str, needle: str, what: str, text: str) -> None:
    @case("doors", name, "refused", needle, what)
    def run(t: Trial) -> None:
        sample = t.ctx.fresh_sample()
        t.protect(sample, strict=True)
        config = write_yaml(t, "settings.yaml", text)
        t.main = t.cli("reconstruct", sample, "--out", t.dir / "run", "--config", config, timeout=120)
        if (t.dir / "run").exists():
            t.verdict = ("damaged", "the refused run left its folder behind")


_config_case("volume-size-tiny", "volume.size_mm", "volume.size_mm 0.01 (meshed for minutes before)",
             "volume:\n  size_mm: 0.01\n")
_config_case("weld-step-long", "section_step_mm", "weld.section_step_mm longer than the weld lines",
             "weld:\n  section_step_mm: 80\n")
_config_case("acceptance-inf", "finite", "an acceptance limit of .inf (written as Infinity into report.json before)",
             "weld:\n  acceptance:\n    rules:\n      - {joint: double-sided butt, treatment: as-welded, source: mine, "
             "toe_radius_mm: {min: 0.0, max: .inf}}\n")


@case("doors", "weld-lines-off-the-weld", "flagged", "no weld found",
      "the manifest's weld lines placed 60 mm off the weld, on the plate (stickers there)", timeout=400)
def _(t: Trial) -> None:
    def move(m: dict) -> None:
        for line in m["weld"]["weld_lines"]:
            for p in line["points_mm"]:
                p[0] = 60.0

    sample = t.ctx.fresh_sample()
    edit_manifest(move)(sample)
    t.main = t.cli("reconstruct", sample, "--out", t.dir / "run", "--config", CI_CONFIG, timeout=400)
    report = t.dir / "run" / "results" / "report.json"
    if report.is_file():
        weld = json.loads(report.read_text())["weld"]
        if weld.get("sections_measured"):
            t.verdict = ("silent", f"{weld['sections_measured']} sections measured off the weld: {weld.get('verdict')}")



def _declared_as(t: Trial, sample: Path, specimen: dict) -> None:
    """``sample``'s manifest declaring ``specimen``, its weld joint "other" (the kind's own joints
    differ); the sample protected, the run's report read for the check "part as declared"."""
    def declare(m: dict) -> None:
        m["specimen"] = specimen
        m["weld"]["joint"] = "other"

    edit_manifest(declare)(sample)
    t.protect(sample, strict=True)
    t.main = t.cli("reconstruct", sample, "--out", t.dir / "run", "--config", CI_CONFIG, timeout=600)
    report = t.dir / "run" / "results" / "report.json"
    if report.is_file():
        checks = [c for c in json.loads(report.read_text())["checks"] if c["check"] == "part as declared"]
        if not checks or checks[0]["result"] == "ok":
            t.verdict = ("silent", "the report's check 'part as declared': " + (checks[0]["what"] if checks else
                                                                               "missing"))


@case("doors", "tjoint-declared-plate", "flagged", "declared 12 mm",
      "the T-joint (a 60 mm stem on a 12 mm base) declared as a 260 x 120 x 12 mm plate", timeout=900)
def _(t: Trial) -> None:
    sample = t.dir / "tjoint"
    made = t.cli("simulate", "--preset", "tjoint", "--no-preview", sample, timeout=600)
    if made.rc != 0:
        raise Skip(f"could not simulate the tjoint preset: {made.first()}")
    shutil.rmtree(sample / "truth")
    _declared_as(t, sample, {"kind": "plate", "length_mm": 260.0, "width_mm": 120.0, "thickness_mm": 12.0})


@case("doors", "dog-bone-declared-thinner", "flagged", "declared 12 mm thick",
      "the 20 mm dog-bone declared as a 12 mm plate of its length and width", timeout=600)
def _(t: Trial) -> None:
    _declared_as(t, t.ctx.fresh_sample(), {"kind": "plate", "length_mm": 240.0, "width_mm": 60.0,
                                            "thickness_mm": 12.0})


@case("doors", "memory-cgroup-small", "refused", "not enough memory",
      "reconstruct in a memory cgroup of 400 MB (died with a shared-library or libgomp message before)", timeout=120)
def _(t: Trial) -> None:
    cgroups = Path("/sys/fs/cgroup/memory")
    if not os.access(cgroups, os.W_OK):
        raise Skip("needs a writable cgroup v1 memory controller (root)")
    sample = t.ctx.fresh_sample()
    t.protect(sample, strict=True)
    group = cgroups / f"weldrecon-adversarial-{os.getpid()}"
    group.mkdir()
    try:
        (group / "memory.limit_in_bytes").write_text(str(400 * 2 ** 20))
        args = ("reconstruct", sample, "--out", t.dir / "run", "--config", CI_CONFIG)
        line = " ".join(f"'{a}'" for a in t.ctx.cli.argv(args))
        started = time.monotonic()
        proc = subprocess.Popen(["sh", "-c", f"echo $$ > {group / 'cgroup.procs'} && exec {line}"], cwd=t.ctx.cli.cwd,
                                env=t.ctx.cli.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                start_new_session=True)
        t.main = t.ctx.cli.finish(proc, args, started, t.case.timeout)
    finally:
        group.rmdir()
    if (t.dir / "run").exists():
        t.verdict = ("damaged", "the refused run left its folder behind")


# ------------------------------------------------------------------------------------------------
# running, the table, the tally


@contextlib.contextmanager
def prefect_api(root: Path, env: dict[str, str]) -> Iterator[str | None]:
    """One Prefect API server for every flow run of the benchmark (saves each run starting its
    own); stopped at the end."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log = open(root / "prefect-server.log", "wb")
    server = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port",
                               str(port)], env={**env, "PREFECT_UI_ENABLED": "false"}, stdout=log, stderr=log,
                              start_new_session=True, cwd=root)
    url = f"http://127.0.0.1:{port}/api"
    try:
        deadline = time.monotonic() + 120
        while True:
            with contextlib.suppress(OSError):
                with urllib.request.urlopen(url + "/health", timeout=2) as answer:
                    if answer.status == 200:
                        break
            if server.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"adversarial: the Prefect API server did not start (see {root / 'prefect-server.log'})")
            time.sleep(0.5)
        yield url
    finally:
        kill_group(server)
        server.wait()
        log.close()


def selected(only: list[str] | None, everything: bool) -> list[Case]:
    """The cases to run: the default set (with ``everything``, the extended ones too), narrowed
    to groups named in ``only``; a case named there by its id runs whatever its set."""
    wanted = [w for part in only or [] for w in part.split(",") if w]
    unknown = [w for w in wanted if w not in GROUPS and not any(c.id == w for c in CASES)]
    if unknown:
        raise SystemExit(f"adversarial: unknown group or case {unknown}; groups: {', '.join(GROUPS)} (--list)")
    if missing := sorted(EXTENDED - {c.id for c in CASES}):
        raise SystemExit(f"adversarial: EXTENDED names no case: {missing}")
    return [c for c in CASES if c.id in wanted
            or ((not wanted or c.group in wanted) and (everything or c.id not in EXTENDED))]


def run_case(ctx: Context, c: Case, keep: bool) -> tuple[str, str, float]:
    folder = ctx.cases / c.id.replace("/", "-")
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for stale in (ctx.cli.cwd / "SENTINEL",):
        stale.unlink(missing_ok=True)
    trial = Trial(ctx, c, folder, needle=c.needle)
    prepared = ctx.prep_seconds
    t0 = time.monotonic()
    try:
        c.fn(trial)
        outcome, message = judge(trial)
    except Skip as exc:
        outcome, message = "skipped", str(exc)
    except Exception as exc:  # noqa: BLE001 - a broken case is reported, the others go on
        outcome, message = "unclear", f"the case itself failed: {type(exc).__name__}: {exc}"
    seconds = time.monotonic() - t0 - (ctx.prep_seconds - prepared)  # the one-off preparation is not the case's
    if not keep:
        shutil.rmtree(folder, ignore_errors=True)
    return outcome, message, seconds


def md(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ").strip()


def tally_line(counts: Counter, n: int) -> str:
    line = (f"adversarial: {n} cases: {counts['refused']} refused, {counts['flagged']} flagged, {counts['ok']} ok, "
            f"{counts['unclear']} unclear, {counts['traceback']} traceback, {counts['silent']} silent, "
            f"{counts['damaged']} damaged")
    return line + (f", {counts['skipped']} skipped" if counts["skipped"] else "")


def write_table(path: Path, rows: list[tuple[Case, str, str, float]], counts: Counter, wall: float, api: str,
                prep: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip() or "?"
    dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    out = ["# weldrecon adversarial benchmark", "",
           f"Run of {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')} on {REPO} at {commit}"
           f"{' (with uncommitted changes)' if dirty else ''}; {len(rows)} cases in {wall / 60:.1f} min "
           f"(of which {prep:.0f} s preparing: the ci sample simulated, its 6-pass subset reconstructed); "
           f"Prefect API: {api}. `python bench/adversarial.py` (see its docstring for the outcomes).", "",
           "`" + tally_line(counts, len(rows)) + "`", "",
           "| group | count | " + " | ".join(OUTCOMES) + " |", "|---|---|" + "---|" * len(OUTCOMES)]
    for group in GROUPS:
        g = Counter(o for c, o, _, _ in rows if c.group == group)
        if sum(g.values()):
            out.append(f"| {group} | {sum(g.values())} | " + " | ".join(str(g[o]) for o in OUTCOMES) + " |")
    out += ["", "| case | group | expected | outcome | message (first line) | what | s |",
            "|---|---|---|---|---|---|---|"]
    for c, outcome, message, seconds in rows:
        shown = f"**{outcome}**" if outcome not in ("refused", "flagged", "ok") else outcome
        out.append(f"| {c.name} | {c.group} | {' or '.join(c.expect)}{f' (names `{md(c.needle)}`)' if c.needle else ''} "
                   f"| {shown} | {md(message)[:400]} | {md(c.what)} | {seconds:.0f} |")
    path.write_text("\n".join(out) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", action="append", metavar="GROUP[,GROUP/CASE]",
                        help=f"run only these groups or cases ({', '.join(GROUPS)})")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    parser.add_argument("--all", action="store_true", help="the extended cases too (about twice as long)")
    parser.add_argument("--out", metavar="DIR", help="scratch folder (default: a temporary folder, removed at the end)")
    parser.add_argument("--keep", action="store_true", help="keep the scratch folder (and every case's folder)")
    parser.add_argument("--table", metavar="FILE", default=str(RESULTS_MD),
                        help=f"where the Markdown table goes (default {RESULTS_MD.relative_to(REPO)})")
    parser.add_argument("--temporary-api", action="store_true",
                        help="let each flow run start its own temporary Prefect API server (slower)")
    args = parser.parse_args(argv)
    cases = selected(args.only, args.all)
    if args.list:
        for c in cases:
            print(f"{c.id:<48} {'/'.join(c.expect):<16} {c.needle or '-':<22} {c.what}"
                  f"{' (extended)' if c.id in EXTENDED else ''}")
        counts = Counter(c.group for c in cases)
        print(f"{len(cases)} cases: " + ", ".join(f"{g} {counts[g]}" for g in GROUPS if counts[g]))
        return 0
    started = time.monotonic()
    made_root = args.out is None
    root = Path(args.out or tempfile.mkdtemp(prefix="weldrecon-adversarial-")).resolve()
    root.mkdir(parents=True, exist_ok=True)
    rows: list[tuple[Case, str, str, float]] = []
    counts: Counter = Counter()
    api_label = "a temporary server per run"
    ctx: Context | None = None
    try:
        with contextlib.ExitStack() as stack:
            base_cli = Cli(root, None)
            api = None if args.temporary_api else stack.enter_context(prefect_api(root, base_cli.env))
            if api:
                api_label = "one shared server"
            ctx = Context(root, Cli(root, api))
            for number, c in enumerate(cases, start=1):
                outcome, message, seconds = run_case(ctx, c, args.keep)
                counts[outcome] += 1
                rows.append((c, outcome, message, seconds))
                print(f"[{time.monotonic() - started:6.0f} s] {number:>3}/{len(cases)} {c.id:<46} {outcome:<9} "
                      f"{seconds:5.1f} s  {message[:150]}", flush=True)
    finally:
        if rows:
            write_table(Path(args.table), rows, counts, time.monotonic() - started, api_label,
                        ctx.prep_seconds if ctx else 0.0)
        if made_root and not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    print(f"table: {args.table}")
    print(tally_line(counts, len(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
