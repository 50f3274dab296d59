"""What a command's failure shows: one line per problem on the terminal, the traceback in a log
file (the run's own log when the command opened one, else one under $WELDRECON_LOG_DIR)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["quiet_prefect", "log_to_file", "end_log_file", "say_error", "run_log_handler"]

_LOG_FILE: Path | None = None  # the log file a command opened (log_to_file), for its traceback
_UNDO: list = []  # what end_log_file does to undo log_to_file, last first


def quiet_prefect() -> None:
    """No analytics, and only Prefect's warnings: set before Prefect is imported."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")


def _log_path(folder: Path, name: str) -> Path:
    """A new log file's name in ``folder``: the command, UTC time and process id."""
    from datetime import UTC, datetime

    return folder / f"{name}-{datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')}-{os.getpid()}.log"


def run_log_handler(path: Path):
    """A file handler for ``path`` (created on the first record) that never writes to the
    terminal when the file cannot be written; ``.lost`` counts the records it dropped."""
    import logging

    class _Handler(logging.FileHandler):
        lost = 0

        def handleError(self, record):  # noqa: N802 - logging's name
            self.lost += 1

        def flush(self):
            try:
                super().flush()
            except OSError:
                self.lost += 1

        def close(self):
            try:
                super().close()
            except OSError:  # what the buffer still held is lost with the disk's space
                self.lost += 1
                self.stream = None

    return _Handler(path, encoding="utf-8", delay=True)


def log_to_file(folder: Path, name: str) -> Path:
    """Send Prefect's and the libraries' log records (tracebacks included) to a log file in
    ``folder`` instead of the terminal, which gets one line per problem; returns the file."""
    import logging
    import warnings

    from prefect.logging.configuration import setup_logging

    global _LOG_FILE
    end_log_file()  # one log file per command
    setup_logging()  # Prefect's own configuration first (later calls only adjust it)
    folder.mkdir(parents=True, exist_ok=True)
    path = _log_path(folder, name)
    handler = run_log_handler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s %(threadName)s: %(message)s"))
    root = logging.getLogger()
    shown, level = warnings.showwarning, root.level
    _UNDO.extend([handler.close, lambda: setattr(warnings, "showwarning", shown),
                  lambda: logging.captureWarnings(False), lambda: root.setLevel(level)])
    loggers = [lg for lg in list(logging.root.manager.loggerDict.values()) if isinstance(lg, logging.Logger)]
    for logger in [root, *loggers]:
        for k, old in enumerate(logger.handlers):
            if type(old).__name__ == "PrefectConsoleHandler":  # replaced where it stands
                logger.handlers[k] = handler
                _UNDO.append(lambda logger=logger, old=old: logger.handlers.__setitem__(
                    logger.handlers.index(handler), old))
    # a Prefect console handler made after this point (a logger Prefect configures later, a second
    # setup) writes to the file too: its class's emit is the file's while the command runs
    from prefect.logging.handlers import PrefectConsoleHandler

    console_emit = PrefectConsoleHandler.emit
    PrefectConsoleHandler.emit = lambda self, record: handler.emit(record)
    _UNDO.append(lambda: setattr(PrefectConsoleHandler, "emit", console_emit))
    # logging's own complaints ("--- Logging error ---", Prefect's "--- Error logging to API ---" when
    # its server is gone or slow) are not for the terminal: the records themselves are in the file
    raising = logging.raiseExceptions
    logging.raiseExceptions = False
    _UNDO.append(lambda: setattr(logging, "raiseExceptions", raising))
    root.setLevel(logging.INFO)
    logging.captureWarnings(True)
    _LOG_FILE = path
    return path


def end_log_file() -> None:
    """Undo log_to_file (a command run inside another program, e.g. the tests, leaves its logging
    as it found it): the terminal's handlers back, the file closed."""
    global _LOG_FILE
    while _UNDO:
        _UNDO.pop()()
    _LOG_FILE = None


def _traceback_log(command: str, exc: BaseException) -> Path | None:
    """Where the traceback of a failure goes: the run's log file when the command opened one,
    else a file under $WELDRECON_LOG_DIR (default ~/.local/state/weldrecon/logs); None if
    neither can be written (a full disk: the one line must still reach the terminal)."""
    import logging
    import traceback

    if _LOG_FILE is not None:
        logging.getLogger("weldrecon").error("%s failed", command, exc_info=exc)
        return _LOG_FILE
    folder = Path(os.environ.get("WELDRECON_LOG_DIR") or Path.home() / ".local" / "state" / "weldrecon" / "logs")
    path = _log_path(folder, command)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        path.write_text("".join(traceback.format_exception(exc)), encoding="utf-8")
    except OSError:
        return None
    return path


# what a library that could not be loaded, or a thread that could not start, says when the memory
# limit is reached (the loader maps the library's segments; libgomp starts its threads)
_OUT_OF_MEMORY = ("failed to map segment from shared object", "Cannot allocate memory",
                  "Thread creation failed: Resource temporarily unavailable")


def say_error(command: str, exc: Exception) -> int:
    """``weldrecon COMMAND: error: ...`` on stderr, one line for the problem (the traceback of
    one not known as an input error goes to a log file, named on a second line); returns the
    exit status, 2."""
    import sqlite3

    if isinstance(exc, KeyError):
        what = exc.args[0] if exc.args else exc
    elif isinstance(exc, (ImportError, OSError)) and any(sign in str(exc) for sign in _OUT_OF_MEMORY):
        what = (f"out of memory ({exc}); give the run more memory (the least it needs: flows/preflight.py, "
                "MEMORY_FLOOR_BYTES)")
    elif isinstance(exc, (ValueError, OSError, RuntimeError, TimeoutError, sqlite3.Error)):
        stage = getattr(exc, "stage", None)
        what = (f"stage {stage}: " if stage and not str(exc).startswith(f"stage {stage}") else "") + str(exc)
    elif isinstance(exc, MemoryError):
        what = f"out of memory ({exc or 'no detail'}); give the run more memory or smaller blocks"
    else:  # not an input problem we know of: say so, and keep the evidence
        what = f"unexpected {type(exc).__name__}: {exc} (please report it with the log below)"
    print(f"weldrecon {command}: error: {what}", file=sys.stderr)
    from flows.preflight import NotEnoughMemory

    # input errors we name, and a machine too small for the run
    plain = (KeyError, ValueError, FileNotFoundError, FileExistsError, TimeoutError, NotEnoughMemory)
    if _LOG_FILE is not None or not isinstance(exc, plain):
        log = _traceback_log(command, exc)
        if log is not None:
            print(f"  (the details and the traceback: {log})", file=sys.stderr)
    return 2
