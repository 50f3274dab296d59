"""Files a person writes (settings, a cell's CELL.yaml), read within limits: a YAML whose aliases
expand past what any such file holds, or a file of megabytes, refused in one line before it is
built; merge keys read as YAML defines them; a key given twice refused."""

from __future__ import annotations

import pytest

from data_catalog.textfiles import MAX_YAML_VALUES, read_yaml_mapping
from tests.flows.cli import weldrecon


def _bomb(levels: int = 9) -> str:
    """A 'billion laughs': each level a list of nine aliases of the one before (9^levels values)."""
    lines = ['l0: &l0 ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    lines += [f"l{k}: &l{k} [{', '.join([f'*l{k - 1}'] * 9)}]" for k in range(1, levels)]
    return "\n".join(lines) + "\n"


def test_nested_aliases_are_refused_before_they_expand(tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text(_bomb())
    with pytest.raises(ValueError) as caught:
        read_yaml_mapping(path, "settings")
    assert str(caught.value) == (f"{path}: the settings expands to 490,329,064 values through its aliases (*name); "
                                 f"expected at most {MAX_YAML_VALUES:,} (nested aliases multiply)")


def test_a_few_aliases_and_merge_keys_read_as_yaml_defines_them(tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text("base: &base {a: 1, b: 2}\nx: {<<: *base, a: 3}\ny: [*base, *base]\n" + _bomb(4))
    raw = read_yaml_mapping(path, "settings")
    assert raw["x"] == {"a": 3, "b": 2} and raw["y"] == [{"a": 1, "b": 2}] * 2 and len(raw["l3"]) == 9


def test_a_key_twice_and_a_huge_file_are_refused(tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text("merge:\n  voxel_mm: 0.1\nmerge:\n  voxel_mm: 0.2\n")
    with pytest.raises(ValueError, match=r"settings.yaml: the settings is not valid YAML \(line 3, column 1: 'merge' "
                                         "given twice in one mapping\\)"):
        read_yaml_mapping(path, "settings")
    path.write_text("# " + "x" * (5 << 20) + "\n")
    with pytest.raises(ValueError, match=r"settings.yaml: 5,242,883 characters; expected a settings file of at most "
                                         "4,194,304"):
        read_yaml_mapping(path, "settings")


@pytest.mark.parametrize("command", ["import", "measure-weld"])
def test_an_alias_bomb_on_the_command_line_is_one_line_and_writes_nothing(tmp_path, command):
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(_bomb())
    out = tmp_path / "out"
    if command == "import":
        done = weldrecon("import", str(bomb), str(out))
    else:
        scan = tmp_path / "scan.xyz"
        scan.write_text("0 0 0\n1 0 0\n0 1 0\n")
        done = weldrecon("measure-weld", str(scan), "--units", "mm", "--config", str(bomb), "--out", str(out))
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "expands to 490,329,064 values through its aliases" in done.stderr, done.stderr
    assert not out.exists()


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n  # and another\n"])
def test_a_file_that_sets_nothing_is_refused_and_braces_say_none_on_purpose(tmp_path, text):
    path = tmp_path / "settings.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as caught:
        read_yaml_mapping(path, "settings")
    assert str(caught.value) == (f"{path}: the settings file is empty (no fields, only blank lines or comments); "
                                 "expected its fields (section: field: value), or {} to set none on purpose")
    path.write_text("{}  # the defaults\n")
    assert read_yaml_mapping(path, "settings") == {}
    path.write_text("~\n")
    with pytest.raises(ValueError, match=r"settings.yaml: the settings must be a mapping of fields \(section: field: "
                                         r"value\), not null$"):
        read_yaml_mapping(path, "settings")


def test_an_empty_config_on_the_command_line_is_one_line_and_writes_nothing(tmp_path):
    empty = tmp_path / "settings.yaml"
    empty.write_text("")
    scan = tmp_path / "scan.xyz"
    scan.write_text("0 0 0\n1 0 0\n0 1 0\n")
    out = tmp_path / "out"
    done = weldrecon("measure-weld", str(scan), "--units", "mm", "--config", str(empty), "--out", str(out))
    assert done.returncode == 2, done.stderr
    assert done.stderr == (f"weldrecon measure-weld: error: {empty}: the measure-weld settings file is empty (no fields, "
                           "only blank lines or comments); expected its fields (section: field: value), or {} to set "
                           "none on purpose\n"), done.stderr
    assert not out.exists() and empty.read_text() == ""
