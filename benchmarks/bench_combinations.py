"""Worlds made four ways times every consumer, on small real frames: each cell's outputs checked
for what they claim.

Worlds (:data:`WORLD_KINDS`), all from two halves of one real TUM recording (A: its first
``--frames`` frames, B: the next ``--frames``):

* ``built``: ``atlas-gs build --input A`` (mapped at the ground-truth poses, ``pose_source: auto``);
* ``estimated``: the same, mapped from the tracker's own poses (``mapping.pose_source=estimated``);
* ``extended``: ``built`` extended with B (``build --input B --extend built``): keyframes from two recordings;
* ``imported``: ``import-ply`` of ``built``'s ``gaussians.ply``: no recording, no keyframes.

Consumers (:data:`CONSUMERS`): localization of A (the world's own recording, or relocalized where
the world has none), relocalization of B, the transitions, the four exports, the viewer's data, a
demo video and the lineage. A cell checks what its output claims, not only that it exists: an
exported image's pose is the pose of the frame whose pixels it holds (matched to the source frames
by content, so a keyframe read from the wrong recording is caught), transitions name frames of the
localized recording, a report's anchor appears only for the world's own recording.

Usage::

    python benchmarks/bench_combinations.py                     # ../shared/data teddy, 30 + 30 frames
    python benchmarks/bench_combinations.py --data DIR --frames 40 --camera freiburg1

Prints one row per cell (``ok`` with its figures, or what is wrong) and exits 1 when any cell
fails. ``tests/test_combination_matrix.py`` runs the same cells.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import SHARED_DATA  # noqa: E402

WORLD_KINDS = ("built", "estimated", "extended", "imported")
# Where a pose of a frame is checked against that frame's ground truth: the tracker's error on
# these sequences is 1-3 cm, while a pose paired with another frame of the same recording half a
# second away is off by tens of centimetres.
POSE_TOLERANCE_M = 0.06
# Share of a recording's frames a localization must place (own recording, and a neighbouring
# recording of the same place relocalized with no start pose).
MIN_PLACED_OWN = 0.9
MIN_PLACED_OTHER = 0.8
FAST_BUILD = ("--set", "mapping.fit.epochs=0")
DEFAULT_SEQUENCE = "tum_fr3_teddy_100"


class CellFailure(AssertionError):
    """A cell whose output does not hold what it claims."""


@dataclass
class Recording:
    """One half of the source recording: its folder and, per frame, a digest of its colour pixels,
    of its depth in metres and its ground-truth pose (``T_world_cam_gt [N, 4, 4]``, NaN where
    unknown)."""

    name: str
    path: Path
    pixel_digests: list[str]
    T_world_cam_gt: np.ndarray
    depth_digests: list[str] = field(default_factory=list)


@dataclass
class Setup:
    """The recordings and the worlds built from them."""

    root: Path
    camera: str
    a: Recording
    b: Recording
    worlds: dict[str, Path] = field(default_factory=dict)
    alignments: dict[str, np.ndarray] = field(default_factory=dict)
    build_s: dict[str, float] = field(default_factory=dict)

    def frame_of(self, digest: str) -> tuple[Recording, int]:
        """The recording and frame whose colour pixels have ``digest``."""
        for rec in (self.a, self.b):
            if digest in rec.pixel_digests:
                return rec, rec.pixel_digests.index(digest)
        raise CellFailure("an exported image holds pixels of no frame of either recording")


def cli(*argv: str, expect: int = 0) -> str:
    """Run ``atlas-gs argv`` in this process; its stdout, or a CellFailure on another exit code."""
    from assets.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(argv))
    if rc != expect:
        raise CellFailure(f"atlas-gs {' '.join(argv)} exited {rc}, expected {expect}: "
                          f"{(err.getvalue() or out.getvalue()).strip()[-400:]}")
    return out.getvalue()


def _digest(image: np.ndarray) -> str:
    """A digest of an image's values (colour: its first three channels)."""
    values = image[..., :3] if image.ndim == 3 else image
    return hashlib.sha1(np.ascontiguousarray(values).tobytes()).hexdigest()


