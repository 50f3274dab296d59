"""``flows.stages.contracts.map_in_order``, the merge stage's two blocks at once: the results in the
items' order whichever thread ends first, a bounded number in flight, an error raised where its
item stands."""

from __future__ import annotations

import threading
import time

import pytest

from flows.stages.contracts import map_in_order


def test_results_come_in_the_items_order_with_few_in_flight():
    lock, state = threading.Lock(), {"now": 0, "most": 0}

    def work(k: int) -> int:
        with lock:
            state["now"] += 1
            state["most"] = max(state["most"], state["now"])
        time.sleep(0.02 if k % 2 == 0 else 0.001)  # the even items end last
        with lock:
            state["now"] -= 1
        return k * k

    taken = []

    def items():
        for k in range(20):
            taken.append(k)
            yield k

    seen = []
    for k, value in enumerate(map_in_order(work, items(), workers=2, ahead=2)):
        seen.append(value)
        assert len(taken) <= k + 1 + 4  # at most workers + ahead items drawn past the one yielded
    assert seen == [k * k for k in range(20)]
    assert state["most"] == 2
    assert list(map_in_order(work, range(5), workers=1)) == [0, 1, 4, 9, 16]


def test_an_error_is_raised_at_its_item():
    def work(k: int) -> int:
        if k == 3:
            raise ValueError("block 3 is unreadable")
        return k

    got = []
    with pytest.raises(ValueError, match="block 3 is unreadable"):
        for value in map_in_order(work, range(10), workers=2):
            got.append(value)
    assert got == [0, 1, 2]
