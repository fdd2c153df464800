"""TUM RGB-D layout: list files, RGB-depth association, ground-truth lookup, frame manifest.

Layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    rgb.txt          timestamp filename      (8-bit colour PNG or JPEG)
    depth.txt        timestamp filename      (16-bit PNG, depth_m = value / depth_scale, 0 = none)
    groundtruth.txt  timestamp tx ty tz qx qy qz qw   (camera-to-world, optional)

Comment lines start with ``#``. Timestamps are seconds (TUM: since the Unix epoch). Their unit is
checked from the data (:func:`check_timestamps_are_seconds`): stamps that cannot be seconds, such
as nanoseconds since the epoch or frames 33,000 "s" apart, are an error naming the file and the
likely unit, never converted (a guessed factor would silently be wrong for some other unit).
RGB and depth frames are paired by nearest timestamp within 20 ms
(as TUM's ``associate.py``). A frame's time is its depth image's (the pose estimated from it;
the colour time is kept beside it), and ground truth there is interpolated between the two
neighbouring motion-capture samples, or taken from the nearest one within 20 ms at the ends.
"""

from __future__ import annotations

import json
import logging
import math
import posixpath
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from atlas_pipeline.errors import ArtifactError, DatasetError
from atlas_pipeline.geometry import interpolate_pose, pose_from_tq, tq_from_pose
from atlas_pipeline.io_utils import atomic_path, sha256_files, write_json_atomic
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.images import check_depth_header, check_rgb_header

logger = logging.getLogger(__name__)

MAX_ASSOCIATION_DT_S = 0.02  # TUM's associate.py default max_difference
MAX_GT_INTERPOLATION_GAP_S = 0.1  # never interpolate across a longer hole in the motion capture
# A list line is "timestamp filename" (< 100 bytes in TUM); longer lines are not a list file, and
# reading them in bounded pieces keeps a garbage file from being read as one huge line.
MAX_LIST_LINE_BYTES = 4096
# Depth frames within +-max_dt of one RGB frame: a 100 Hz sensor puts 4-5 there; far more means
# the timestamps are not seconds (and association would consider every pair).
MAX_DEPTH_FRAMES_PER_RGB_WINDOW = 64
# Seconds since 1970 reach 1e11 in the year 5138; the same epoch in ms, us and ns is 1.7e12, 1.7e15
# and 1.7e18, so a larger stamp is not seconds.
MAX_TIMESTAMP_S = 1e11
# Cameras and motion capture sample at 1 Hz - 1 kHz, frames 1 ms - 1 s apart; a median spacing
# above 10 "s" is milliseconds (33 at 30 Hz), microseconds (33,000) or nanoseconds (3.3e7).
MAX_MEDIAN_SPACING_S = 10.0
# Ground truth gives unit quaternions printed to 4-9 digits (TUM: 4, norm within 2e-4 of 1); a norm
# further from 1 is no rounding but a column missing or shifted, and normalising it would read
# (0, 0, 1e-6, 1e-6) as a 90 degree turn.
QUATERNION_NORM_TOLERANCE = 1e-2
# The fastest a camera of this pipeline moves: hand-held cameras reach 1-2 m/s, indoor robots 2 m/s,
# a running person 6 m/s, a car in town 15 m/s; 20 m/s covers them all, and a pose faster than that
# is a wrong line (a marker swap, another recording's poses, a unit mix-up), which would map the
# scene twice.
MAX_CAMERA_SPEED_M_PER_S = 20.0
# Motion capture jitters by millimetres; between stamps 0.1 ms apart that alone reads as 10 m/s, so
# a step shorter than this is never called a jump.
MIN_JUMP_M = 0.05
# A motion-capture glitch (a marker swap, a reflection taken for a marker) throws the pose away for
# one sample or a few (tens of ms at 100-300 Hz) and the path goes on where it left off; a longer
# excursion is not told apart from a wrong or merged file, and is refused like a jump that stays.
MAX_GLITCH_ROWS = 5
# Glitches named one warning each; more are summed up in one line.
MAX_GLITCHES_LOGGED = 5
# (unit, seconds per unit, smallest stamp of an epoch in it / smallest spacing of a 1 kHz sensor in it)
_UNITS = (("nanoseconds", 1e-9, 1e17, 1e6), ("microseconds", 1e-6, 1e14, 1e3), ("milliseconds", 1e-3, 1e11, 1.0))

__all__ = [
    "FrameManifest",
    "read_list_file",
    "increasing_timestamps",
    "check_timestamps_are_seconds",
    "read_groundtruth",
    "check_groundtruth_speed",
    "screen_pose_jumps",
    "PoseGlitch",
    "check_groundtruth_overlap",
    "check_unique_files",
    "associate",
    "lookup_groundtruth",
    "load_tum_sequence",
    "check_tum_layout",
]


def _iter_lines(path: Path):
    """``(line_number, text)`` of a list file, read in bounded pieces: a line longer than
    ``MAX_LIST_LINE_BYTES`` or one that is not UTF-8 is a ``DatasetError`` naming it."""
    try:
        with open(path, "rb") as f:
            lineno = 0
            while True:
                raw = f.readline(MAX_LIST_LINE_BYTES + 1)
                if not raw:
                    return
                lineno += 1
                if len(raw) > MAX_LIST_LINE_BYTES:
                    raise DatasetError(path, f"line is longer than {MAX_LIST_LINE_BYTES} bytes "
                                             "(not a TUM list file?)", lineno)
                try:
                    text = raw.decode("utf-8")
                except UnicodeDecodeError as exc:
                    raise DatasetError(path, f"line is not UTF-8 text (byte {exc.start}: "
                                             f"{raw[exc.start:exc.start + 1]!r})", lineno) from None
                yield lineno, text.lstrip("\ufeff") if lineno == 1 else text  # editors may add a BOM
    except OSError as exc:
        raise DatasetError(path, f"cannot read list file ({exc.strerror or exc})") from None


