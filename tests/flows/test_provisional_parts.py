"""The provisional thread's own pieces (flows.provisional): the part cut from the provisional mesh
for its FE model, and the mark a provisional QA page carries."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from flows.provisional import mark_provisional
from tasks.mesh import mesh_report
from tasks.volume_mesh import largest_piece


def _box(centre, size) -> tuple[np.ndarray, np.ndarray]:
    box = o3d.geometry.TriangleMesh.create_box(*size)
    box.translate(np.asarray(centre, float) - np.asarray(size, float) / 2)
    return np.asarray(box.vertices, np.float64), np.asarray(box.triangles, np.int64)


def test_the_largest_piece_is_the_part_whole_and_closed():
    """A plate and two clamp corners the drawing box caught, their vertices interleaved: the plate
    comes back alone, closed, with its own volume; the count names all three."""
    pieces = [_box((0, 0, 0), (100, 40, 10)), _box((80, 0, 20), (5, 5, 5)), _box((-80, 0, 20), (3, 3, 3))]
    vertices = np.concatenate([v for v, _ in pieces])
    offsets = np.cumsum([0] + [len(v) for v, _ in pieces[:-1]])
    triangles = np.concatenate([t + o for (_, t), o in zip(pieces, offsets)])
    order = np.random.default_rng(3).permutation(len(vertices))  # the pieces' vertices mixed, as Poisson leaves them
    rank = np.argsort(order)
    v, t, count = largest_piece(vertices[order], rank[triangles])
    assert count == 3 and len(t) == len(pieces[0][1]) and len(v) == len(pieces[0][0])
    report = mesh_report(v, t)
    assert report.watertight and report.volume_mm3 == pytest.approx(100 * 40 * 10)
    assert np.ptp(v, axis=0) == pytest.approx([100, 40, 10])
    one_v, one_t, one = largest_piece(*pieces[0])
    assert one == 1 and one_v is pieces[0][0] and one_t is pieces[0][1]  # one piece: unchanged


def test_a_provisional_page_says_so_in_its_title_and_first_line():
    page = "<html>\n<head>\n<title>weldrecon QA report: s1</title>\n</head>\n<body>\n<header>x</header>\n</body>\n</html>\n"
    marked = mark_provisional(page, "made after pass b-W04 <32 of 32>")
    assert "<title>PROVISIONAL weldrecon QA report: s1</title>" in marked
    body = marked.split("<body>\n", 1)[1]
    assert body.startswith('<p class="bad" id="provisional"') and "PROVISIONAL: made after pass b-W04 &lt;32 of 32&gt;." in body
    with pytest.raises(ValueError, match="no <title> or <body>"):
        mark_provisional("<html>no page</html>", "x")
