"""Failures the command line meets in a lab (issue 10, item 6): one clear line per problem that
names the file, pass or field and what was expected, no traceback on the terminal (it goes to a
log file), and nothing that already existed damaged."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from data_catalog.audit import read_trail
from data_catalog.hashing import sha256_tree
from tests.conftest import SIX
from tests.flows.cli import run_cli, weldrecon
from tests.flows.samples import QUICK_CONFIG, copy_sample

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = str(REPO / "deploy" / "configs" / "ci.yaml")


def _problems(stderr: str) -> list[str]:
    """The terminal's lines that are not progress ("[  1.2 s] ...")."""
    return [line for line in stderr.splitlines() if line.strip() and not line.startswith("[")]


def _mount_tmpfs(where: Path, size: str) -> None:
    where.mkdir(parents=True)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")


def test_a_damaged_catalog_is_named_and_left_as_it_was(tmp_path):
    workspace = tmp_path / "ws"
    workspace.mkdir()
    (workspace / "catalog.sqlite").write_bytes(b"this is not an SQLite database" * 100)
    before = (workspace / "catalog.sqlite").read_bytes()
    for args in (["catalog", "list"], ["catalog", "show", "x"], ["catalog", "register", str(tmp_path)],
                 ["batch"], ["audit", "verify", "some-sample"]):
        done = run_cli(*args, "--workspace", str(workspace))
        assert done.returncode == 2, (args, done.stderr)
        problems = _problems(done.stderr)
        assert problems[0] == (f"weldrecon {args[0]}: error: catalog {workspace / 'catalog.sqlite'}: file is not a "
                               "database; it is damaged or not a catalog: move it aside (sample and run folders are "
                               "untouched) and register the samples again"), (args, done.stderr)
        assert "Traceback" not in done.stderr and len(problems) <= 2, (args, done.stderr)
    assert (workspace / "catalog.sqlite").read_bytes() == before


def test_register_names_what_is_not_a_sample_and_registers_the_rest(ci_sample, tmp_path):
    workspace = tmp_path / "ws"
    a_file = tmp_path / "notes.txt"
    a_file.write_text("not a sample")
    folder_manifest = copy_sample(ci_sample, tmp_path / "samples" / "odd", ["top-L01"])
    (folder_manifest / "manifest.json").unlink()
    (folder_manifest / "manifest.json").mkdir()  # a manifest that is a folder
    broken = tmp_path / "samples" / "broken"
    broken.mkdir()
    (broken / "manifest.json").write_bytes(b"\xff\xfe not json")
    good = copy_sample(ci_sample, tmp_path / "samples" / "good", ["top-L01"])
    empty = tmp_path / "empty"
    empty.mkdir()
    done = run_cli("catalog", "register", str(a_file), str(tmp_path / "samples"), str(empty), str(tmp_path / "gone"),
                   "--workspace", str(workspace))
    assert done.returncode == 2
    assert done.stdout.splitlines() == ["sim-ci-0011: new"]  # the good sample, despite the others
    lines = _problems(done.stderr)
    assert lines == [
        f"not registered: {a_file}: is a file, neither a sample folder (with manifest.json) nor a folder of "
        "sample folders",
        f"not registered: {broken}: {broken / 'manifest.json'}: not UTF-8 text at byte 0, expected the sample's manifest file (JSON)",
        f"not registered: {folder_manifest}: {folder_manifest / 'manifest.json'}: is a folder, expected the "
        "sample's manifest file (JSON)",
        f"not registered: {empty}: no sample folder (one holding manifest.json) in it or under it",
        f"not registered: {tmp_path / 'gone'}: does not exist",
    ]
    assert (good / "manifest.json").is_file()
    done = run_cli("reconstruct", str(folder_manifest), "--out", str(tmp_path / "run"))
    assert done.returncode == 2 and _problems(done.stderr) == [
        f"weldrecon reconstruct: error: {folder_manifest / 'manifest.json'}: is a folder, expected the sample's "
        "manifest file (JSON)"]
    assert not (tmp_path / "run").exists()


