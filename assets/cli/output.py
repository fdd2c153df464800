"""What a command shows: results on stdout, one short log format on stderr, exit statuses.

Results (JSON, or words for a person at a terminal) go to stdout below any progress bar. Log lines
go to stderr as ``message`` (INFO) or ``level: message``; by default only the command's own lines,
warnings and errors, and of a Dagster run one line per finished stage, a failed step, a failed
check. ``-v`` adds the library's and Dagster's lines, every run event and Python's warnings.
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
from typing import Any

from assets.launch import ASSET_ORDER, RUN_LOGGER, step_error

logger = logging.getLogger("atlas_gs.cli")

EXIT_ERROR = 2  # a clear error (bad input, refused output, failed write): nothing half-done was left
EXIT_INCOMPLETE = 3  # the command wrote its report but could not finish (e.g. frames not in this world)
# The reader of stdout went away (`atlas-gs dataset list | head -1`): 128 + SIGPIPE, the status a
# shell reports for any tool a closed pipe ended, and no message (the reader wanted no more).
EXIT_BROKEN_PIPE = 141

# Third-party loggers that say nothing a user of atlas-gs needs, even with -v (numba's DEBUG lines
# alone are thousands a compile).
MUTED_LOGGERS = ("numba", "matplotlib", "PIL", "asyncio", "urllib3", "filelock", "fsspec", "grpc", "websockets",
                 "sqlalchemy")  # sqlalchemy: every SQL statement of the instance's database
# Dagster's own loggers and its database migrations': shown with -v only (instance notices, migration lines).
DAGSTER_LOGGERS = ("dagster", "alembic")
WARNINGS_LOGGER = "py.warnings"  # where logging.captureWarnings sends them (-v)
# Loggers whose INFO lines the default (quiet) output keeps: the command's own and its runs'.
QUIET_INFO_LOGGERS = ("atlas_gs.cli", "atlas_gs.launch", RUN_LOGGER)
DAGSTER_META_ATTR = "dagster_meta"  # what Dagster's log manager attaches to the records it passes on
# Dagster's line for each step left out after another failed ("Dependencies for step keyframes
# failed: ['fused_frames']. Not executing."): one per later stage, shown with -v only.
SKIPPED_STEP = re.compile(r"^Dependencies for step \S+ (failed|were not executed)")
SECONDS_PER_MS = 1e-3
SECONDS_PER_MINUTE = 60


def out(text: str) -> None:
    """A result on stdout, after any progress bar is cleared from the terminal."""
    from atlas_pipeline.progress import current_terminal

    term = current_terminal()
    if term is not None:
        term.clear()
    print(text, flush=True)


def json_document(obj: Any) -> str:
    """``obj`` as one standard JSON document (indented): NaN and infinities, which ``json.dumps``
    writes as the non-JSON ``NaN`` / ``Infinity`` that jq and most parsers refuse, become null."""
    import math

    def finite(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: finite(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [finite(x) for x in v]
        if isinstance(v, float) and not math.isfinite(v):
            return None
        return v

    return json.dumps(finite(obj), indent=2, allow_nan=False)


def took(seconds: float) -> str:
    from atlas_pipeline.progress import format_duration

    return f"{seconds:.1f} s" if seconds < SECONDS_PER_MINUTE else format_duration(seconds)


def stdout_closed() -> int:
    """``EXIT_BROKEN_PIPE`` after stdout's reader went away, quietly (Python's recipe for SIGPIPE,
    docs.python.org/3/library/signal.html#note-on-sigpipe): stdout is pointed at devnull, so
    flushing what is left of it at exit cannot raise (and print "Broken pipe") again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # a stdout without a file descriptor (an in-process caller's)
        pass
    return EXIT_BROKEN_PIPE


def _under(name: str, loggers: tuple[str, ...]) -> bool:
    """Whether the logger ``name`` is one of ``loggers`` or a child of one."""
    return any(name == n or name.startswith(n + ".") for n in loggers)


class CliFormatter(logging.Formatter):
    """``message`` for INFO, ``warning: message`` otherwise; Dagster's records as
    ``step: message`` (``step EVENT: message`` for its events) instead of its 110-character prefix."""

    def __init__(self, verbose: bool):
        super().__init__()
        self.verbose = verbose

    def format(self, record: logging.LogRecord) -> str:
        text = getattr(record, "atlas_text", None)
        if text is None:
            meta = getattr(record, DAGSTER_META_ATTR, None)
            if isinstance(meta, dict) and "orig_message" in meta:
                ev = meta.get("dagster_event")
                text = str(meta["orig_message"])
                if ev is not None:
                    text = f"{ev.event_type_value}: {text}"
                    if ev.is_failure and self.verbose:
                        text += f": {step_error(ev)}"
                if meta.get("step_key"):
                    text = f"{meta['step_key']}: {text}"
            else:
                text = record.getMessage()
        if record.exc_info and self.verbose:
            text += "\n" + self.formatException(record.exc_info)
        return text if record.levelno == logging.INFO else f"{record.levelname.lower()}: {text}"