def read_list_file(path: Path, n_fields: int) -> list[tuple[int, list[str]]]:
    """Parse a TUM list file into ``(line_number, fields)`` rows, skipping comments and blanks.

    Raises:
        DatasetError: missing or unreadable file, a line that is too long or not UTF-8, a line
            with a wrong number of fields, or a timestamp that is not a finite number.
    """
    problem = file_problem(path)
    if problem is not None:
        raise DatasetError(path, f"list file {problem}")
    rows: list[tuple[int, list[str]]] = []
    for lineno, raw in _iter_lines(path):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != n_fields:
            raise DatasetError(
                path, f"expected {n_fields} fields, found {len(parts)}: {line[:80]!r}", lineno
            )
        try:
            t = float(parts[0])
        except ValueError:
            raise DatasetError(path, f"timestamp is not a number: {parts[0][:40]!r}", lineno) from None
        if not math.isfinite(t):
            raise DatasetError(path, f"timestamp {parts[0][:40]!r} is not a finite number", lineno)
        rows.append((lineno, parts))
    if not rows:
        raise DatasetError(path, "no entries")
    return rows


def _likely_unit(value: float, spacing: bool) -> tuple[str, float]:
    """``(unit name, seconds per unit)`` a stamp (``spacing`` False) or a frame spacing (True) that
    is too large for seconds most likely has."""
    for name, factor, epoch, gap in _UNITS:
        if value >= (gap if spacing else epoch):
            return name, factor
    return _UNITS[-1][0], _UNITS[-1][1]


def check_timestamps_are_seconds(path: Path, rows: list[tuple[int, list[str]]], ts: np.ndarray) -> None:
    """Refuse timestamps ``ts`` ``[N]`` (of ``rows``, sorted by time) that cannot be seconds.

    Units are checked from the data, not converted: a median spacing of consecutive stamps above
    ``MAX_MEDIAN_SPACING_S`` (10 s: frames of a 30 Hz camera are 3.3e7 ns apart; the spacing tells
    the unit best), or a stamp above ``MAX_TIMESTAMP_S`` (1e11 s, the year 5138: milliseconds,
    microseconds or nanoseconds since the epoch) is a ``DatasetError`` naming the file (and the
    line of the first stamp too large), the likely unit and the factor to seconds. Without the
    check nanosecond stamps pass as seconds and association fails with "no depth frame within
    20 ms", or ground truth matches no frame.
    """
    if len(ts) >= 2:
        spacing = float(np.median(np.diff(ts)))
        if spacing > MAX_MEDIAN_SPACING_S:
            unit, factor = _likely_unit(spacing, spacing=True)
            raise DatasetError(path, f"timestamps are a median {spacing:.6g} apart, too far for seconds (frames "
                                     f"of a 1-1000 Hz sensor are 0.001-1 s apart): they look like {unit}; TUM "
                                     f"list files give seconds (multiply by {factor:g})")
    big = np.flatnonzero(np.abs(ts) > MAX_TIMESTAMP_S)
    if len(big):
        line, parts = rows[int(big[0])]
        unit, factor = _likely_unit(abs(float(ts[big[0]])), spacing=False)
        raise DatasetError(path, f"timestamp {parts[0][:40]} is too large for seconds (more than {MAX_TIMESTAMP_S:g}, "
                                 f"the year 5138): the timestamps look like {unit} since the epoch; TUM list files "
                                 f"give seconds (multiply by {factor:g})", line)


def increasing_timestamps(path: Path, rows: list[tuple[int, list[str]]]) -> np.ndarray:
    """Timestamps ``[N]`` of :func:`read_list_file` rows, which must strictly increase and be
    seconds (:func:`check_timestamps_are_seconds`).

    TUM's rgb.txt and depth.txt are in capture order; a timestamp that repeats or goes back means
    an edited or concatenated list, and association would silently drop or swap frames.

    Raises:
        DatasetError: naming the list file and the first line whose time is not after the one before.
    """
    ts = np.array([float(p[0]) for _, p in rows])
    bad = np.flatnonzero(np.diff(ts) <= 0)
    if len(bad):
        k = int(bad[0]) + 1
        (prev_line, prev), (line, cur) = rows[k - 1], rows[k]
        raise DatasetError(
            path, f"timestamp {cur[0][:40]} is not after the previous one (line {prev_line}: {prev[0][:40]}); "
                  "TUM lists must be in increasing time order", line)
    check_timestamps_are_seconds(path, rows, ts)
    return ts


def _parse_groundtruth(path: Path) -> tuple[list[tuple[int, list[str]]], np.ndarray, np.ndarray]:
    """The rows of ``groundtruth.txt`` in time order (``(line_number, fields)``), their times ``[M]``
    and ``tx ty tz qx qy qz qw`` ``[M, 7]``, every row checked (see :func:`read_groundtruth`)."""
    rows = read_list_file(path, 8)
    ts = np.empty(len(rows))
    tq = np.empty((len(rows), 7))
    for i, (lineno, parts) in enumerate(rows):
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise DatasetError(path, "non-numeric value", lineno) from None
        if not np.all(np.isfinite(vals)):
            raise DatasetError(path, "non-finite value", lineno)
        norm = float(np.linalg.norm(vals[4:8]))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise DatasetError(path, f"quaternion qx qy qz qw ({', '.join(parts[4:8])}) has norm {norm:.6g}, not 1 "
                                     f"(within {QUATERNION_NORM_TOLERANCE:g}): ground truth rows are 'timestamp tx ty "
                                     "tz qx qy qz qw' with a unit quaternion; is a column missing or shifted?", lineno)
        ts[i] = vals[0]
        tq[i] = vals[1:]
    order = np.argsort(ts, kind="stable")
    ts, tq = ts[order], tq[order]
    same = np.flatnonzero(np.diff(ts) == 0)
    if len(same):
        first, second = rows[order[same[0]]], rows[order[same[0] + 1]]
        raise DatasetError(path, f"timestamp {second[1][0][:40]} repeats line {first[0]}; ground truth "
                                 "needs one pose per time", second[0])
    sorted_rows = [rows[k] for k in order]
    check_timestamps_are_seconds(path, sorted_rows, ts)
    return sorted_rows, ts, tq


def read_groundtruth(path: Path, frame_ts: np.ndarray | None = None,
                     max_dt: float = MAX_ASSOCIATION_DT_S) -> tuple[np.ndarray, np.ndarray]:
    """Read ``groundtruth.txt``: timestamps ``[M']`` and ``poses_se3`` ``[M', 4, 4]`` (camera-to-world).

    Rows are sorted by time (motion-capture exports are not always in order), but two rows with
    the same timestamp are an error naming both lines; a non-numeric value or a quaternion whose
    norm is not 1 within ``QUATERNION_NORM_TOLERANCE`` names its line; timestamps must be seconds
    (:func:`check_timestamps_are_seconds`). The camera may not move faster than
    ``MAX_CAMERA_SPEED_M_PER_S`` (:func:`check_groundtruth_speed`) between the rows the frames at
    ``frame_ts`` ``[N]`` read (every row when None); glitch rows that jump away and back are left
    out of what is returned (``M' <= M``), with a warning.
    """
    rows, ts, tq = _parse_groundtruth(path)
    keep = check_groundtruth_speed(path, rows, ts, tq[:, :3], frame_ts, max_dt)
    return ts[keep], pose_from_tq(tq[keep, :3], tq[keep, 3:])


