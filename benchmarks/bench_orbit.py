"""Orbit video frames against the recording's own views ("every orbit frame sharp and
covered, on synthetic and on the shared teddy frames"; "the teddy orbit keeps the teddy in frame").

    python benchmarks/bench_orbit.py                          # synthetic, teddy, fr1 (when present)
    python benchmarks/bench_orbit.py --datasets teddy --unfitted

For each dataset the world is built as the main job builds it (default profile: ground-truth
keyframe poses where the dataset has them, the keyframe fit unless ``--unfitted``), and the orbit
video's path is planned by the function the ``demo_videos`` stage calls
(:func:`atlas_pipeline.viz.demo.orbit_trajectory`, ``video.orbit_frames`` poses). Every orbit
frame and every keyframe view is rendered, and per orbit frame:

* sharpness (mean gradient magnitude) and coverage (share of pixels with opacity > 0.5), each
  divided by the median over the keyframe views: the thresholds are the test's
  (``tests/test_camera_paths.py``: 0.7 and 0.8);
* whether the keyframes' point of attention is in frame: the point nearest to all their optical
  axes (least squares), projected inside the middle 80 % of the image; for teddy, that point is
  the teddy. The keyframe views' own share is printed beside it; when it is under 90 % the
  recording circled nothing (fr1's sideways sweep) and the check does not apply.

Exit status 1 when a threshold is missed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

SHARPNESS_RATIO_MIN = 0.7  # as tests/test_camera_paths.py
COVERAGE_RATIO_MIN = 0.8
IN_FRAME_MARGIN = 0.1  # the attention point must project this far (fraction of the size) inside the image
# The attention point counts only when the keyframes themselves frame it this often (a recording
# that circles an object); parallel lines of sight (fr1's sideways sweep) meet nowhere useful.
KEYFRAMES_FRAMING_MIN = 0.9


def attention_point(T_kf: np.ndarray) -> np.ndarray:
    """``[3]``: the point nearest to every keyframe's optical axis in the least-squares sense
    (where the recording's lines of sight meet: the object a recording circles)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for T in T_kf:
        d = T[:3, 2] / np.linalg.norm(T[:3, 2])
        P = np.eye(3) - np.outer(d, d)  # distance to the axis, across it
        A += P
        b += P @ T[:3, 3]
    return np.linalg.lstsq(A, b, rcond=None)[0]


def in_frame(p_world: np.ndarray, T: np.ndarray, K: np.ndarray, w: int, h: int) -> bool:
    pc = (p_world - T[:3, 3]) @ T[:3, :3]
    if pc[2] <= 0:
        return False
    u, v = K[0, 0] * pc[0] / pc[2] + K[0, 2], K[1, 1] * pc[1] / pc[2] + K[1, 2]
    return bool(IN_FRAME_MARGIN * w <= u <= (1 - IN_FRAME_MARGIN) * w and IN_FRAME_MARGIN * h <= v <= (1 - IN_FRAME_MARGIN) * h)


def run(name: str, unfitted: bool) -> dict | None:
    from bench_photometric import _load

    from atlas_pipeline.config import load_profile
    from atlas_pipeline.gaussian_world.render import render_gaussians
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.viz.camera_paths import image_sharpness
    from atlas_pipeline.viz.demo import orbit_trajectory

    manifest = _load(name)
    if manifest is None:
        return None
    cfg = load_profile("default")
    if unfitted:
        cfg = cfg.with_overrides({"mapping.fit.epochs": 0})
    fused = fuse(manifest, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(manifest, fused, cfg), cfg, manifest=manifest)
    cam, f = manifest.camera, world.field
    T_kf = np.asarray(world.T_world_cam_keyframes)
    orbit = orbit_trajectory(f, cfg, T_kf, camera_K=cam.K, image_size=(cam.width, cam.height))

    def stats(poses):
        sharp, cov = [], []
        for T in poses:
            r = render_gaussians(f.positions, f.scales, f.rotations_xyzw, f.colors, f.opacities, T, cam.K,
                                 cam.width, cam.height)
            sharp.append(image_sharpness(r.rgb))
            cov.append(float(np.mean(r.alpha > 0.5)))
        return np.array(sharp), np.array(cov)

    kf_sharp, kf_cov = stats(T_kf)
    sharp, cov = stats(orbit)
    target = attention_point(T_kf)
    framed = np.array([in_frame(target, T, cam.K, cam.width, cam.height) for T in orbit])
    kf_framed = np.array([in_frame(target, T, cam.K, cam.width, cam.height) for T in T_kf])
    s_ratio, c_ratio = sharp / np.median(kf_sharp), cov / np.median(kf_cov)
    return {"dataset": name, "pose_source": world.pose_source, "fitted": not unfitted, "orbit_frames": len(orbit),
            "sharpness_ratio_min": float(s_ratio.min()), "sharpness_ratio_median": float(np.median(s_ratio)),
            "coverage_ratio_min": float(c_ratio.min()), "coverage_ratio_median": float(np.median(c_ratio)),
            "coverage_min": float(cov.min()), "keyframe_coverage_median": float(np.median(kf_cov)),
            "attention_in_frame": float(framed.mean()), "attention_in_keyframes": float(kf_framed.mean()),
            "ok": bool(s_ratio.min() >= SHARPNESS_RATIO_MIN and c_ratio.min() >= COVERAGE_RATIO_MIN
                       and (kf_framed.mean() < KEYFRAMES_FRAMING_MIN or framed.all()))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["synthetic", "teddy", "fr1"], choices=["synthetic", "teddy", "fr1"])
    ap.add_argument("--unfitted", action="store_true", help="skip the keyframe fit (quicker; the path does not use it)")
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    rows = [r for r in (run(n, args.unfitted) for n in args.datasets) if r is not None]
    print(f"| dataset | poses | orbit frames | sharpness / keyframes' (min, median) | coverage / keyframes' (min, median) "
          f"| attention point in frame: orbit (keyframes) | ok |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['dataset']} | {r['pose_source']} | {r['orbit_frames']} | {r['sharpness_ratio_min']:.2f}, "
              f"{r['sharpness_ratio_median']:.2f} | {r['coverage_ratio_min']:.2f}, {r['coverage_ratio_median']:.2f} "
              f"| {100 * r['attention_in_frame']:.0f} % ({100 * r['attention_in_keyframes']:.0f} %"
              f"{'' if r['attention_in_keyframes'] >= KEYFRAMES_FRAMING_MIN else ': does not apply'}) "
              f"| {'yes' if r['ok'] else 'NO'} |")
    print(f"thresholds: sharpness >= {SHARPNESS_RATIO_MIN}, coverage >= {COVERAGE_RATIO_MIN} of the keyframe views' "
          f"medians, in every frame; the attention point inside the middle {100 - 200 * IN_FRAME_MARGIN:.0f} % in every frame")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
