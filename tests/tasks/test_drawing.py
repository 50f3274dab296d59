"""``tasks.drawing.Drawing``: pictures drawn on worker processes are the bytes drawn here, filled in
the order they were asked for; a picture that cannot be drawn is raised, not left empty."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from tasks.drawing import Drawing
from tasks.report_figures import histogram


def _pictures(workers: int) -> list[dict[str, str]]:
    rng = np.random.default_rng(3)
    with Drawing(workers) as draw:
        pictures = [draw.picture(histogram, rng.normal(k, 1.0, 500), bins=np.arange(-4, 12, 0.5), title=f"picture {k}",
                                 xlabel="value", mark=float(k), alt=f"histogram {k}", caption=f"caption {k}")
                    for k in range(5)]
        if workers:
            assert all(p["src"] == "" for p in pictures)  # places, filled when the drawing finishes
    return pictures


def test_pictures_drawn_on_worker_processes_are_the_bytes_drawn_here_in_order():
    here, there = _pictures(0), _pictures(2)
    assert here == there == _pictures(1)
    assert [p["alt"] for p in there] == [f"histogram {k}" for k in range(5)]
    assert [p["caption"] for p in there] == [f"caption {k}" for k in range(5)]
    assert len({p["src"] for p in there}) == 5
    for p in there:
        assert p["src"].startswith("data:image/png;base64,")
        assert base64.b64decode(p["src"].split(",", 1)[1]).startswith(b"\x89PNG\r\n\x1a\n")


@pytest.mark.parametrize("workers", [0, 1, 2])
def test_a_picture_that_cannot_be_drawn_is_raised(workers):
    with pytest.raises(TypeError):
        with Drawing(workers) as draw:
            draw.picture(histogram, np.zeros(10), bins=np.arange(3.0), title="fine", xlabel="x", alt="fine")
            draw.picture(histogram, np.zeros(10), bins=np.arange(3.0), title="bad", xlabel="x", no_such_argument=1,
                         alt="bad")


def _halves(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if not len(values):
        raise ValueError("nothing to halve")
    return values[: len(values) // 2], values[len(values) // 2:]


@pytest.mark.parametrize("workers", [0, 2])
def test_work_submitted_gives_its_result_or_its_error_where_asked(workers):
    values = np.arange(7.0)
    with Drawing(workers) as draw:
        done = draw.submit(_halves, values)
        failed = draw.submit(_halves, np.zeros(0))
        first, second = done.result()
        with pytest.raises(ValueError, match="nothing to halve"):
            failed.result()
    assert first.tolist() == [0.0, 1.0, 2.0] and second.tolist() == [3.0, 4.0, 5.0, 6.0]