def _read_rgb(path: Path) -> np.ndarray:
    """``[H, W, 3]`` uint8 of an image file (an export's, or a source frame's)."""
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def split_recording(src: Path, out: Path, start: int, stop: int) -> Path:
    """A TUM folder with frames ``[start, stop)`` of ``src`` (list files trimmed, images copied,
    the whole ground truth kept)."""
    out.mkdir(parents=True)
    for sub in ("rgb", "depth"):
        (out / sub).mkdir()
        rows = [r for r in (src / f"{sub}.txt").read_text().splitlines() if r.strip() and not r.startswith("#")]
        for row in rows[start:stop]:
            shutil.copy2(src / row.split()[1], out / row.split()[1])
        (out / f"{sub}.txt").write_text("\n".join(rows[start:stop]) + "\n")
    shutil.copy2(src / "groundtruth.txt", out / "groundtruth.txt")
    return out


def _manifest(path: Path, camera: str):
    from atlas_pipeline.sensors.camera import TUM_CAMERAS
    from atlas_pipeline.sensors.registry import DatasetEntry, read_dataset_manifest

    return read_dataset_manifest(DatasetEntry(path.name, "tum", path, camera=TUM_CAMERAS[camera]))


def _recording(path: Path, camera: str) -> Recording:
    m = _manifest(path, camera)
    digests = [_digest(_read_rgb(m.root / f)) for f in m.rgb_files]
    depth = [_digest(m.read_depth_m(i, allow_empty=True)) for i in range(m.n_frames)]
    return Recording(path.name, path, digests, np.asarray(m.T_world_cam_gt, np.float64), depth)


def build_worlds(root: Path, source: Path, n_frames: int, camera: str) -> Setup:
    """Split ``source`` into A and B under ``root`` and build the four worlds from them."""
    a = split_recording(source, root / "rec_a", 0, n_frames)
    b = split_recording(source, root / "rec_b", n_frames, 2 * n_frames)
    setup = Setup(root, camera, _recording(a, camera), _recording(b, camera))
    w = root / "worlds"
    steps: dict[str, tuple[str, ...]] = {
        "built": ("build", "--input", str(a), "--camera", camera, "--output", str(w / "built"), *FAST_BUILD),
        "estimated": ("build", "--input", str(a), "--camera", camera, "--output", str(w / "estimated"), *FAST_BUILD,
                      "--set", "mapping.pose_source=estimated"),
        "extended": ("build", "--input", str(b), "--camera", camera, "--extend", str(w / "built"),
                     "--output", str(w / "extended"), *FAST_BUILD),
        "imported": ("import-ply", str(w / "built" / "gaussians.ply"), "--output", str(w / "imported")),
    }
    for kind in WORLD_KINDS:
        t0 = time.perf_counter()
        cli(*steps[kind])
        setup.build_s[kind] = time.perf_counter() - t0
        setup.worlds[kind] = w / kind
    return setup


def world_copy(setup: Setup, kind: str, tag: str) -> Path:
    """A fresh copy of world ``kind`` for a consumer that writes into it."""
    dst = setup.root / "cells" / f"{kind}-{tag}"
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(setup.worlds[kind], dst)
    return dst


def world_to_ground_truth(setup: Setup, kind: str) -> np.ndarray:
    """``[4, 4]`` S with ``S @ T_world_cam`` in the ground truth's frame: the identity for a world
    mapped at ground-truth poses (or imported from one), else the rigid ATE alignment of recording
    A localized in the world (every placed frame, not the few an export holds)."""
    if kind not in setup.alignments:
        S = np.eye(4)
        if kind == "estimated":
            from atlas_pipeline.localization.metrics import align_rigid

            rep = _report(_localized(setup, kind, "alignment"))
            ok = np.isfinite(rep.T_world_cam).all(axis=(1, 2)) & np.isfinite(setup.a.T_world_cam_gt).all(axis=(1, 2))
            S = align_rigid(rep.T_world_cam[ok], setup.a.T_world_cam_gt[ok])
        setup.alignments[kind] = S
    return setup.alignments[kind]


