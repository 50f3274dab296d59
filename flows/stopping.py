"""How a ``weldrecon`` command stops when it is told to (SIGTERM from a scheduler or ``kill``,
SIGINT from Ctrl-C, SIGHUP from a closed terminal): at once, with every process it started
(Prefect's API server, gmsh, CalculiX, Dask workers), and one line saying so.

Raising an exception in the main thread is not enough: the stages run in worker threads that
the interpreter waits for at exit, and a stage's child killed by the same signal was retried as
a failed stage (issue 28: "SIGTERM does not stop the run, its meshing child restarts"). Every
file a stage writes is written atomically (a temporary name, then a rename), so stopping between
any two instructions publishes nothing half-written; what was in flight stays under a temporary
name that the next run of the folder sweeps (``data_catalog.atomic``, ``sweep_leftovers``).

Prefect's flow engine puts its own SIGTERM handler in place while a flow runs (to mark the run
crashed); ``reassert`` puts this one back from inside the flow, so that the run stops the same way
there."""

from __future__ import annotations

import os
import signal
import sys
import threading

__all__ = ["install", "reassert", "STOP_SIGNALS"]

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
_handler = None


def _end_children(grace_s: float = 3.0) -> None:
    """Terminate every process this one started (recursively), then kill those still there after
    ``grace_s``."""
    try:
        import psutil
    except ImportError:  # psutil comes with distributed; without it the children die with their pipes
        return
    try:
        children = psutil.Process().children(recursive=True)
    except psutil.Error:
        return
    for child in children:
        try:
            child.terminate()
        except psutil.Error:
            pass
    _, alive = psutil.wait_procs(children, timeout=grace_s)
    for child in alive:
        try:
            child.kill()
        except psutil.Error:
            pass


def install(command: str) -> None:
    """Stop ``weldrecon COMMAND`` on SIGTERM, SIGINT and SIGHUP: one line on stderr, its child
    processes ended, exit status 128 + the signal's number. Only in the main thread of the
    program's own process (a command run from Python code keeps the caller's handlers)."""
    global _handler

    def stop(signum, frame):  # noqa: ANN001 - the signal module's signature
        for s in (*STOP_SIGNALS, signal.SIGPIPE):  # a second signal while stopping: ignored, the first is
            signal.signal(s, signal.SIG_IGN)    # acted on (and a pipe to a child just ended is no reason to die)
        name = signal.Signals(signum).name
        line = (f"weldrecon {command}: stopped by {name}; its child processes ended, nothing it was writing was "
                "published\n")
        try:  # the terminal's fds to /dev/null meanwhile: the line is the last one, not a progress line after it
            saved = os.dup(2)
            quiet = os.open(os.devnull, os.O_WRONLY)
            os.dup2(quiet, 1)
            os.dup2(quiet, 2)
        except OSError:
            saved = None
        _end_children()
        try:
            if saved is not None:
                os.write(saved, line.encode())
            else:
                sys.stderr.write(line)
                sys.stderr.flush()
        except (OSError, ValueError):
            pass
        os._exit(128 + signum)

    if threading.current_thread() is not threading.main_thread():
        return
    for s in STOP_SIGNALS:
        signal.signal(s, stop)
    _handler = stop


def reassert() -> None:
    """Put the handlers ``install`` set back (Prefect's flow engine replaces SIGTERM's while a flow
    runs); nothing when none were installed or outside the main thread."""
    if _handler is None or threading.current_thread() is not threading.main_thread():
        return
    for s in STOP_SIGNALS:
        signal.signal(s, _handler)
