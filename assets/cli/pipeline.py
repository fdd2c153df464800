"""Commands over the Dagster pipeline: ``run``, ``status``, ``ui``.

``run`` materializes every asset of a dataset partition through Dagster (recorded in
``$DAGSTER_HOME``, default ``<project>/.dagster_home``, so the web UI shows it); ``--all`` runs every
registered dataset, several at a time in worker processes (:mod:`assets.launch`).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import io
import json
import logging
import os
import shlex
import sys
from typing import Any

from assets.cli import options
from assets.cli.output import EXIT_ERROR, CliHandler, CliOutput, out
from assets.launch import (
    ASSET_ORDER,
    default_concurrency,
    dagster_dev_command,
    first_visits_first,
    prepare_launch,
    run_in_pool,
    run_partition,
    stale_partitions,
    use_project_dagster_home,
)
from atlas_pipeline.errors import AtlasError, ConfigError
from atlas_pipeline.sensors.registry import load_registry

logger = logging.getLogger("atlas_gs.cli")


def _launch(args: argparse.Namespace, fetch: bool):
    return prepare_launch(args.profile, args.set, args.dataset, bool(getattr(args, "all", False)), fetch=fetch)


def cmd_run(args: argparse.Namespace) -> int:
    """Materialize the assets of one or more partitions through Dagster (all, or only stale ones).

    JSON output (``--json``, or stdout not a terminal) is one document: the partition's summary
    object, or with ``--all`` a list of them in registry order (``[]`` when nothing was run)."""
    launch = _launch(args, fetch=True)  # a run fetches what it needs first
    asked = getattr(args, "concurrency", None)
    if asked is not None and asked < 1:
        raise ConfigError(f"--concurrency must be at least 1, got {asked}")
    concurrency = min(asked or default_concurrency(), len(launch.partitions))
    if concurrency > 1:  # --all: several partitions at a time, each run in its own process
        return _run_concurrently(args, launch.partitions, concurrency)
    as_json, many = options.json_output(args), bool(getattr(args, "all", False))
    docs: list[dict[str, Any]] = []  # --all --json: every partition's summary, printed as one list
    failed = 0
    for p in first_visits_first(launch.partitions, load_registry()):
        summary = run_partition(launch, p, stale_only=args.stale_only, executor=getattr(args, "executor", None),
                                dask_scheduler=getattr(args, "dask_scheduler", None))
        failed += summary.get("success") is False
        if as_json and many:
            docs.append(summary)
        else:
            out(json.dumps(summary, indent=2) if as_json else run_words(summary))
    if as_json and many:
        out(json.dumps(docs, indent=2))
    return 1 if failed else 0


class _Captured:
    """A worker's stdout: kept to be printed by the parent in partition order; a terminal when the
    parent's is (so the output format is the parent's)."""

    def __init__(self, tty: bool):
        self._buf, self._tty = io.StringIO(), tty

    def write(self, text: str) -> int:
        return self._buf.write(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self._tty

    def getvalue(self) -> str:
        return self._buf.getvalue()


def _run_in_worker(args: argparse.Namespace, tty: bool, partition: str) -> tuple[int, str]:
    """``atlas-gs run`` of one partition in a pool process: (exit code, its stdout)."""
    from assets.runs import interrupts_end_the_command

    job = argparse.Namespace(**{**vars(args), "all": False, "dataset": partition, "concurrency": 1})
    root = logging.getLogger()
    for inherited in [h for h in root.handlers if isinstance(h, CliHandler)]:
        root.removeHandler(inherited)  # a forked worker's copy of the parent's: every line twice
    captured = _Captured(tty)
    with CliOutput(job.verbose, prefix=f"{partition}: "), contextlib.redirect_stdout(captured):
        try:
            # the parent says the line (Ctrl-C reaches the whole group; the parent passes SIGTERM on)
            with interrupts_end_the_command(say=False):
                code = int(cmd_run(job) or 0)
        except AtlasError as exc:
            logger.error("%s", exc)
            code = EXIT_ERROR
    return code, captured.getvalue()


def _run_concurrently(args: argparse.Namespace, partitions: list[str], concurrency: int) -> int:
    """Up to ``concurrency`` partitions at a time, each an ordinary Dagster run in a worker process
    (:func:`assets.launch.run_in_pool`); their output printed in partition order."""
    logger.info("running %d partitions, %d at a time", len(partitions), concurrency)
    task = functools.partial(_run_in_worker, args, sys.stdout.isatty())
    as_json = options.json_output(args)
    docs: list[dict[str, Any]] = []  # JSON: the workers' summaries, printed as one list (as a serial --all)
    worst = 0
    results = run_in_pool(partitions, concurrency, task, executor=getattr(args, "executor", None))
    for partition, (code, text) in zip(partitions, results):
        if as_json:
            docs.append(_worker_summary(partition, code, text))
        elif text:
            sys.stdout.write(text)
            sys.stdout.flush()
        worst = max(worst, code)
    if as_json:
        out(json.dumps(docs, indent=2))
    return worst


def _worker_summary(partition: str, code: int, text: str) -> dict[str, Any]:
    """A pool worker's JSON summary of its partition; one saying it failed when the worker printed
    none (an error before its run, logged on stderr)."""
    try:
        doc = json.loads(text)
    except ValueError:
        doc = None
    if isinstance(doc, dict):
        return doc
    return {"partition": partition, "success": False, "exit_code": code,
            "errors": ["no summary: see the log on stderr"], **({"output": text} if text.strip() else {})}


def run_words(summary: dict[str, Any]) -> str:
    """A run's result for a person: what ran, the outputs that exist (marked when an earlier run
    wrote them), errors and failed checks; or that nothing was stale."""
    p = summary["partition"]
    if summary.get("ran") is False:
        bundle = summary.get("world_bundle")
        return (f"{p}: all {len(ASSET_ORDER)} assets current, nothing to run"
                + (f"\n  world bundle  {bundle}" if bundle else ""))
    ok = summary["success"]
    done = set(summary.get("recomputed", [])) | set(summary.get("reused", []))
    head = (f"{p}: {len(summary.get('recomputed', []))} assets computed, {len(summary.get('reused', []))} reused"
            if ok else f"{p}: run failed")
    lines = [f"{head} (run {summary['run_id']})"]
    outputs = [("world bundle", summary.get("world_bundle"), "world_bundle"),
               ("transitions", summary.get("transitions"), "transitions"),
               *[("video", v, "demo_videos") for v in summary.get("videos", [])]]
    for label, path, asset in outputs:
        if path:
            earlier = "" if asset in done else "  (from an earlier run)"
            lines.append(f"  {label:<13s} {path}{earlier}")
    loc = summary.get("localization")
    if loc:
        ate = loc.get("ate_rmse_m")
        lines.append(f"  localization  {loc.get('n_tracked')} tracked, {loc.get('n_lost')} lost, "
                     f"{loc.get('n_relocalized')} relocalized" + (f", ATE {ate * 1000:.1f} mm" if ate is not None else ""))
    lines += [f"  error: {e}" for e in summary.get("errors", [])]
    lines += [f"  failed check: {c}" for c in summary.get("failed_checks", [])]
    return "\n".join(lines)


def cmd_status(args: argparse.Namespace) -> int:
    """Print which assets of the partition(s) are stale or missing, and why; runs nothing."""
    stale = stale_partitions(_launch(args, fetch=False))
    # The run that recomputes them: the same partition, profile and overrides as this status
    given = "".join(f" {o} {shlex.quote(v)}" for o, vs in (("--profile", [args.profile] if args.profile else []),
                                                          ("--set", args.set or [])) for v in vs)
    out(json.dumps(stale, indent=2) if args.json else "\n".join(status_words(p, s, given) for p, s in stale.items()))
    return 0


def status_words(partition: str, stale: dict[str, list[str]], options: str = "") -> str:
    """``synthetic: all 9 assets current``, or the stale / missing assets in pipeline order with why
    and the command that recomputes them (``options``: the profile and overrides status was given)."""
    if not stale:
        return f"{partition}: all {len(ASSET_ORDER)} assets current"
    lines = [f"{partition}: {len(stale)} of {len(ASSET_ORDER)} assets would be recomputed "
             f"(`atlas-gs run {partition} --stale-only{options}` runs them)"]
    width = max(len(a) for a in stale)
    for asset in sorted(stale, key=lambda a: ASSET_ORDER.index(a) if a in ASSET_ORDER else len(ASSET_ORDER)):
        lines.append(f"  {asset:<{width}s}  {'; '.join(stale[asset])}")
    return "\n".join(lines)


# Ports after a taken --port tried for the one the error suggests.
FREE_PORT_SEARCH = 100
MAX_PORT = 65535


def _port_error(host: str, port: int) -> OSError | None:
    """Why a server could not listen on ``host:port`` now (None: it could), found by binding a
    socket there as the web server will (``SO_REUSEADDR``: a port left in TIME_WAIT is free)."""
    import socket

    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as exc:
        return OSError(exc.errno, exc.strerror)
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            return exc
    return None


def check_ui_port(host: str, port: int) -> None:
    """A ConfigError naming ``--port`` (or ``--host``) when the web UI could not listen on
    ``host:port``: ``dagster dev`` would log "address already in use" and stay up serving nothing."""
    import errno

    if not 1 <= port <= MAX_PORT:
        raise ConfigError(f"--port {port}: must be 1 to {MAX_PORT}")
    exc = _port_error(host, port)
    if exc is None:
        return
    if exc.errno != errno.EADDRINUSE:
        raise ConfigError(f"--host {host} --port {port}: the web UI cannot listen there: {exc.strerror or exc}")
    free = next((p for p in range(port + 1, min(port + FREE_PORT_SEARCH, MAX_PORT) + 1)
                 if _port_error(host, p) is None), None)
    hint = f", e.g. --port {free}" if free is not None else ""
    raise ConfigError(f"--port {port}: {host}:{port} is already in use (another Dagster UI or server); "
                      f"stop that one, or give another --port{hint}")


def cmd_ui(args: argparse.Namespace) -> int:
    """Replace this process with ``dagster dev`` on the project's DAGSTER_HOME, once the port is
    known to be free."""
    check_ui_port(args.host, args.port)
    home = use_project_dagster_home()
    cmd = dagster_dev_command(args.host, args.port)
    logger.info("DAGSTER_HOME=%s; starting %s", home, " ".join(cmd))
    os.execvp(cmd[0], cmd)