def check_poses_of_frames(setup: Setup, digests: list[str], T_world_cam: np.ndarray,
                          S_gt_world: np.ndarray | None = None) -> dict[str, Any]:
    """Each image (by its pixels' digest) at the pose of the frame it is: ``S_gt_world @ T_world_cam``
    (:func:`world_to_ground_truth`; None: the identity) against the ground truth of that frame."""
    frames = [setup.frame_of(d) for d in digests]
    names = [(rec.name, i) for rec, i in frames]
    if len(set(names)) != len(names):
        raise CellFailure("two images are the same source frame")
    T_gt = np.stack([rec.T_world_cam_gt[i] for rec, i in frames])
    known = np.isfinite(T_gt).all(axis=(1, 2))
    if not known.any():
        raise CellFailure("none of the images' frames has ground truth")
    S = np.eye(4) if S_gt_world is None else S_gt_world
    T_est = S @ np.asarray(T_world_cam, np.float64)[known]
    err = np.linalg.norm(T_est[:, :3, 3] - T_gt[known][:, :3, 3], axis=1)
    worst = int(np.argmax(err))
    if err[worst] > POSE_TOLERANCE_M:
        rec, i = [f for f, k in zip(frames, known) if k][worst]
        raise CellFailure(f"an image (frame {i} of {rec.name}) carries a pose {err[worst] * 100:.1f} cm "
                          f"from that frame's ground truth")
    return {"n_images": len(digests), "recordings": sorted({n for n, _ in names}),
            "max_pose_err_cm": round(float(err.max()) * 100, 2)}


def _colmap_poses(model: Path) -> tuple[list[str], np.ndarray]:
    from atlas_pipeline.geometry import quat_xyzw_to_rotmat

    # An image is two lines: its pose and name, then its 2D points (empty here).
    lines = [r for r in (model / "images.txt").read_text().splitlines() if not r.startswith("#")]
    names, poses = [], []
    for row in lines[0::2]:
        f = row.split()
        if not f:
            break
        qw, qx, qy, qz, tx, ty, tz = map(float, f[1:8])
        T_cam_world = np.eye(4)
        T_cam_world[:3, :3] = quat_xyzw_to_rotmat(np.array([qx, qy, qz, qw]))
        T_cam_world[:3, 3] = (tx, ty, tz)
        names.append(f[9])
        poses.append(np.linalg.inv(T_cam_world))
    return names, np.stack(poses)


def _localized(setup: Setup, kind: str, tag: str) -> Path:
    """A copy of world ``kind`` with recording A localized in it (relocalized when the world is
    not A's)."""
    world = world_copy(setup, kind, tag)
    extra = ("--relocalize",) if kind == "imported" else ()
    cli("localize", "--world", str(world), "--input", str(setup.a.path), "--camera", setup.camera, *extra, expect=0)
    return world


def _report(world: Path):
    from atlas_pipeline.localization.localizer import LocalizationReport

    return LocalizationReport.load(world)


def _check_report(setup: Setup, kind: str, rec: Recording, world: Path, own: bool, min_placed: float) -> dict[str, Any]:
    rep = _report(world)
    if len(rep.status) != len(rec.pixel_digests):
        raise CellFailure(f"the report has {len(rep.status)} frames, the recording {len(rec.pixel_digests)}")
    placed = np.array([s in ("anchor", "tracked", "relocalized") for s in rep.status])
    if "anchor" in rep.status and not own:
        raise CellFailure("a recording that is not the world's own was given the world's anchor pose")
    if placed.mean() < min_placed:
        raise CellFailure(f"placed {placed.mean():.0%} of the frames (at least {min_placed:.0%} expected)")
    figures = check_poses_of_frames(setup, [rec.pixel_digests[i] for i in np.flatnonzero(placed)],
                                    rep.T_world_cam[placed], world_to_ground_truth(setup, kind))
    return {"placed": f"{placed.mean():.0%}", "max_pose_err_cm": figures["max_pose_err_cm"],
            "outcome": rep.summary.get("outcome")}