def test_a_batch_names_a_deleted_sample_and_a_malformed_one_instead_of_up_to_date(ci_sample, tmp_path):
    workspace = tmp_path / "ws"
    samples = tmp_path / "samples"
    sample = copy_sample(ci_sample, samples / "one", ["top-L01"])
    assert run_cli("catalog", "register", str(sample), "--workspace", str(workspace)).returncode == 0
    shutil.rmtree(sample)  # deleted after it was registered
    malformed = samples / "two"
    malformed.mkdir()
    (malformed / "manifest.json").write_text('{"sample_id": "x"}')
    done = weldrecon("batch", "--samples", str(samples), "--workspace", str(workspace))
    assert done.returncode == 1, done.stderr
    out = done.stdout.splitlines()
    assert out[0] == "done: none"
    assert out[1].startswith(f"FAILED sim-ci-0011 at register: cannot read the sample folder {sample}: ")
    assert out[2].startswith(f"NOT REGISTERED {malformed}: {malformed / 'manifest.json'}: ")
    assert out[-2] == "up to date: none"  # each missing manifest field on its own line before
    assert out[-1] == f"index: {workspace.resolve() / 'index.html'}"  # the batch index page, rewritten
    shown = run_cli("catalog", "show", "sim-ci-0011", "--workspace", str(workspace)).stdout
    assert "state       failed at stage register" in shown


def test_unreachable_dask_scheduler_is_named_before_any_work(ci_sample, tmp_path):
    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01"])
    done = run_cli("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--dask", "tcp://127.0.0.1:9")
    assert done.returncode == 2
    assert _problems(done.stderr) == [
        "weldrecon reconstruct: error: dask 'tcp://127.0.0.1:9': no Dask scheduler answers at 127.0.0.1:9 "
        "(Connection refused); start one (dask scheduler) or give local:N for worker processes here"]
    assert not (tmp_path / "run").exists()


