"""Bad input to the simulator: a clear error naming the field, and nothing written."""

from __future__ import annotations

import pytest

from flows.cli import main
from schemas.simulation import SimulationConfig
from simulator.presets import UnknownPresetError, preset_config
from simulator.run import simulate


def _run(tmp_path, capsys, *args):
    out = tmp_path / "out"
    code = main(["simulate", *args, str(out)])
    err = capsys.readouterr().err
    return code, err, out


def test_unknown_preset_is_refused(tmp_path, capsys):
    code, err, out = _run(tmp_path, capsys, "--preset", "fast")
    assert code == 2
    assert "unknown preset 'fast'" in err and "ci" in err and "paper" in err
    assert not out.exists()
    with pytest.raises(UnknownPresetError):
        preset_config("fast")


@pytest.mark.parametrize(
    ("yaml_text", "field", "message"),
    [
        ("robot:\n  speed_mm_s: -15\n", "robot.speed_mm_s", "greater than 0"),
        ("specimen:\n  gauge_width_mm: 150\n", "specimen", "gauge_width_mm must not exceed grip_width_mm"),
        ("specimen:\n  gauge_length_mm: 600\n", "specimen", "shorter than length_mm"),
        ("weld:\n  cap_height_mm: [1.0, 25.0]\n", "weld", "cap_height_mm must be less than half"),
        ("weld:\n  cap_width_mm: [20.0, 15.0]\n", "weld.cap_width_mm", "exceeds high bound"),
        ("scanner:\n  z_range_mm: [250.0, 300.0]\n", "scanner", "z_range_mm"),
        ("fixture:\n  block_centres_x_mm: [-400.0, 400.0]\n", "(top level)", "beyond the specimen's ends"),
        ("robot:\n  sped_mm_s: 15\n", "robot.sped_mm_s", "Extra inputs are not permitted"),
        ("stickers:\n  min_common: 2\n", "stickers.min_common", "greater than or equal to 3"),
    ],
)
def test_impossible_config_names_the_field_and_writes_nothing(tmp_path, capsys, yaml_text, field, message):
    config = tmp_path / "bad.yaml"
    config.write_text(yaml_text)
    code, err, out = _run(tmp_path, capsys, "--preset", "ci", "--config", str(config))
    assert code == 2
    assert str(config) in err
    assert f"  {field}:" in err and message in err, err
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["bad.yaml"]


def test_unreadable_config_file_is_named(tmp_path, capsys):
    code, err, out = _run(tmp_path, capsys, "--preset", "ci", "--config", str(tmp_path / "missing.yaml"))
    assert code == 2 and "missing.yaml" in err and not out.exists()


def test_existing_output_is_not_touched(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("earlier work")
    code = main(["simulate", "--preset", "ci", str(out)])
    assert code == 2
    assert "already exists" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    with pytest.raises(FileExistsError):
        simulate(preset_config("ci"), out)


def test_a_failed_simulation_leaves_no_partial_folder(tmp_path, monkeypatch):
    """The scanner fails once the first pass's store is written: nothing of the folder is left."""
    import simulator.run as run

    class Broken(run.PassWriter):
        def close(self):
            super().close()
            assert any(tmp_path.rglob("*.zarr"))  # the first pass is on disk, beside the folder
            raise RuntimeError("scanner exploded")

    monkeypatch.setattr(run, "PassWriter", Broken)
    with pytest.raises(RuntimeError, match="scanner exploded"):
        simulate(preset_config("ci").model_copy(update={"chunk_profiles": 4096}), tmp_path / "out")
    assert list(tmp_path.iterdir()) == []


def test_presets_are_valid_and_distinct():
    seeds = {preset_config(name).seed for name in ("ci", "demo", "paper")}
    assert len(seeds) == 3
    assert SimulationConfig.model_validate(preset_config("paper").model_dump()) == preset_config("paper")


@pytest.mark.parametrize("pace", ["fast", "x0", "x-2", "xnan", ""])  # "": an unset shell variable
def test_a_bad_pace_is_refused_before_anything_is_written(tmp_path, capsys, pace):
    out = tmp_path / "sample"
    assert main(["simulate", "--preset", "ci", "--pace", pace, str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--pace {pace!r}: expected realtime or xN with N > 0" in err
    assert not out.exists()


@pytest.mark.parametrize(("text", "expected"), [
    ("a: [\n", "the simulation config is not valid YAML (line 2, column 1: expected the node content"),
    ("- robot\n- scanner\n", "the simulation config must be a mapping of fields (section: field: value), not a list"),
    ("robot: !!python/object/apply:os.system ['touch pwned']\n", "the simulation config is not valid YAML (line 1"),
    (b"robot:\n  speed_mm_s: \xff\n", "not UTF-8 text at byte 21, expected a simulation config file (YAML)"),
    (None, "is a folder, expected a simulation config file (YAML)"),
])
def test_an_unreadable_config_is_named_in_one_line(tmp_path, capsys, text, expected):
    config = tmp_path / "bad.yaml"
    if text is None:
        config.mkdir()
    elif isinstance(text, bytes):
        config.write_bytes(text)
    else:
        config.write_text(text)
    code, err, out = _run(tmp_path, capsys, "--preset", "ci", "--config", str(config))
    assert code == 2 and not out.exists() and not (tmp_path / "pwned").exists()
    assert err.strip().splitlines() == [f"weldrecon simulate: error: {config}: " + err.split(f"{config}: ", 1)[1].strip()]
    assert expected in err


def test_an_output_folder_that_cannot_be_made_is_refused_before_simulating(tmp_path, capsys):
    a_file = tmp_path / "a-file"
    a_file.write_text("earlier work")
    assert main(["simulate", "--preset", "ci", str(a_file / "sample")]) == 2
    assert capsys.readouterr().err.strip() == (f"weldrecon simulate: error: OUT_DIR {a_file / 'sample'}: {a_file} is "
                                               "a file, not a folder")
    assert main(["simulate", "--preset", "ci", "/proc/weldrecon-sample"]) == 2  # root may "write" there, but not create
    err = capsys.readouterr().err
    assert "cannot create anything in /proc" in err and "simulating" not in err  # before any work
    assert main(["demo", "--out", str(a_file)]) == 2
    assert capsys.readouterr().err.strip() == (f"weldrecon demo: error: --out {a_file}: {a_file} is a file, not a "
                                               "folder")
    assert a_file.read_text() == "earlier work"


def test_a_key_given_twice_in_a_config_is_named(tmp_path, capsys):
    config = tmp_path / "twice.yaml"
    config.write_text("robot:\n  speed_mm_s: 15\nrobot:\n  speed_mm_s: 30\n")
    code, err, out = _run(tmp_path, capsys, "--preset", "ci", "--config", str(config))
    assert code == 2 and not out.exists()
    assert f"{config}: the simulation config is not valid YAML (line 3, column 1: 'robot' given twice" in err