@dataclass(frozen=True)
class PoseGlitch:
    """Rows ``first..last`` of a camera path (indices into the poses screened) that jump away from
    row ``before`` and come back to row ``after``: ``distance_m`` the farthest they lie from row
    ``before``, ``speed_m_per_s`` the speed of the jump away."""

    before: int
    first: int
    last: int
    after: int
    distance_m: float
    speed_m_per_s: float


def _too_fast(dt_s, step_m):
    """Steps of ``step_m`` metres in ``dt_s`` seconds (both ``[K]`` arrays, or numbers) no camera
    makes: faster than ``MAX_CAMERA_SPEED_M_PER_S`` and longer than ``MIN_JUMP_M`` (motion-capture
    jitter)."""
    return (step_m > MIN_JUMP_M) & (step_m > MAX_CAMERA_SPEED_M_PER_S * dt_s)


def _glitch_around(t_s: np.ndarray, c_m: np.ndarray, k: int) -> tuple[int, int, int, int] | None:
    """``(before, first, last, after)`` for a too-fast step from row ``k`` to ``k + 1`` when rows
    ``first..last`` (at most ``MAX_GLITCH_ROWS``, the step's far side) leave the path that rows
    ``before`` and ``after`` continue at a camera's speed; None when the path goes on from where
    it jumped to. ``t_s`` ``[M]``, ``c_m`` ``[M, 3]``. The shortest such run wins, rows after the
    step first."""
    n = len(t_s)

    def physical(a: int, b: int) -> bool:
        return not _too_fast(float(t_s[b] - t_s[a]), float(np.linalg.norm(c_m[b] - c_m[a])))

    for rows in range(1, MAX_GLITCH_ROWS + 1):
        if k + rows + 1 < n and physical(k, k + rows + 1):
            return k, k + 1, k + rows, k + rows + 1
        if k - rows >= 0 and physical(k - rows, k + 1):
            return k - rows, k - rows + 1, k, k + 1
    return None


def screen_pose_jumps(t_s: np.ndarray, t_world_cam_m: np.ndarray, read_span) -> tuple[
        np.ndarray, list[PoseGlitch], list[tuple[int, int]]]:
    """Tell glitches from jumps in a camera path (``t_s`` ``[M]`` increasing times, ``t_world_cam_m``
    ``[M, 3]`` camera centres).

    Only the rows that are read matter: ``read_span(kept)`` gives, for the indices ``kept`` of the
    rows not dropped so far, the positions ``(first, last)`` in ``kept`` of the first and last row
    read (or None: none is). Steps between those rows, and with one row of margin each side (so a
    glitch on the first or last row read is seen), that no camera makes (:func:`_too_fast`) are
    either a glitch, rows that leave the path and come back (:func:`_glitch_around`), which are
    dropped, or a jump: the path goes on from the new place. Rows dropped can change which rows are
    read, so this repeats until no step is left to judge.

    Returns:
        ``(keep [M] bool, glitches, jumps)``: ``jumps`` are ``(row, next row)`` (indices into the
        input) of the too-fast steps between rows read that are no glitch, empty when the path is
        one camera's; a jump from the first or last row read to its margin row is no error, as no
        frame reads poses on its far side.
    """
    keep = np.ones(len(t_s), bool)
    glitches: list[PoseGlitch] = []
    while True:
        kept = np.flatnonzero(keep)
        span = read_span(kept) if len(kept) >= 2 else None
        if span is None:
            return keep, glitches, []
        r0, r1 = span
        lo, hi = max(r0 - 1, 0), min(r1 + 1, len(kept) - 1)
        t, c = t_s[kept], t_world_cam_m[kept]
        step_m = np.linalg.norm(np.diff(c[lo:hi + 1], axis=0), axis=1)  # [hi - lo]
        bad = lo + np.flatnonzero(_too_fast(np.diff(t[lo:hi + 1]), step_m))
        drop = np.zeros(len(kept), bool)
        jumps: list[tuple[int, int]] = []
        for k in (int(x) for x in bad):
            if drop[k] or drop[k + 1]:  # a step to or from a row already found to be a glitch
                continue
            found = _glitch_around(t, c, k)
            if found is None:
                if r0 <= k < r1:
                    jumps.append((int(kept[k]), int(kept[k + 1])))
                continue
            before, first, last, after = found
            drop[first:last + 1] = True
            away_m = np.linalg.norm(c[first:last + 1] - c[before], axis=1)
            glitches.append(PoseGlitch(int(kept[before]), int(kept[first]), int(kept[last]), int(kept[after]),
                                       float(away_m.max()), float(away_m[0] / (t[first] - t[before]))))
        if jumps:
            return keep, glitches, jumps
        if not drop.any():
            return keep, glitches, []
        keep[kept[drop]] = False


def _frame_list(frames: np.ndarray) -> str:
    """Frame indices ``[K]`` (increasing) as ``frame 3`` / ``frames 0-1, 4``."""
    frames = [int(f) for f in frames]
    if not frames:
        return "no frame"
    parts, start = [], frames[0]
    for prev, cur in zip(frames, frames[1:] + [None]):
        if cur != prev + 1:
            parts.append(f"{start}" if start == prev else f"{start}-{prev}")
            start = cur
    return ("frame " if len(frames) == 1 else "frames ") + ", ".join(parts)


def _line_span(rows: list[tuple[int, list[str]]], first: int, last: int) -> str:
    """``line 14`` or ``lines 14-16`` of rows ``first..last`` (time order; lines as in the file)."""
    lines = sorted(rows[k][0] for k in range(first, last + 1))
    if len(lines) == 1:
        return f"line {lines[0]}"
    return f"lines {lines[0]}-{lines[-1]}" if lines[-1] - lines[0] == len(lines) - 1 else \
        "lines " + ", ".join(str(n) for n in lines)