def cell_localize(setup: Setup, kind: str) -> dict[str, Any]:
    world = _localized(setup, kind, "localize")
    return _check_report(setup, kind, setup.a, world, own=kind != "imported", min_placed=MIN_PLACED_OWN)


def cell_relocalize(setup: Setup, kind: str) -> dict[str, Any]:
    world = world_copy(setup, kind, "relocalize")
    cli("localize", "--world", str(world), "--input", str(setup.b.path), "--camera", setup.camera, "--relocalize")
    return _check_report(setup, kind, setup.b, world, own=False, min_placed=MIN_PLACED_OTHER)


def cell_log_transitions(setup: Setup, kind: str) -> dict[str, Any]:
    import pandas as pd

    from atlas_pipeline.scene_memory.bundle import load_world_bundle

    world = _localized(setup, kind, "transitions")
    cli("log-transitions", "--world", str(world), "--input", str(setup.a.path), "--camera", setup.camera)
    df = pd.read_parquet(world / "transitions.parquet")
    rep, bundle = _report(world), load_world_bundle(world)
    n = len(rep.status)
    if len(df) != n - 1:
        raise CellFailure(f"{len(df)} transitions for {n} frames")
    if not ((df["frame_id_after"] - df["frame_id_before"]) == 1).all() or df["frame_id_after"].max() >= n:
        raise CellFailure("transitions name frames outside the localized recording")
    if set(df["map_id"]) != {bundle.map_id} or set(df["n_gaussians"]) != {len(bundle.field)}:
        raise CellFailure("transitions name another map or Gaussian count than the world holds")
    ts = np.asarray(rep.timestamps_s)
    if not np.allclose(df["timestamp_after_s"], ts[df["frame_id_after"]]):
        raise CellFailure("a transition's timestamp is not its frame's")
    return {"rows": len(df), "valid": int(df["valid"].sum())}


def _export(setup: Setup, world: Path, fmt: str, tag: str, *argv: str, expect: int = 0) -> Path:
    out = setup.root / "exports" / tag
    if out.exists():
        shutil.rmtree(out)
    cli("export", str(world), "--format", fmt, "--output", str(out), *argv, expect=expect)
    return out


def cell_export_colmap(setup: Setup, kind: str) -> dict[str, Any]:
    figures: dict[str, Any] = {}
    if kind == "imported":  # no keyframes and no localization: nothing to pair poses with
        _export(setup, setup.worlds[kind], "colmap", f"{kind}-colmap-kf", expect=2)
    else:
        out = _export(setup, setup.worlds[kind], "colmap", f"{kind}-colmap-kf")
        names, T = _colmap_poses(out / "sparse" / "0")
        digests = [_digest(_read_rgb(out / "images" / n)) for n in names]
        figures["keyframes"] = check_poses_of_frames(setup, digests, T, world_to_ground_truth(setup, kind))
    world = _localized(setup, kind, "colmap")
    out = _export(setup, world, "colmap", f"{kind}-colmap-est")
    names, T = _colmap_poses(out / "sparse" / "0")
    digests = [_digest(_read_rgb(out / "images" / n)) for n in names]
    figures["estimated"] = check_poses_of_frames(setup, digests, T, world_to_ground_truth(setup, kind))
    return figures


def cell_export_nerfstudio(setup: Setup, kind: str) -> dict[str, Any]:
    world = _localized(setup, kind, "nerfstudio")
    out = _export(setup, world, "nerfstudio", f"{kind}-nerfstudio")
    frames = json.loads((out / "transforms.json").read_text())["frames"]
    opengl_to_opencv = np.diag([1.0, -1.0, -1.0, 1.0])
    T = np.stack([np.asarray(f["transform_matrix"], np.float64) @ opengl_to_opencv for f in frames])
    digests = [_digest(_read_rgb(out / f["file_path"])) for f in frames]
    return check_poses_of_frames(setup, digests, T, world_to_ground_truth(setup, kind))