def test_a_server_that_is_not_a_dask_scheduler_is_named_before_any_work(ci_sample, tmp_path):
    """Something listens at the address (here a server that answers every connection with an HTTP
    error), but not Dask: a client would hang, or take its first bytes for a frame length of exabytes."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def answer():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            conn.sendall(b"HTTP/1.0 400 Bad Request\r\n\r\n")
            conn.close()

    threading.Thread(target=answer, daemon=True).start()
    try:
        sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01"])
        done = run_cli("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--dask", f"tcp://127.0.0.1:{port}")
    finally:
        server.close()
    assert done.returncode == 2
    [line] = _problems(done.stderr)
    assert line.startswith(f"weldrecon reconstruct: error: dask 'tcp://127.0.0.1:{port}': something answers at "
                           f"127.0.0.1:{port}, but not a Dask scheduler ("), line
    assert line.endswith("expected the address of one (dask scheduler prints it) or local:N"), line
    assert not (tmp_path / "run").exists()


def test_a_volume_size_that_would_take_hours_is_refused_before_any_work(ci_sample, tmp_path):
    """volume.size_mm 0.01 passed validation and meshed for minutes (issue 28): refused up front, with the
    least count of tetrahedra it asks for."""
    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01"])
    config = tmp_path / "fine.yaml"
    config.write_text("volume:\n  size_mm: 0.01\n")
    done = run_cli("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--config", str(config))
    assert done.returncode == 2
    [line] = _problems(done.stderr)
    assert line.startswith("weldrecon reconstruct: error: volume.size_mm 0.01: the part (") and "tetrahedra" in line, line
    assert line.endswith("are graded finer by weld_size_mm and toe_size_mm on their own)"), line
    assert not (tmp_path / "run").exists()


def test_a_weld_section_step_longer_than_the_weld_is_refused_before_any_work(ci_sample, tmp_path):
    """It gave "0 of 0 sections measured, fail" after the whole run (issue 28)."""
    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01"])
    config = tmp_path / "step.yaml"
    config.write_text("weld:\n  section_step_mm: 80\n")
    done = run_cli("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--config", str(config))
    assert done.returncode == 2
    assert _problems(done.stderr) == [
        "weldrecon reconstruct: error: weld.section_step_mm 80: longer than the weld lines less the end margins "
        "(weld.end_margin_mm 2 at each end): top 60 mm, bottom 60 mm; expected a step that gives every line its sections"]
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("value", [".inf", ".nan", "-.inf"])
def test_a_non_finite_acceptance_limit_is_refused_naming_the_field(tmp_path, value):
    """A limit of .inf passed and was written into report.json as Infinity, which JSON parsers reject."""
    config = tmp_path / "limits.yaml"
    config.write_text("weld:\n  acceptance:\n    rules:\n      - {joint: double-sided butt, treatment: as-welded, "
                      f"source: mine, toe_radius_mm: {{min: 0.0, max: {value}}}}}\n")
    from flows.preflight import load_config

    with pytest.raises(ValueError) as caught:
        load_config(config)
    assert str(caught.value) == (f"{config}: invalid reconstruction config:\n"
                                 "  weld.acceptance.rules.0.toe_radius_mm.max: Input should be a finite number")


def test_a_dask_scheduler_passes_the_check(collected_after):
    from distributed import LocalCluster

    from flows.preflight import check_dask_scheduler

    with LocalCluster(n_workers=1, processes=False, protocol="tcp://", dashboard_address=None) as cluster:
        check_dask_scheduler(cluster.scheduler_address)


@pytest.mark.parametrize("edit, message", [
    ("int32", r"pass top-L02: .*top-L02\.zarr/x_mm has dtype int32, expected float32 \(mm\)"),
    ("intensity", r"pass top-L02: .*top-L02\.zarr/intensity is 2000 at profile 3, column 7; expected 0\.\.1023"),
])
def test_pass_values_outside_the_format_are_named_not_reported_as_missing_stickers(ci_sample, tmp_path, edit,
                                                                                   message):
    import re

    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01", "top-L02"])
    store = sample / "passes" / "top-L02.zarr"
    group = zarr.open_group(str(store), mode="r+")
    if edit == "int32":  # what a converter writing micrometre integers leaves
        x = np.nan_to_num(group["x_mm"][...] * 1000).astype(np.int32)
        chunks = group["x_mm"].chunks
        del group["x_mm"]
        group.create_array("x_mm", data=x, chunks=chunks, config={"write_empty_chunks": True})
    else:  # a 12-bit sensor's intensities
        intensity = group["intensity"][...]
        intensity[3, 7] = 2000
        group["intensity"][...] = intensity
    manifest = json.loads((sample / "manifest.json").read_text())
    manifest["setups"][0]["passes"][1]["content_sha256"] = sha256_tree(store)
    (sample / "manifest.json").write_text(json.dumps(manifest))
    done = weldrecon("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--config", CI_CONFIG)
    assert done.returncode == 2
    assert any(re.search(message, line) for line in _problems(done.stderr)), done.stderr
    assert "no sticker" not in done.stderr and "Traceback" not in done.stderr


def test_a_read_only_place_for_the_default_run_folder_is_named(ci_sample, tmp_path):
    disk = tmp_path / "ro"
    _mount_tmpfs(disk, "16m")
    try:
        sample = copy_sample(ci_sample, disk / "s", ["top-L01"])
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        done = run_cli("reconstruct", str(sample))
        assert done.returncode == 2
        assert _problems(done.stderr) == [
            f"weldrecon reconstruct: error: --out {disk / 's-reconstruction'}: cannot create anything in {disk} "
            "(Read-only file system); give --out a folder you can write (without --out, the run folder is made beside "
            "the sample)"]
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def test_an_unexpected_error_is_one_line_and_its_traceback_goes_to_a_log(tmp_path, monkeypatch, capsys):
    import flows.cli
    import flows.cli.info

    def broken(args):
        raise TypeError("something the code did not expect")

    monkeypatch.setattr(flows.cli.info, "_cmd_stages", broken)
    monkeypatch.setenv("WELDRECON_LOG_DIR", str(tmp_path / "logs"))
    assert flows.cli.main(["stages"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == ("weldrecon stages: error: unexpected TypeError: something the code did not expect "
                      "(please report it with the log below)")
    log = Path(err[1].removeprefix("  (the details and the traceback: ").removesuffix(")"))
    assert log.parent == tmp_path / "logs" and len(err) == 2
    assert "Traceback" in log.read_text() and "something the code did not expect" in log.read_text()


def test_a_full_disk_is_named_nothing_half_written_is_trusted_and_the_run_recovers(ci_sample, six_run, tmp_path):
    """The run folder on an 8 MiB tmpfs: the denoise stage of some passes meets a full disk (its
    copy from the session's stage cache fails, then making it does). The terminal names the passes
    and the cause, the trail stays intact, and after space is freed the same command finishes,
    placing again what failed (from the stage cache: copied and verified, never the half-written
    folder) and reusing what was complete in the folder. Each run a process of its own, as a user
    runs it: run inside the test process, a build folder of the failed run was left at the end once
    in three suite runs (not pinned down; likely a pass's stage still running in its thread when
    the run failed, which a process's exit ends). The session's six-pass run is made first, so that
    the stage cache holds every stage this sample's runs copy."""
    sample = copy_sample(ci_sample, tmp_path / "s", SIX)
    disk = tmp_path / "disk"
    _mount_tmpfs(disk, "8m")
    try:
        run = disk / "run"
        done = run_cli("reconstruct", str(sample), "--out", str(run), "--config", QUICK_CONFIG)
        assert done.returncode == 2
        problems = _problems(done.stderr)
        assert problems[0].startswith("weldrecon reconstruct: error: stage denoise failed for ")
        assert all(line.startswith("  pass ") and line.endswith(": [Errno 28] No space left on device")
                   for line in problems[1:-1]) and len(problems) >= 3
        assert problems[-1].startswith("  (the details and the traceback: ")
        assert "Traceback" not in done.stderr
        assert not (run / "results").exists()
        verify = run_cli("audit", "verify", str(run))
        assert verify.returncode == 0 and "audit trail intact" in verify.stdout
        # space freed: enough for the whole run (its stage folders, the C3D10 model, the stress sections)
        subprocess.run(["mount", "-o", "remount,size=256m", str(disk)], check=True)
        done = run_cli("reconstruct", str(sample), "--out", str(run), "--config", QUICK_CONFIG)
        assert done.returncode == 0, done.stderr
        report = json.loads((run / "results" / "report.json").read_text())
        assert report["mesh"]["triangles"] > 10_000  # (this subset's mesh is open: 3 passes per side)
        trail = read_trail(run)
        second = max(k for k, e in enumerate(trail) if e["kind"] == "run-started")
        denoised = [e for e in trail[second:] if e["kind"] == "stage" and e["stage"] == "denoise"]
        reused = [bool(e.get("cached")) and "from_stage_cache" not in e for e in denoised]  # complete in the folder
        assert len(reused) == len(SIX) and 0 < sum(reused) < len(SIX)  # what failed was placed again
        verify = run_cli("audit", "verify", str(run))
        assert verify.returncode == 0 and "audit trail intact" in verify.stdout
        assert not list(run.rglob("*.partial")) and not list(run.rglob(".build-*"))
    finally:
        subprocess.run(["umount", str(disk)], check=False)


@pytest.mark.parametrize("edit, message", [
    ("poses-gone", r"pass top-L02 \(.*top-L02\.zarr\): the manifest says has_profile_poses true, but the store has no "
                   r"T_world_flange; expected both to agree"),
    ("times-in-ms", r"pass top-L02 \(.*top-L02\.zarr\): timestamp_s spans 20010\.7 s, but the manifest's duration_s "
                    r"is 20 s; expected seconds since the pass started"),
])
def test_a_pass_that_contradicts_its_manifest_entry_is_named(ci_sample, tmp_path, edit, message):
    """Logged poses that went missing (the nominal sweep would silently stand in for them) and
    profile times in the wrong unit are refused with the pass named, not run."""
    import re

    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01", "top-L02"])
    store = sample / "passes" / "top-L02.zarr"
    group = zarr.open_group(str(store), mode="r+")
    if edit == "poses-gone":
        del group["T_world_flange"]
    else:
        group["timestamp_s"][...] = group["timestamp_s"][...] * 1000
    manifest = json.loads((sample / "manifest.json").read_text())  # the exporter's hash, as it would write it
    manifest["setups"][0]["passes"][1]["content_sha256"] = sha256_tree(store)
    (sample / "manifest.json").write_text(json.dumps(manifest))
    done = weldrecon("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--config", CI_CONFIG)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert any(re.search(message, line) for line in _problems(done.stderr)), done.stderr


def _copy_pass(sample: Path, copied: str) -> None:
    """top-L03's store made a copy of top-L01's, its hash rewritten as an exporter would: the whole
    store relabelled (``store``), or only its profiles (``measurements``: times and intensities its own)."""
    store = sample / "passes" / "top-L03.zarr"
    if copied == "store":
        shutil.rmtree(store)
        shutil.copytree(sample / "passes" / "top-L01.zarr", store)
        zarr.open_group(str(store), mode="r+").attrs["pass_id"] = "top-L03"
    else:
        for name in ("x_mm", "z_mm"):
            shutil.rmtree(store / name)
            shutil.copytree(sample / "passes" / "top-L01.zarr" / name, store / name)
    manifest = json.loads((sample / "manifest.json").read_text())
    manifest["setups"][0]["passes"][2]["content_sha256"] = sha256_tree(store)
    (sample / "manifest.json").write_text(json.dumps(manifest))


_COPIED = ("pass top-L03 (setup top): its store passes/top-L03.zarr holds the same measurements, byte for byte, as "
           "pass top-L01 (setup top); a copy of another pass's store (relabelled or exported twice?): expected each "
           "pass its own scan")


def test_a_pass_store_that_is_a_copy_of_another_is_named_with_both_passes(ci_sample, tmp_path):
    """A store copied over another and relabelled: refused before any work, naming the copy and its
    original, not as a registration failure of unrelated passes; and a store whose profiles alone
    are another's (``data_catalog.manifests.check_passes_distinct``)."""
    from data_catalog.manifests import ManifestError, check_passes_distinct, load_manifest

    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01", "top-L02", "top-L03"])
    check_passes_distinct(sample, load_manifest(sample))
    _copy_pass(sample, "store")
    before = sha256_tree(sample)
    run = tmp_path / "run"
    done = weldrecon("reconstruct", str(sample), "--out", str(run), "--config", QUICK_CONFIG)
    assert done.returncode == 2 and _problems(done.stderr) == [f"weldrecon reconstruct: error: {_COPIED}"], done.stderr
    assert not run.exists() and sha256_tree(sample) == before
    other = copy_sample(ci_sample, tmp_path / "t", ["top-L01", "top-L02", "top-L03"])
    _copy_pass(other, "measurements")
    with pytest.raises(ManifestError) as caught:
        check_passes_distinct(other, load_manifest(other))
    assert str(caught.value) == _COPIED


def test_an_out_folder_of_other_files_and_a_bad_follow_timeout_are_refused_before_any_work(ci_sample, tmp_path):
    foreign = tmp_path / "thesis"
    foreign.mkdir()
    (foreign / "chapter1.tex").write_text("work of months")
    done = run_cli("reconstruct", str(ci_sample), "--out", str(foreign))
    assert done.returncode == 2 and _problems(done.stderr) == [
        f"weldrecon reconstruct: error: --out {foreign}: holds 1 thing(s) that are not a weldrecon run's (chapter1.tex) "
        "and no audit trail; give a new or empty folder, or an earlier run's folder"]
    assert sorted(p.name for p in foreign.iterdir()) == ["chapter1.tex"]
    done = run_cli("reconstruct", str(ci_sample), "--out", str(tmp_path / "run"), "--follow", "--follow-timeout", "-5")
    assert done.returncode == 2 and _problems(done.stderr) == [
        "weldrecon reconstruct: error: --follow-timeout -5: expected a number of seconds > 0"]
    assert not (tmp_path / "run").exists()


def test_a_refusal_comes_before_prefect_and_the_compute_stack_are_loaded(ci_sample, tmp_path):
    """What a run checks before any work (flows.preflight) needs neither Prefect nor the stages'
    numerics: a user's mistake is named at once, not after the ~4 s those imports take."""
    foreign = tmp_path / "thesis"
    foreign.mkdir()
    (foreign / "chapter1.tex").write_text("work of months")
    script = ("import sys\nfrom flows.cli import main\ncode = main(['reconstruct', sys.argv[1], '--out', sys.argv[2]])\n"
              "heavy = sorted(m for m in ('prefect', 'open3d', 'pymeshlab', 'numba', 'flows.stages') if m in sys.modules)\n"
              "print(code, heavy)\n")
    done = subprocess.run([sys.executable, "-c", script, str(ci_sample), str(foreign)], capture_output=True, text=True,
                          cwd=REPO, timeout=120)
    assert done.stdout.strip() == "2 []", done.stdout + done.stderr
    assert "holds 1 thing(s) that are not a weldrecon run's" in done.stderr


def test_a_log_file_that_cannot_be_written_says_nothing_on_the_terminal(capsys):
    """A full disk under the run's log file: the record is dropped and counted, and logging's own
    "--- Logging error ---" traceback does not reach the terminal (which gets one line per problem;
    the full-disk run above printed it once in a suite run, when a record came while the disk was full)."""
    import logging

    from flows.cli.errors import run_log_handler

    handler = run_log_handler(Path("/dev/full"))  # every write fails: no space left on device
    logger = logging.getLogger("weldrecon.test-full-disk")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        logger.error("a record the disk cannot take")
        handler.flush()
    finally:
        logger.removeHandler(handler)
        handler.close()
    captured = capsys.readouterr()
    assert "Logging error" not in captured.err and captured.err == ""
    assert handler.lost >= 1


def test_prefect_noise_goes_to_the_log_file_not_the_terminal(tmp_path, capfd):
    """Prefect's internal errors ("Service 'EventsWorker' failed", "--- Error logging to API ---" when its
    server is gone or slow) printed above the one-line errors (issue 28): while a command logs to its file,
    a Prefect console handler made later writes there, and logging's own complaints stay off the terminal."""
    import logging

    from prefect.logging.handlers import PrefectConsoleHandler

    from flows.cli.errors import end_log_file, log_to_file

    raising = logging.raiseExceptions
    path = log_to_file(tmp_path / "logs", "reconstruct")
    try:
        late = logging.getLogger("prefect._internal.concurrency.late")  # made after the command's setup
        late.propagate = False
        late.addHandler(PrefectConsoleHandler())
        late.error("Service 'EventsWorker' failed to process item")
        assert logging.raiseExceptions is False
    finally:
        end_log_file()
    out, err = capfd.readouterr()
    assert "EventsWorker" not in out + err
    assert "Service 'EventsWorker' failed to process item" in path.read_text()
    assert logging.raiseExceptions is raising and PrefectConsoleHandler.emit is not None
    late.handlers.clear()