def check_groundtruth_speed(path: Path, rows: list[tuple[int, list[str]]], ts: np.ndarray,
                            t_world_cam_m: np.ndarray, frame_ts: np.ndarray | None = None,
                            max_dt: float = MAX_ASSOCIATION_DT_S) -> np.ndarray:
    """Hold ground truth to a camera's speed where the frames read it; drop glitch rows.

    ``rows`` ``[M]`` are the file's rows in time order, ``ts`` ``[M]`` their times (s, increasing),
    ``t_world_cam_m`` ``[M, 3]`` the camera centres, ``frame_ts`` ``[N]`` the times of the frames
    used (after ``dataset.max_frames``; None: every row counts). Only the rows those frames'
    ground truth is looked up from (:func:`lookup_groundtruth`), with one row of margin each side,
    are judged (:func:`screen_pose_jumps`): rows of other times (before the clip, after
    ``max_frames``) are never the frames' poses. Rows that jump faster than
    ``MAX_CAMERA_SPEED_M_PER_S`` away and come back within ``MAX_GLITCH_ROWS`` rows (a marker swap)
    are dropped with a warning naming the file, the lines and the frames that read them; those
    frames then take their ground truth from the rows left, as every frame does: interpolated
    between the rows around them when at most ``MAX_GT_INTERPOLATION_GAP_S`` apart, else the nearest
    within ``max_dt``, else none.

    Returns:
        ``[M]`` bool, the rows kept.

    Raises:
        DatasetError: a jump the path goes on from (poses of two places: the scene would be mapped
            twice), naming the file, both lines and times, the distance, the speed, the frames on
            each side and how many such jumps there are.
    """
    if frame_ts is None:
        def read_span(kept: np.ndarray):
            return 0, len(kept) - 1
    else:
        frame_ts = np.asarray(frame_ts, dtype=np.float64)

        def read_span(kept: np.ndarray):
            a, b = _rows_read(ts[kept], frame_ts, max_dt)
            read = np.concatenate([a[a >= 0], b[b >= 0]])
            return (int(read.min()), int(read.max())) if len(read) else None

    keep, glitches, jumps = screen_pose_jumps(ts, t_world_cam_m, read_span)
    if jumps:
        a, b = jumps[0]
        (line_a, row_a), (line_b, row_b) = rows[a], rows[b]
        step_m = float(np.linalg.norm(t_world_cam_m[b] - t_world_cam_m[a]))
        dt_s = float(ts[b] - ts[a])
        more = f"; {len(jumps) - 1} more such jump(s) follow" if len(jumps) > 1 else ""
        frames = ""
        if frame_ts is not None:
            kept = np.flatnonzero(keep)
            ra, rb = _rows_read(ts[kept], frame_ts, max_dt)
            pa, pb = int(np.searchsorted(kept, a)), int(np.searchsorted(kept, b))
            before = np.flatnonzero((ra >= 0) & (rb <= pa))
            after = np.flatnonzero(ra >= pb)
            across = np.flatnonzero((ra == pa) & (rb == pb))
            sides = [(which, f) for which, f in (("before", before), ("after", after), ("across", across)) if len(f)]
            frames = "; " + ", ".join(f"{_frame_list(f)} {'read poses ' if n == 0 else ''}{which} it"
                                      for n, (which, f) in enumerate(sides))
            frames += f": the scene would be mapped twice, {step_m:.3g} m apart"
        raise DatasetError(path, f"the camera moves {step_m:.3g} m in {dt_s:.3g} s from line {line_a} (t = "
                                 f"{row_a[0][:40]}) to this line (t = {row_b[0][:40]}): {step_m / dt_s:.3g} m/s, "
                                 f"faster than the {MAX_CAMERA_SPEED_M_PER_S:g} m/s any hand-held or robot camera "
                                 f"moves, and the path goes on from there (no motion-capture glitch: it does not "
                                 f"come back within {MAX_GLITCH_ROWS} rows){frames}{more}; these poses are not one "
                                 "camera's path (a wrong or merged file): correct or remove those lines", line_b)
    if glitches:
        _warn_glitches(path, rows, ts, keep, glitches, frame_ts, max_dt)
    return keep


def _warn_glitches(path: Path, rows: list[tuple[int, list[str]]], ts: np.ndarray, keep: np.ndarray,
                   glitches: list[PoseGlitch], frame_ts: np.ndarray | None, max_dt: float) -> None:
    """One warning per dropped glitch (at most ``MAX_GLITCHES_LOGGED``): its lines, times, how far
    and fast it jumps, the frames that read those rows and what those frames read now."""
    if frame_ts is not None:
        a0, b0 = _rows_read(ts, frame_ts, max_dt)  # as the file is written
        a1, b1 = _rows_read(ts[keep], frame_ts, max_dt)  # without the glitches
    for g in glitches[:MAX_GLITCHES_LOGGED]:
        what = (f"{_line_span(rows, g.first, g.last)} (t = {rows[g.first][1][0][:40]}"
                + (f" - {rows[g.last][1][0][:40]}" if g.last > g.first else "") + ")")
        frames = ""
        if frame_ts is not None:
            hit = ((a0 >= g.first) & (a0 <= g.last)) | ((b0 >= g.first) & (b0 <= g.last))
            hit_idx = np.flatnonzero(hit)
            if not len(hit_idx):
                frames = "; no frame reads " + ("it" if g.first == g.last else "them")
            else:
                interp = int((hit & (a1 >= 0) & (a1 != b1)).sum())
                near = int((hit & (a1 >= 0) & (a1 == b1)).sum())
                none = int((hit & (a1 < 0)).sum())
                now = [f"{n} {text}" for n, text in (
                    (interp, f"interpolated between the rows around {'it' if g.first == g.last else 'them'} (at "
                             f"most {MAX_GT_INTERPOLATION_GAP_S:g} s apart)"),
                    (near, f"from the nearest row left within {max_dt * 1000:.0f} ms"),
                    (none, "without ground truth (no row left near enough)")) if n]
                reads = ("reads" if len(hit_idx) == 1 else "read") + (" it" if g.first == g.last else " them")
                frames = f"; {_frame_list(hit_idx)} {reads}: now " + ", ".join(now)
        logger.warning("%s: %s %s %.3g m away from line %d and back to line %d (%.3g m/s, faster than the %g m/s "
                       "a camera moves): a motion-capture glitch (a marker swap?), left out%s", path, what,
                       "jumps" if g.first == g.last else "jump", g.distance_m, rows[g.before][0], rows[g.after][0],
                       g.speed_m_per_s, MAX_CAMERA_SPEED_M_PER_S, frames)
    if len(glitches) > MAX_GLITCHES_LOGGED:
        rest = glitches[MAX_GLITCHES_LOGGED:]
        named = ", ".join(_line_span(rows, g.first, g.last) for g in rest[:20]) + (", ..." if len(rest) > 20 else "")
        logger.warning("%s: %d more glitch(es) left out likewise (%s)", path, len(rest), named)