def _world_bounds(world: Path, margin_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    from atlas_pipeline.scene_memory.bundle import load_world_bundle

    pos = load_world_bundle(world).field.positions
    return pos.min(axis=0) - margin_m, pos.max(axis=0) + margin_m


def cell_export_mesh(setup: Setup, kind: str) -> dict[str, Any]:
    from plyfile import PlyData

    world = _localized(setup, kind, "mesh") if kind == "imported" else setup.worlds[kind]
    poses = ("--poses", "estimated") if kind == "imported" else ()
    out = _export(setup, world, "mesh", f"{kind}-mesh", *poses)
    plys = sorted(out.glob("*.ply"))
    if not plys:
        raise CellFailure("the mesh export wrote no PLY")
    v = PlyData.read(str(plys[0]))["vertex"]
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1)
    lo, hi = _world_bounds(world)
    if len(xyz) == 0 or not ((xyz >= lo) & (xyz <= hi)).all():
        raise CellFailure("the mesh is empty or lies outside the world's Gaussians")
    return {"vertices": len(xyz)}


def cell_export_occupancy(setup: Setup, kind: str) -> dict[str, Any]:
    import yaml

    from atlas_pipeline.interop.occupancy import read_pgm

    world = _localized(setup, kind, "occupancy") if kind == "imported" else setup.worlds[kind]
    poses = ("--poses", "estimated") if kind == "imported" else ()
    out = _export(setup, world, "occupancy", f"{kind}-occupancy", *poses)
    meta = yaml.safe_load((out / "map.yaml").read_text())
    grid = read_pgm(out / meta["image"])
    occupied, free = int((grid == 0).sum()), int((grid == 254).sum())
    if occupied == 0 or free == 0:
        raise CellFailure(f"the occupancy map has {occupied} occupied and {free} free cells")
    if any(len(repr(float(x))) > 12 for x in meta["origin"]):
        raise CellFailure(f"the map origin {meta['origin']} is not rounded to the grid")
    # The depth each of the map's frames contributes is that frame's own, at that frame's pose.
    from atlas_pipeline.interop.frames import source_from_bundle
    from atlas_pipeline.interop.occupancy import keyframe_depths

    src = source_from_bundle(world, poses="estimated" if kind == "imported" else "keyframes")
    by_depth = {d: rec.pixel_digests[i] for rec in (setup.a, setup.b) for i, d in enumerate(rec.depth_digests)}
    used, T = [], []
    for T_world_cam, depth_m, _ in keyframe_depths(src):
        if _digest(depth_m) not in by_depth:
            raise CellFailure("the occupancy map reads a depth image of no frame of either recording")
        used.append(by_depth[_digest(depth_m)])
        T.append(T_world_cam)
    poses = check_poses_of_frames(setup, used, np.stack(T), world_to_ground_truth(setup, kind))
    return {"occupied": occupied, "free": free, "frames": poses["n_images"], "max_pose_err_cm": poses["max_pose_err_cm"]}


def cell_view(setup: Setup, kind: str) -> dict[str, Any]:
    from atlas_pipeline.viz import viewer

    data = viewer.load_viewer_data(setup.worlds[kind], read_dataset=True, layers=[])
    shown = [img for img in data.keyframe_images if img is not None]
    if kind != "imported" and not shown:
        raise CellFailure(f"no keyframe image shown ({'; '.join(data.notes)})")
    # Each thumbnail is that keyframe's own frame: the one at its pose.
    digests_by_thumb = {}
    for rec in (setup.a, setup.b):
        m = _manifest(rec.path, setup.camera)
        for i, f in enumerate(m.rgb_files):
            digests_by_thumb[_digest(viewer._thumbnail(_read_rgb(m.root / f)))] = rec.pixel_digests[i]
    matched = [digests_by_thumb.get(_digest(img)) for img in data.keyframe_images if img is not None]
    if None in matched:
        raise CellFailure("a keyframe thumbnail is no frame of either recording")
    T = np.stack([T for T, img in zip(data.T_world_cam_keyframes, data.keyframe_images) if img is not None]) \
        if shown else np.zeros((0, 4, 4))
    figures: dict[str, Any] = {"keyframes": len(data.keyframe_images), "with_image": len(shown)}
    if shown:
        figures.update(check_poses_of_frames(setup, matched, T, world_to_ground_truth(setup, kind)))
    return figures