class CliHandler(logging.Handler):
    """Writes records below the progress bar (:class:`atlas_pipeline.progress.Terminal`); decides
    what the quiet default shows, and turns Dagster's step events into one line per stage."""

    def __init__(self, terminal: Any, verbose: bool, prefix: str = ""):
        super().__init__(logging.DEBUG)
        self.terminal = terminal
        self.verbose = verbose
        self.prefix = prefix
        self.setFormatter(CliFormatter(verbose))
        self._reused: dict[str, bool] = {}
        self._warned: set[str] = set()

    def _shown(self, record: logging.LogRecord) -> bool:
        name = record.name
        if _under(name, MUTED_LOGGERS) and record.levelno < logging.WARNING:
            return False
        meta = getattr(record, DAGSTER_META_ATTR, None)
        if isinstance(meta, dict) and meta.get("dagster_event") is not None:
            return self._dagster_event(record, meta["dagster_event"])
        if name == WARNINGS_LOGGER:
            # once each, on one line ("file:line: Category: message"; the source line left out),
            # however many times and from wherever Dagster raises it
            first = record.getMessage().strip().splitlines()[0] if record.getMessage().strip() else ""
            if first in self._warned:
                return False
            self._warned.add(first)
            record.atlas_text = first
            return True
        if self.verbose:
            return True
        if isinstance(meta, dict) and SKIPPED_STEP.match(str(meta.get("orig_message", ""))):
            return False  # follows from the failed step's own line
        if _under(name, DAGSTER_LOGGERS):
            return record.levelno >= logging.ERROR  # instance notices and migrations: -v only
        if record.levelno >= logging.WARNING:
            return True
        return _under(name, QUIET_INFO_LOGGERS) and not isinstance(meta, dict)

    def _dagster_event(self, record: logging.LogRecord, ev: Any) -> bool:
        """Dagster's events: all with -v; else a line per finished pipeline stage, a failed step,
        a failed check."""
        kind = ev.event_type_value
        if kind == "ASSET_MATERIALIZATION" and ev.asset_key is not None and len(ev.asset_key.path) == 1:
            reused = ev.event_specific_data.materialization.metadata.get("reused")
            self._reused[ev.asset_key.path[-1]] = bool(reused is not None and reused.value)
        if self.verbose:
            return True
        step = ev.step_key or ""
        if kind == "STEP_SUCCESS" and step in ASSET_ORDER:
            ms = getattr(ev.event_specific_data, "duration_ms", None)
            duration = f"  {took(ms * SECONDS_PER_MS)}" if ms is not None else ""
            record.atlas_text = f"{step:<20s} {'reused' if self._reused.get(step) else 'computed'}{duration}"
            record.levelno, record.levelname = logging.INFO, "INFO"
            return True
        if kind == "STEP_FAILURE":
            record.atlas_text = f"{step} failed: {step_error(ev)}"
            record.levelno, record.levelname = logging.ERROR, "ERROR"
            return True
        if kind == "ASSET_CHECK_EVALUATION" and not ev.event_specific_data.passed:
            d = ev.event_specific_data
            record.atlas_text = f"check {d.asset_key.to_user_string()}:{d.check_name} failed: {d.description or ''}".strip()
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            return True
        return False

    def emit(self, record: logging.LogRecord) -> None:
        try:
            if self._shown(record):
                self.terminal.write_line(self.prefix + self.format(record))
        except Exception:  # noqa: BLE001 - logging must never break the command
            self.handleError(record)


def _unmirrored(stream: Any) -> Any:
    """A second handle on ``stream``'s file descriptor, or None when it has none (an in-process
    caller's). Dagster's compute-log capture points fd 2 at a file during a run and mirrors it back
    through ``tail -F``, which it stops at the run's end before reading the last second; writing
    through a descriptor duplicated before the run keeps the command's own lines out of that path."""
    try:
        fd = stream.fileno()
        stream.flush()
    except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is an OSError
        return None
    return os.fdopen(os.dup(fd), "w", buffering=1, encoding=getattr(stream, "encoding", None) or "utf-8",
                     errors="backslashreplace")


class CliOutput:
    """The command's stderr for the duration of ``main``: one handler on the root logger, levels of
    Dagster's and third-party loggers, warnings (ignored; with -v shown once, as log lines) and
    the progress terminal. Everything is restored on exit (``main`` may run many times in a process).
    ``prefix`` starts every line (a partition's name, when several run at once)."""

    def __init__(self, verbose: bool, prefix: str = ""):
        self.verbose = verbose
        self.prefix = prefix

    def __enter__(self) -> "CliOutput":
        import warnings

        from atlas_pipeline.progress import Terminal, use_terminal

        self._own_stream = _unmirrored(sys.stderr)
        self.terminal = Terminal(self._own_stream or sys.stderr)
        self.handler = CliHandler(self.terminal, self.verbose, self.prefix)
        root = logging.getLogger()
        self._levels = {n: logging.getLogger(n).level for n in ("", *MUTED_LOGGERS, *DAGSTER_LOGGERS, RUN_LOGGER)}
        root.setLevel(logging.DEBUG if self.verbose else logging.INFO)
        for n in MUTED_LOGGERS:
            logging.getLogger(n).setLevel(logging.WARNING)
        for n in DAGSTER_LOGGERS:
            logging.getLogger(n).setLevel(logging.DEBUG if self.verbose else logging.WARNING)
        logging.getLogger(RUN_LOGGER).setLevel(logging.DEBUG)  # step events are DEBUG: summaries need them
        root.addHandler(self.handler)
        self._warnings = warnings.catch_warnings()
        self._warnings.__enter__()
        # Dagster's BetaWarning / PreviewWarning / deprecations: nothing for a user to act on by default
        warnings.simplefilter("once" if self.verbose else "ignore")
        logging.captureWarnings(self.verbose)
        self._terminal_ctx = use_terminal(self.terminal)
        self._terminal_ctx.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._terminal_ctx.__exit__(None, None, None)
        logging.captureWarnings(False)
        self._warnings.__exit__(None, None, None)
        logging.getLogger().removeHandler(self.handler)
        for n, level in self._levels.items():
            logging.getLogger(n).setLevel(level)
        if self._own_stream is not None:
            try:
                self._own_stream.close()
            except OSError:  # a reader that went away: nothing left to flush to
                pass