def check_unique_files(path: Path, rows: list[tuple[int, list[str]]], kind: str) -> None:
    """Refuse a list (``rows`` of :func:`read_list_file`, ``[timestamp, filename]``) naming one
    image file on two lines (``rgb/1.png`` and ``./rgb/1.png`` are one file): each time needs its
    own image, and a list repeating one would build the world from one view many times over.

    Raises:
        DatasetError: naming the list file, the later line and the line that named the file first.
    """
    first: dict[str, int] = {}
    for lineno, parts in rows:
        key = posixpath.normpath(parts[1])
        if key in first:
            raise DatasetError(path, f"{kind} image {parts[1][:80]!r} is also named on line {first[key]}: each "
                                     "timestamp needs its own image file", lineno)
        first[key] = lineno


def check_groundtruth_overlap(gt_path: Path, gt_ts: np.ndarray, gt_poses: np.ndarray, frames_path: Path,
                              frame_ts: np.ndarray, max_dt: float = MAX_ASSOCIATION_DT_S,
                              gt_lines: list[int] | None = None) -> None:
    """Refuse ground truth (times ``gt_ts`` ``[M]``, poses ``[M, 4, 4]``, file lines ``gt_lines``
    ``[M]`` when known) that gives no pose at any of the recording's frame times ``frame_ts`` ``[N]``
    (from ``frames_path``): the world would silently be mapped from estimated poses with no ATE.

    Poses that all end before the first frame or start after the last are another recording's, or
    a clock offset; poses around the frames that still give none have a gap where the frames are
    (the motion capture lost the camera), and the error names that gap.

    Raises:
        DatasetError: naming the ground-truth file and both time spans (and the offset between
            them), or the gap(s) in the poses (times and lines) and the frames they cover.
    """
    if len(gt_ts) == 0 or lookup_groundtruth(gt_ts, gt_poses, frame_ts, max_dt)[1].any():
        return
    t0, t1 = float(frame_ts.min()), float(frame_ts.max())
    head = (f"ground truth matches none of the {len(frame_ts)} frames: its poses span {gt_ts[0]:.3f} - "
            f"{gt_ts[-1]:.3f} s, the frames ({frames_path.name}) {t0:.3f} - {t1:.3f} s")
    if gt_ts[-1] < t0 or gt_ts[0] > t1:
        where = (f"the poses end {t0 - gt_ts[-1]:.3f} s before the first frame" if gt_ts[-1] < t0 else
                 f"the poses start {gt_ts[0] - t1:.3f} s after the last frame")
        raise DatasetError(gt_path, f"{head}; {where}; it is another recording's ground truth, or its clock is "
                                    "offset: correct its timestamps, or remove the file to map from estimated poses")
    line = (lambda k: f" (line {gt_lines[k]})") if gt_lines is not None else (lambda k: "")
    j = np.searchsorted(gt_ts, frame_ts)  # [N] frame i lies between rows j - 1 and j
    holes = []
    for jk in np.unique(j):
        frames = _frame_list(np.flatnonzero(j == jk))
        if jk == 0:
            holes.append(f"{frames} before its first pose (t = {gt_ts[0]:.3f}{line(0)})")
        elif jk == len(gt_ts):
            holes.append(f"{frames} after its last pose (t = {gt_ts[-1]:.3f}{line(len(gt_ts) - 1)})")
        else:
            holes.append(f"{frames} in a gap from t = {gt_ts[jk - 1]:.3f}{line(jk - 1)} to {gt_ts[jk]:.3f}"
                         f"{line(jk)}, {gt_ts[jk] - gt_ts[jk - 1]:.3g} s without a pose")
    shown = "; ".join(holes[:3]) + (f"; and {len(holes) - 3} more gap(s)" if len(holes) > 3 else "")
    raise DatasetError(gt_path, f"{head}; the poses have gaps where the frames are: {shown} (ground truth is "
                                f"interpolated across at most {MAX_GT_INTERPOLATION_GAP_S:g} s, or taken from a "
                                f"pose within {max_dt * 1000:.0f} ms): the motion capture lost the camera for the "
                                "whole clip; read frames the poses cover, or remove the file to map from estimated "
                                "poses")


def associate(ts_a: np.ndarray, ts_b: np.ndarray, max_dt: float = MAX_ASSOCIATION_DT_S) -> list[tuple[int, int]]:
    """Pair timestamps one-to-one by nearest time within ``max_dt`` (greedy, closest first).

    Same rule as TUM's ``associate.py``: all candidate pairs under ``max_dt`` are taken in order of
    increasing time difference, each timestamp used at most once. Returns pairs sorted by ``a``.
    """
    a = np.asarray(ts_a, dtype=np.float64)
    b = np.asarray(ts_b, dtype=np.float64)
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    lo = np.searchsorted(bs, a - max_dt, side="left")
    hi = np.searchsorted(bs, a + max_dt, side="right")
    n_cand = np.maximum(hi - lo, 0)  # [len(a)] candidates of each a
    # Candidate k of a[i] is bs[lo[i] + k]; as flat arrays (24 bytes per candidate, not a tuple each).
    cand_a = np.repeat(np.arange(len(a)), n_cand)
    first = np.cumsum(n_cand) - n_cand
    pos = np.arange(int(n_cand.sum())) + np.repeat(lo - first, n_cand)
    cand_b = order_b[pos]
    dt = np.abs(bs[pos] - a[cand_a])
    used_a = np.zeros(len(a), bool)
    used_b = np.zeros(len(b), bool)
    pairs = []
    for k in np.lexsort((cand_b, cand_a, dt)):  # by time difference, ties by a then b
        i, j = int(cand_a[k]), int(cand_b[k])
        if used_a[i] or used_b[j]:
            continue
        used_a[i] = used_b[j] = True
        pairs.append((i, j))
    pairs.sort()
    return pairs


