"""The docs: the site builds with ``mkdocs build --strict``, the stage graph drawn on the
architecture page is the registry's, the layers drawn there are the import rules, the README
stays a short page, and every relative link in it and in docs/ points at a file that exists."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from flows.stages import STAGE_NAMES, STAGES

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
ARCHITECTURE = DOCS / "architecture.md"
README_MAX_LINES = 150

_MERMAID = re.compile(r"^```mermaid\n(.*?)^```", re.S | re.M)
_NODE = r"([A-Za-z_][A-Za-z0-9_]*)(?:\s*(?:\(\[.*?\]\)|\[.*?\]|\(.*?\)))?"
_EDGE = re.compile(r"^\s*(.+?)\s*(?:-->|-\.\s*\"[^\"]*\"\s*\.->|-\.->)\s*(.+?)\s*$")
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _mermaid_graph(marker: str) -> tuple[set[str], set[tuple[str, str]]]:
    """Nodes and edges (a, b) of the one mermaid block on the architecture page whose comment
    starts with ``%% <marker>:``; ``a & b --> c`` is two edges."""
    blocks = [b for b in _MERMAID.findall(ARCHITECTURE.read_text(encoding="utf-8"))
              if re.search(rf"^\s*%%\s*{re.escape(marker)}:", b, re.M)]
    assert len(blocks) == 1, f"docs/architecture.md: {len(blocks)} mermaid blocks marked '%% {marker}:', expected 1"
    nodes: set[str] = set()
    edges: set[tuple[str, str]] = set()
    for line in blocks[0].splitlines():
        line = line.strip()
        if not line or line.startswith("%%") or line.startswith(("flowchart", "graph")):
            continue
        edge = _EDGE.match(line)
        if edge:
            ends = []
            for side in edge.groups():
                names = [re.fullmatch(_NODE, part.strip()) for part in side.split("&")]
                assert all(names), f"docs/architecture.md: cannot read the node(s) {side!r} in {line!r}"
                ends.append([n.group(1) for n in names])
            edges.update((a, b) for a in ends[0] for b in ends[1])
            nodes.update(ends[0] + ends[1])
            continue
        node = re.fullmatch(_NODE, line)
        assert node, f"docs/architecture.md: cannot read the mermaid line {line!r}"
        nodes.add(node.group(1))
    return nodes, edges


def _registry_block() -> str:
    """The stage-graph lines as they should be, for the failure message."""
    return "\n".join(f"    {need} --> {s.name}" for s in STAGES for need in s.needs)


def test_the_stage_graph_on_the_architecture_page_is_the_registry():
    nodes, edges = _mermaid_graph("stage graph")
    expected = {(need, s.name) for s in STAGES for need in s.needs}
    assert nodes == set(STAGE_NAMES), (f"stages drawn but not in STAGES: {sorted(nodes - set(STAGE_NAMES))}; "
                                       f"in STAGES but not drawn: {sorted(set(STAGE_NAMES) - nodes)}")
    assert edges == expected, (f"arrows drawn that no stage needs: {sorted(edges - expected)}; needs not drawn: "
                               f"{sorted(expected - edges)}; the registry's arrows:\n{_registry_block()}")


def test_per_pass_stages_are_drawn_as_such():
    text = ARCHITECTURE.read_text(encoding="utf-8")
    for s in STAGES:
        drawn_per_pass = re.search(rf"^\s*{s.name}\(\[\"{s.name} \(per pass\)\"\]\)\s*$", text, re.M) is not None
        assert drawn_per_pass == s.per_pass, f"docs/architecture.md: {s.name} per pass: {s.per_pass}"


def test_the_layers_on_the_architecture_page_are_the_import_rules():
    spec = importlib.util.spec_from_file_location("_layering", REPO / "tests" / "test_layering.py")
    layering = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(layering)
    nodes, edges = _mermaid_graph("layers")
    expected = {(package, other) for package, (allowed, _) in layering.RULES.items() for other in allowed
                if other != package}
    # flows may import every other package (the simulator only in a few commands)
    expected |= {("flows", other) for other in layering.PROJECT if other != "flows"}
    assert nodes == set(layering.PROJECT)
    assert edges == expected, (f"drawn, not allowed: {sorted(edges - expected)}; "
                               f"allowed, not drawn: {sorted(expected - edges)}")


def test_the_readme_is_short():
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, (f"README.md has {len(lines)} lines (at most {README_MAX_LINES}): "
                                            "move reference material to docs/")


def test_the_readme_keeps_the_two_commands():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    assert re.search(r"^make demo\b", text, re.M) and re.search(r"^make test\b", text, re.M)


def _markdown_files() -> list[Path]:
    return [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]


@pytest.mark.parametrize("page", _markdown_files(), ids=lambda p: p.relative_to(REPO).as_posix())
def test_relative_links_point_at_files_that_exist(page):
    text = page.read_text(encoding="utf-8")
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)  # links in code blocks are not links
    text = re.sub(r"`[^`\n]*`", "", text)
    missing = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # http:, mailto:, an anchor on the same page (mkdocs --strict checks anchors)
        path = target.split("#", 1)[0]
        if not (page.parent / path).exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(REPO)}: links to files that do not exist: {missing}"


def test_the_nav_lists_every_page():
    def pages(entries):
        for entry in entries:
            value = next(iter(entry.values())) if isinstance(entry, dict) else entry
            if isinstance(value, list):
                yield from pages(value)
            else:
                yield value

    config = yaml.load((REPO / "mkdocs.yml").read_text(encoding="utf-8"), Loader=_IgnoreTags)
    listed = list(pages(config["nav"]))
    on_disk = sorted(p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md"))
    assert sorted(listed) == on_disk, f"nav: {sorted(listed)}; docs/: {on_disk}"


class _IgnoreTags(yaml.SafeLoader):
    """mkdocs.yml's ``!!python/name:`` tags read as plain strings."""


_IgnoreTags.add_multi_constructor("tag:yaml.org,2002:python/", lambda loader, suffix, node: None)


def test_the_site_builds_strictly(tmp_path):
    mkdocs = Path(sys.executable).parent / "mkdocs"
    if not mkdocs.exists():
        pytest.fail(f"{mkdocs} is missing: install the test extra (pip install -e '.[test]')")
    result = subprocess.run([str(mkdocs), "build", "--strict", "--config-file", str(REPO / "mkdocs.yml"),
                             "--site-dir", str(tmp_path / "site")], cwd=REPO, capture_output=True, text=True,
                            timeout=300, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{result.stdout}\n{result.stderr}"
    architecture = (tmp_path / "site" / "architecture" / "index.html").read_text(encoding="utf-8")
    assert architecture.count('<pre class="mermaid">') == 2, "the architecture page's diagrams are not mermaid blocks"
    assert (tmp_path / "site" / "img" / "qa-report.png").exists()
