"""Pictures drawn on worker processes while the page that wants them goes on reading its inputs.

matplotlib draws under the GIL, so threads draw no faster than one; a QA page of the paper preset
draws ~90 pictures (~20 s of one core). ``Drawing`` hands each picture (a function of
``tasks.report_figures`` and its arguments, pickled) to a pool of ``forkserver`` processes (not
forked from the run's process, whose other threads may hold locks) and gives back a place for it:
a picture dict ``{"src", "alt", "caption"}`` whose ``src`` is filled, in the order the pictures were
asked for, when the drawing is finished (``with`` block's end, or ``finish``). The PNG bytes are the
same as drawn in the caller's process: the same function of the same arguments, matplotlib's
settings its own defaults plus the figure's ``rc_context``.

``workers`` 0 draws each picture at once, in the caller (no pool). ``submit`` hands the pool any
other work the page would wait on (a module-level function), so that it runs beside the caller too.
"""

from __future__ import annotations

import base64
import multiprocessing
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

__all__ = ["Drawing", "png_uri"]


def png_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


class Drawing:
    """Pictures drawn on ``workers`` processes (module description)."""

    def __init__(self, workers: int = 0) -> None:
        self.workers = max(int(workers), 0)
        self._pool: ProcessPoolExecutor | None = None
        self._pending: list[tuple[dict[str, str], Future]] = []

    def picture(self, draw: Callable[..., bytes], *args: Any, alt: str, caption: str = "", **kwargs: Any) -> dict[str, str]:
        """``draw(*args, **kwargs)`` (PNG bytes; a module-level function, picklable arguments) as a
        picture dict; its ``src`` is filled when the drawing finishes (at once without workers)."""
        out = {"src": "", "alt": alt, "caption": caption}
        if not self.workers:
            out["src"] = png_uri(draw(*args, **kwargs))
            return out
        self._pending.append((out, self.submit(draw, *args, **kwargs)))
        return out

    def submit(self, work: Callable[..., Any], *args: Any, **kwargs: Any) -> Future:
        """``work(*args, **kwargs)`` (a module-level function, picklable arguments and result) on
        the pool, its result in the future returned; done at once, in the caller, without workers."""
        if not self.workers:
            future: Future = Future()
            try:
                future.set_result(work(*args, **kwargs))
            except Exception as exc:  # raised where the result is asked for, as from the pool
                future.set_exception(exc)
            return future
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("forkserver"))
        return self._pool.submit(work, *args, **kwargs)

    def finish(self) -> None:
        """Every picture asked for drawn and filled in; the first that failed raised (after the
        others are done or cancelled), the pool shut down either way."""
        try:
            for out, future in self._pending:
                out["src"] = png_uri(future.result())
        finally:
            self.close()

    def close(self) -> None:
        pool, self._pool, self._pending = self._pool, None, []
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> Drawing:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.finish()
        else:
            self.close()