def _check_association_density(rgb_path: Path, depth_path: Path, rgb_rows, rgb_ts: np.ndarray,
                               depth_ts: np.ndarray, max_dt: float) -> None:
    """Refuse lists where many depth frames fall within ``max_dt`` of one RGB frame: real sensors
    run at <= 100 Hz (a 40 ms window holds a few frames), so this is a unit error (timestamps not
    in seconds) or garbage, and association would consider every pair (quadratic memory)."""
    n = np.searchsorted(depth_ts, rgb_ts + max_dt, side="right") - np.searchsorted(depth_ts, rgb_ts - max_dt, side="left")
    worst = int(np.argmax(n)) if len(n) else 0
    if len(n) and n[worst] > MAX_DEPTH_FRAMES_PER_RGB_WINDOW:
        raise DatasetError(depth_path, f"{int(n[worst])} depth frames lie within {max_dt * 1000:.0f} ms of the RGB "
                                       f"frame at {rgb_path.name} line {rgb_rows[worst][0]} (at most "
                                       f"{MAX_DEPTH_FRAMES_PER_RGB_WINDOW} expected): are the timestamps in seconds?")


def _rows_read(gt_ts: np.ndarray, t: np.ndarray, max_dt: float = MAX_ASSOCIATION_DT_S) -> tuple[
        np.ndarray, np.ndarray]:
    """The ground-truth rows (of times ``gt_ts`` ``[M]``, increasing) each time in ``t`` ``[N]``
    reads, as :func:`lookup_groundtruth` uses them: ``(a [N], b [N])`` int, the bracketing rows
    ``j - 1, j`` when interpolated, ``(k, k)`` for the nearest row ``k`` within ``max_dt``, ``(-1,
    -1)`` for none."""
    t = np.asarray(t, dtype=np.float64)
    m = len(gt_ts)
    a = np.full(len(t), -1, np.int64)
    b = np.full(len(t), -1, np.int64)
    if m == 0:
        return a, b
    j = np.searchsorted(gt_ts, t)
    inner = (j > 0) & (j < m)
    interp = np.zeros(len(t), bool)
    interp[inner] = gt_ts[j[inner]] - gt_ts[j[inner] - 1] <= MAX_GT_INTERPOLATION_GAP_S
    lo, hi = np.clip(j - 1, 0, m - 1), np.clip(j, 0, m - 1)
    best = np.where(np.abs(gt_ts[lo] - t) <= np.abs(gt_ts[hi] - t), lo, hi)  # ties: the earlier row
    near = ~interp & (np.abs(gt_ts[best] - t) <= max_dt)
    a[interp], b[interp] = j[interp] - 1, j[interp]
    a[near] = b[near] = best[near]
    return a, b