def cell_demo_video(setup: Setup, kind: str) -> dict[str, Any]:
    import imageio.v3 as iio

    out = setup.root / "videos" / f"{kind}.mp4"
    out.parent.mkdir(parents=True, exist_ok=True)
    cli("demo-video", "--world", str(setup.worlds[kind]), "--output", str(out), "--mode", "orbit")
    frames = iio.imread(out)
    if len(frames) == 0 or frames.std() < 1.0:
        raise CellFailure("the orbit video is empty or blank")
    return {"frames": len(frames)}


def cell_lineage(setup: Setup, kind: str) -> dict[str, Any]:
    from atlas_pipeline.scene_memory.bundle import load_world_bundle, read_lineage

    text = cli("lineage", str(setup.worlds[kind]))
    lin = read_lineage(setup.worlds[kind])
    bundle = load_world_bundle(setup.worlds[kind])
    if lin["map_id"] != bundle.map_id or lin["map_id"] not in text:
        raise CellFailure("the lineage names another map than the world holds")
    if kind == "extended":
        parent = lin.get("parent") or {}
        if parent.get("map_id") != load_world_bundle(setup.worlds["built"]).map_id:
            raise CellFailure("the extended world's lineage does not name the world it extends")
    return {"map_id": lin["map_id"], "parent": (lin.get("parent") or {}).get("map_id")}


CONSUMERS: dict[str, Callable[[Setup, str], dict[str, Any]]] = {
    "localize": cell_localize,
    "relocalize": cell_relocalize,
    "log-transitions": cell_log_transitions,
    "export-colmap": cell_export_colmap,
    "export-nerfstudio": cell_export_nerfstudio,
    "export-mesh": cell_export_mesh,
    "export-occupancy": cell_export_occupancy,
    "view": cell_view,
    "demo-video": cell_demo_video,
    "lineage": cell_lineage,
}


def run_cell(setup: Setup, kind: str, consumer: str) -> tuple[bool, str, float]:
    """``(passed, figures or what is wrong, seconds)`` of one cell."""
    t0 = time.perf_counter()
    try:
        figures = CONSUMERS[consumer](setup, kind)
        return True, json.dumps(figures, default=str), time.perf_counter() - t0
    except CellFailure as exc:
        return False, str(exc), time.perf_counter() - t0
    except Exception as exc:  # a crash is a failed cell, reported as such
        return False, f"{type(exc).__name__}: {exc}", time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=SHARED_DATA / DEFAULT_SEQUENCE, help="a TUM RGB-D folder")
    ap.add_argument("--camera", default="freiburg3", help="its camera preset")
    ap.add_argument("--frames", type=int, default=30, help="frames in each half (A, B)")
    ap.add_argument("--workdir", type=Path, default=None, help="where to build (default: a temporary folder)")
    args = ap.parse_args(argv)
    if not (args.data / "rgb.txt").is_file():
        print(f"no TUM recording at {args.data}", file=sys.stderr)
        return 2
    import tempfile

    with tempfile.TemporaryDirectory(prefix="atlas-combos-") as tmp:
        root = args.workdir or Path(tmp)
        setup = build_worlds(root, args.data, args.frames, args.camera)
        print(f"data {args.data} ({args.frames} + {args.frames} frames, camera {args.camera})")
        print("worlds built in " + ", ".join(f"{k} {s:.1f} s" for k, s in setup.build_s.items()))
        failed = 0
        print(f"{'world':10s} {'consumer':18s} {'result':6s} {'s':>6s}  figures / problem")
        for kind in WORLD_KINDS:
            for consumer in CONSUMERS:
                ok, text, secs = run_cell(setup, kind, consumer)
                failed += not ok
                print(f"{kind:10s} {consumer:18s} {'ok' if ok else 'FAIL':6s} {secs:6.1f}  {text}", flush=True)
        print(f"{len(WORLD_KINDS) * len(CONSUMERS) - failed} of {len(WORLD_KINDS) * len(CONSUMERS)} cells pass")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
