"""``atlas-gs``: the command line over the library and the Dagster definitions.

It parses the arguments (:mod:`assets.cli.parser`), calls the library (``atlas_pipeline``) or the
Dagster layer (:mod:`assets.launch`, :mod:`assets.artifacts`) and prints (:mod:`assets.cli.output`).
Commands by group: :mod:`~assets.cli.worlds` (build, import-ply, demo-video, export, lineage),
:mod:`~assets.cli.localization` (localize, relocalize, log-transitions, evaluate-trajectory),
:mod:`~assets.cli.pipeline` (run, status, ui), :mod:`~assets.cli.datasets` (dataset ...),
:mod:`~assets.cli.view` (view).
"""

from __future__ import annotations

import logging
import sys

from assets.cli.output import EXIT_BROKEN_PIPE, EXIT_ERROR, EXIT_INCOMPLETE, CliOutput, stdout_closed
from assets.cli.parser import build_parser
from assets.launch import ASSET_ORDER
from atlas_pipeline.errors import AtlasError

__all__ = ["main", "command", "build_parser", "ASSET_ORDER", "EXIT_ERROR", "EXIT_INCOMPLETE", "EXIT_BROKEN_PIPE"]

logger = logging.getLogger("atlas_gs.cli")


def main(argv: list[str] | None = None) -> int:
    """Run one command; its exit status: 0, ``EXIT_ERROR`` for a clear error (one line on stderr),
    ``EXIT_INCOMPLETE``, 1 for a failed run, 130 after Ctrl-C, 143 after SIGTERM, ``EXIT_BROKEN_PIPE``."""
    try:
        args = build_parser().parse_args(argv)  # --help prints here
    except BrokenPipeError:
        return stdout_closed()
    from assets.runs import interrupts_end_the_command, signal_dispositions_kept

    with CliOutput(args.verbose), signal_dispositions_kept():  # a Dagster run changes them (assets.runs)
        try:
            with interrupts_end_the_command():  # Ctrl-C, SIGTERM: one line, status 130 or 143
                return int(args.func(args) or 0)
        except AtlasError as exc:
            logger.error("%s", exc)
            return EXIT_ERROR
        except BrokenPipeError:  # before OSError: a closed stdout is no error of the command's
            return stdout_closed()
        except OSError as exc:  # an OS error the library did not wrap: still name the path
            where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f) or "(no path given by the OS)"
            logger.error("%s: %s", where, exc.strerror or exc)
            return EXIT_ERROR
        except Exception as exc:
            from assets.runs import instance_storage_error

            if (line := instance_storage_error(exc)) is None:
                raise
            logger.error("%s", line)
            return EXIT_ERROR


def command() -> int:
    """The ``atlas-gs`` executable: :func:`main`, then a quick exit. Everything the command wrote is
    closed and renamed into place by then; freezing the objects it leaves keeps the interpreter's
    final garbage collection from walking them one by one (Dagster's, SQLAlchemy's and the
    plotting modules' object graphs: about 0.4 s of every command). Tests call :func:`main`."""
    import gc

    code = main()
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        code = stdout_closed()
    sys.stderr.flush()
    gc.freeze()
    return code