def lookup_groundtruth(
    gt_ts: np.ndarray, gt_poses: np.ndarray, t: np.ndarray, max_dt: float = MAX_ASSOCIATION_DT_S
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth pose at each time in ``t`` ``[N]``.

    Inside the motion-capture span the pose is interpolated (linear translation, slerp rotation)
    between the bracketing samples when they are at most ``MAX_GT_INTERPOLATION_GAP_S`` apart;
    otherwise, and at the ends, the nearest sample is used if it lies within ``max_dt`` (TUM's
    ``associate.py`` rule).

    Returns:
        ``(T_world_cam [N, 4, 4] with NaN where unknown, has_gt [N] bool)``.
    """
    t = np.asarray(t, dtype=np.float64)
    out = np.full((len(t), 4, 4), np.nan)
    a, b = _rows_read(gt_ts, t, max_dt)
    for k in np.flatnonzero(a >= 0):
        i, j = int(a[k]), int(b[k])
        out[k] = gt_poses[i] if i == j else interpolate_pose(gt_ts[i], gt_poses[i], gt_ts[j], gt_poses[j], t[k])
    return out, a >= 0


@dataclass
class FrameManifest:
    """The frames of one RGB-D sequence: which files, when, seen by which camera, with what ground truth.

    Attributes:
        dataset: registry name (the Dagster partition key).
        root: folder holding the sequence; file paths below are relative to it.
        camera: intrinsics and depth scale.
        timestamps_s: ``[N]`` frame times: when the depth image was taken. A frame's pose (estimated
            or ground truth) is the camera's at that time: the tracker's geometric term and the
            fused points come from the depth image, so stamping it with the colour image's time
            misplaces it by the camera's motion in between (TUM fr1: depth ~15 ms before colour at
            0.36 m/s, ~5 mm; ATE against ground truth at the colour times 0.47 cm, at the depth
            times 0.30 cm).
        depth_timestamps_s: ``[N]`` the depth images' timestamps (the frame times).
        rgb_timestamps_s: ``[N]`` the paired colour images' timestamps (within the association
            gap of the depth's); None when they are the frame times.
        rgb_files, depth_files: ``N`` relative paths.
        T_world_cam_gt: ``[N, 4, 4]`` ground-truth camera-to-world, NaN where unknown.
        has_gt: ``[N]`` bool.
        content_hash: sha256 over the list files (or pose / intrinsics files) and every image used
            (data version of the raw data).
        source: where the frames came from and how to decode them, saved with the manifest:
            ``layout`` (``tum``, ``7scenes``, ``replica``, ``scannet``, ``bag``), ``path``, and the
            decoding parameters :meth:`read_rgb` / :meth:`read_depth_m` apply:
            ``depth_invalid_raw`` (raw depth values meaning "no reading", besides 0) and
            ``colour_camera`` (camera dict of the colour images when they differ from the depth
            camera ``camera``; colour is then resampled onto the depth camera). Manifests saved
            before these keys existed decode as TUM (neither key).

    Callers read frames with :meth:`read_rgb` and :meth:`read_depth_m`, never from the paths
    directly, so no caller needs to know the layout.
    """

    dataset: str
    root: Path
    camera: CameraIntrinsics
    timestamps_s: np.ndarray
    depth_timestamps_s: np.ndarray
    rgb_files: list[str]
    depth_files: list[str]
    T_world_cam_gt: np.ndarray
    has_gt: np.ndarray
    content_hash: str = ""
    source: dict = field(default_factory=dict)
    rgb_timestamps_s: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return len(self.timestamps_s)

    def colour_delay_s(self, i: int) -> float:
        """How long after frame ``i``'s depth image its colour image was taken (s; 0 when the
        manifest has no colour times)."""
        if self.rgb_timestamps_s is None:
            return 0.0
        return float(self.rgb_timestamps_s[i] - self.timestamps_s[i])

    def rgb_path(self, i: int) -> Path:
        return self.root / self.rgb_files[i]

    def depth_path(self, i: int) -> Path:
        return self.root / self.depth_files[i]

    @property
    def colour_camera(self) -> CameraIntrinsics:
        """The camera of the colour files (``camera`` unless ``source`` names another one)."""
        spec = self.source.get("colour_camera")
        return CameraIntrinsics.from_dict(spec) if spec else self.camera

    def read_rgb(self, i: int) -> np.ndarray:
        """Colour of frame ``i`` on the depth camera's pixel grid: ``[H, W, 3]`` uint8 (``H, W`` of
        ``camera``); resampled bilinearly when the colour camera differs (see ``source``)."""
        from atlas_pipeline.sensors.images import read_rgb, resample_rgb

        colour = self.colour_camera
        rgb = read_rgb(self.rgb_path(i), colour)
        return rgb if colour is self.camera else resample_rgb(rgb, colour, self.camera)

    def read_depth_m(self, i: int, allow_empty: bool = False) -> np.ndarray:
        """Depth of frame ``i`` in metres, ``[H, W]`` float32, 0 where there is no reading (the
        layout's invalid raw values included). An all-invalid image is a DatasetError unless
        ``allow_empty``."""
        from atlas_pipeline.sensors.images import read_depth_m

        invalid = tuple(int(v) for v in self.source.get("depth_invalid_raw") or ())
        return read_depth_m(self.depth_path(i), self.camera, allow_empty=allow_empty, invalid_raw=invalid)

    # ---- persistence: frames.parquet (one row per frame) + manifest.json -------------------
    def save(self, directory: Path) -> list[Path]:
        directory.mkdir(parents=True, exist_ok=True)
        t = np.full((self.n_frames, 3), np.nan)
        q = np.full((self.n_frames, 4), np.nan)
        if self.has_gt.any():
            t[self.has_gt], q[self.has_gt] = tq_from_pose(self.T_world_cam_gt[self.has_gt])
        table = pa.table({
            "frame_id": pa.array(np.arange(self.n_frames), pa.int64()),
            "timestamp_s": pa.array(self.timestamps_s, pa.float64()),
            "depth_timestamp_s": pa.array(self.depth_timestamps_s, pa.float64()),
            "rgb_timestamp_s": pa.array(self.timestamps_s if self.rgb_timestamps_s is None else self.rgb_timestamps_s,
                                        pa.float64()),
            "rgb_file": pa.array(self.rgb_files, pa.string()),
            "depth_file": pa.array(self.depth_files, pa.string()),
            "has_gt": pa.array(self.has_gt, pa.bool_()),
            **{f"gt_{k}": pa.array(t[:, i], pa.float64()) for i, k in enumerate("xyz")},
            **{f"gt_q{k}": pa.array(q[:, i], pa.float64()) for i, k in enumerate("xyzw")},
        })
        frames = directory / "frames.parquet"
        with atomic_path(frames) as tmp:
            pq.write_table(table, tmp)
        meta = directory / "manifest.json"
        write_json_atomic(meta, {
            "dataset": self.dataset,
            "root": str(self.root),
            "camera": self.camera.to_dict(),
            "n_frames": self.n_frames,
            "n_with_ground_truth": int(self.has_gt.sum()),
            "content_hash": self.content_hash,
            "source": self.source,
        })
        return [frames, meta]

    @classmethod
    def load(cls, directory: Path) -> "FrameManifest":
        meta_path = directory / "manifest.json"
        frames_path = directory / "frames.parquet"
        if not meta_path.is_file() or not frames_path.is_file():
            raise ArtifactError(f"{directory}: frame manifest is missing manifest.json or frames.parquet")
        meta = json.loads(meta_path.read_text())
        df = pq.read_table(frames_path).to_pandas()
        has = df["has_gt"].to_numpy(bool)
        t = df[["gt_x", "gt_y", "gt_z"]].to_numpy(np.float64)
        q = df[["gt_qx", "gt_qy", "gt_qz", "gt_qw"]].to_numpy(np.float64)
        T = np.full((len(df), 4, 4), np.nan)
        if has.any():
            T[has] = pose_from_tq(t[has], q[has])
        return cls(
            dataset=meta["dataset"],
            root=Path(meta["root"]),
            camera=CameraIntrinsics.from_dict(meta["camera"]),
            timestamps_s=df["timestamp_s"].to_numpy(np.float64),
            depth_timestamps_s=df["depth_timestamp_s"].to_numpy(np.float64),
            rgb_files=df["rgb_file"].tolist(),
            depth_files=df["depth_file"].tolist(),
            T_world_cam_gt=T,
            has_gt=has,
            content_hash=meta.get("content_hash", ""),
            source=meta.get("source", {}),
            rgb_timestamps_s=df["rgb_timestamp_s"].to_numpy(np.float64) if "rgb_timestamp_s" in df else None,
        )


def check_tum_layout(root: Path) -> None:
    """Raise DatasetError unless ``root`` looks like a TUM sequence (folder with rgb.txt, depth.txt)."""
    if not root.is_dir():
        raise DatasetError(root, "dataset folder not found")
    for name in ("rgb.txt", "depth.txt"):
        problem = file_problem(root / name)
        if problem == "not found":
            raise DatasetError(root / name, "list file not found (expected TUM RGB-D layout)")
        if problem is not None:
            raise DatasetError(root / name, f"list file {problem}")


def _is_file(path: Path) -> bool:
    """``path.is_file()``, False also for names the OS refuses (too long), which pathlib raises for."""
    try:
        return path.is_file()
    except OSError:
        return False


def file_problem(path: Path) -> str | None:
    """Why ``path`` cannot be read as a file, in words (None: it is a regular file): ``not found``,
    ``is a directory``, ``is not a regular file (a FIFO)`` ... A FIFO or device named in a list
    would block or stream forever if opened, and calling a directory "not found" sends the user
    looking for a file that is there."""
    try:
        mode = path.stat().st_mode  # follows links: what opening it would read
    except FileNotFoundError:
        return "not found"
    except OSError as exc:  # name too long, a link loop, no permission on the folder
        return f"cannot be looked up ({exc.strerror or exc})"
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "is a directory"
    what = ("a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a file")
    return f"is not a regular file ({what})"


def _safe_member(root: Path, rel: str, list_path: Path, lineno: int) -> Path:
    """Resolve a file named in a list file, refusing paths that leave the dataset folder."""
    try:
        p = (root / rel).resolve()
    except (ValueError, OSError) as exc:  # embedded NUL byte, symlink loop, name too long
        raise DatasetError(list_path, f"invalid file path {rel[:80]!r} ({exc})", lineno) from None
    if not p.is_relative_to(root.resolve()):
        raise DatasetError(list_path, f"file path leaves the dataset folder: {rel!r}", lineno)
    return p


def load_tum_sequence(
    root: str | Path,
    camera: CameraIntrinsics,
    dataset: str,
    max_frames: int | None = None,
    max_dt: float = MAX_ASSOCIATION_DT_S,
) -> FrameManifest:
    """Read a TUM-layout folder into a :class:`FrameManifest`, checking every image header.

    Before any image is opened, rgb.txt and depth.txt must be in strictly increasing time order
    (:func:`increasing_timestamps`) and name each image file once (:func:`check_unique_files`), and
    ``groundtruth.txt``, when there is one, must read (:func:`read_groundtruth`: unit quaternions),
    give a pose at one frame at least (:func:`check_groundtruth_overlap`) and move at a camera's
    speed where the frames kept read it (:func:`check_groundtruth_speed`: glitch rows dropped).
    Every listed image must be a regular file (one that is
    missing, a directory or a FIFO is named as such, :func:`file_problem`) with the camera's size
    (header only): 8-bit colour PNG or JPEG for RGB, 16-bit single-channel PNG for depth; the first
    offending file is named with its list line.
    """
    root = Path(root)
    check_tum_layout(root)
    rgb_rows = read_list_file(root / "rgb.txt", 2)
    depth_rows = read_list_file(root / "depth.txt", 2)
    # Order is checked before any image is opened: a repeated timestamp would make association
    # drop a frame without saying why.
    rgb_ts = increasing_timestamps(root / "rgb.txt", rgb_rows)
    depth_ts = increasing_timestamps(root / "depth.txt", depth_rows)
    check_unique_files(root / "rgb.txt", rgb_rows, "rgb")
    check_unique_files(root / "depth.txt", depth_rows, "depth")
    _check_association_density(root / "rgb.txt", root / "depth.txt", rgb_rows, rgb_ts, depth_ts, max_dt)
    pairs = associate(rgb_ts, depth_ts, max_dt)
    if not pairs:
        raise DatasetError(root / "depth.txt", f"no depth frame within {max_dt * 1000:.0f} ms of any RGB frame")
    dropped = len(rgb_rows) - len(pairs)
    if dropped:
        logger.info("%s: %d RGB frames have no depth within %.0f ms and are skipped", root, dropped, max_dt * 1000)
    all_depth_ts = depth_ts[[j for _, j in pairs]]  # every frame's time, for the ground truth's check
    if max_frames is not None:
        pairs = pairs[:max_frames]
    if len(pairs) < 2:
        raise DatasetError(root, f"need at least 2 RGB-D frames, found {len(pairs)}")

    t_rgb = rgb_ts[[i for i, _ in pairs]]
    t_depth = depth_ts[[j for _, j in pairs]]
    # Ground truth is read and checked before any image is: a wrong file is named at once.
    gt_file = root / "groundtruth.txt"
    list_files = [root / "rgb.txt", root / "depth.txt"]
    gt_problem = file_problem(gt_file)
    if gt_problem is None:
        gt_rows, gt_ts, gt_tq = _parse_groundtruth(gt_file)
        gt_poses = pose_from_tq(gt_tq[:, :3], gt_tq[:, 3:])
        check_groundtruth_overlap(gt_file, gt_ts, gt_poses, root / "depth.txt", all_depth_ts, max_dt,
                                  [line for line, _ in gt_rows])
        # judged where the frames kept read it; glitch rows dropped
        keep = check_groundtruth_speed(gt_file, gt_rows, gt_ts, gt_tq[:, :3], t_depth, max_dt)
        T_gt, has_gt = lookup_groundtruth(gt_ts[keep], gt_poses[keep], t_depth, max_dt)  # at the frame (depth) times
        list_files.append(gt_file)
    elif gt_problem == "not found":  # optional: a recording without ground truth
        T_gt, has_gt = np.full((len(pairs), 4, 4), np.nan), np.zeros(len(pairs), bool)
    else:
        raise DatasetError(gt_file, f"ground-truth file {gt_problem}")

    rgb_files, depth_files, used_paths, used_names = [], [], [], []
    seen: dict[tuple[str, Path], int] = {}  # (list, resolved image) -> line: links and ".." naming one file twice
    for i, j in pairs:
        for rows, idx, kind, list_name, files in (
            (rgb_rows, i, "rgb", "rgb.txt", rgb_files),
            (depth_rows, j, "depth", "depth.txt", depth_files),
        ):
            lineno, parts = rows[idx]
            list_path = root / list_name
            path = _safe_member(root, parts[1], list_path, lineno)
            earlier = seen.setdefault((list_name, path), lineno)
            if earlier != lineno:
                raise DatasetError(list_path, f"{kind} image {parts[1][:80]!r} is the file line {earlier} names "
                                              f"({path}): each timestamp needs its own image file", lineno)
            problem = file_problem(path)
            if problem is not None:
                raise DatasetError(list_path, f"{kind} image {parts[1]!r} {problem}", lineno)
            if kind == "rgb":
                check_rgb_header(path, camera.width, camera.height, list_path, lineno)
            else:
                check_depth_header(path, camera.width, camera.height, list_path, lineno)
            files.append(parts[1])
            used_paths.append(path)
            used_names.append(parts[1])

    content_hash = sha256_files(list_files + used_paths, [p.name for p in list_files] + used_names)
    logger.info(
        "%s: %d RGB-D frames, %d with ground truth, %.1f s", dataset, len(pairs), int(has_gt.sum()),
        t_depth[-1] - t_depth[0],
    )
    return FrameManifest(
        dataset=dataset, root=root.resolve(), camera=camera, timestamps_s=t_depth.copy(),
        depth_timestamps_s=t_depth, rgb_timestamps_s=t_rgb, rgb_files=rgb_files, depth_files=depth_files,
        T_world_cam_gt=T_gt, has_gt=has_gt, content_hash=content_hash,
        source={"layout": "tum", "path": str(root.resolve()), "max_frames": max_frames},
    )
