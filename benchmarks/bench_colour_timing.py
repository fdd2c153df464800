"""When was each colour image taken? Photometric consistency of frame pairs under ground truth,
with each colour image placed at the pose of its depth time plus ``s`` times its colour delay
(the colour image's timestamp minus the depth image's).

For frames ``i`` and ``j`` (``j = i + 1 .. i + GAP``), the points of depth image ``i`` (at its
ground-truth pose) are projected into colour image ``i`` and colour image ``j``, each placed at
``GT(t_depth + s * delay)``; the figure is the mean absolute difference of the two colours (0-255,
pixels inside both images, the central half of the image only: the renderer's pinhole model ignores
TUM fr1's lens distortion, strongest at the border). The ``s`` with the smallest difference says
when the colour was taken: 1 = at its own timestamp, 0 = at the depth image's.

    python benchmarks/bench_colour_timing.py                           # fr1, teddy (when present)
    python benchmarks/bench_colour_timing.py --synthetic synthetic-handheld --sensor colour_delay_s=0.015
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

SCALES = (-1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0)
PAIR_GAP = 3  # pairs up to this many frames apart
CENTRAL = 0.5  # the central fraction of each image axis used
DEPTH_RANGE_M = (0.3, 4.0)
SHARED = ROOT.parent / "shared" / "data"


def _sample(rgb: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear colour ``[M, 3]`` float at pixel coordinates ``u, v`` ``[M]`` (inside the image)."""
    x0, y0 = np.floor(u).astype(int), np.floor(v).astype(int)
    ax, ay = (u - x0)[:, None], (v - y0)[:, None]
    img = rgb.astype(np.float32)
    top = img[y0, x0] * (1 - ax) + img[y0, x0 + 1] * ax
    bottom = img[y0 + 1, x0] * (1 - ax) + img[y0 + 1, x0 + 1] * ax
    return top * (1 - ay) + bottom * ay


def _project(X_world: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray, w: int, h: int):
    """Pixel coordinates ``[M]`` x2 and a mask of those inside the image (with a 1 px margin)."""
    Xc = (X_world - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    z = Xc[:, 2]
    ok = z > 0.05
    u = K[0, 0] * Xc[:, 0] / np.where(ok, z, 1) + K[0, 2]
    v = K[1, 1] * Xc[:, 1] / np.where(ok, z, 1) + K[1, 2]
    ok &= (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
    return u, v, ok


def consistency(m, gt_ts: np.ndarray, gt_poses: np.ndarray) -> dict[float, float]:
    """Mean absolute colour difference (0-255) of every pair, per delay scale ``s``."""
    from atlas_pipeline.sensors.tum import lookup_groundtruth

    cam = m.camera
    K, w, h = cam.K, cam.width, cam.height
    ys, xs = np.mgrid[0:h, 0:w]
    central = ((np.abs(xs - w / 2) < CENTRAL * w / 2) & (np.abs(ys - h / 2) < CENTRAL * h / 2))
    delays = np.array([m.colour_delay_s(i) for i in range(m.n_frames)])
    T_depth, ok_d = lookup_groundtruth(gt_ts, gt_poses, m.timestamps_s)
    rgbs = [m.read_rgb(i) for i in range(m.n_frames)]
    sums = {s: [0.0, 0] for s in SCALES}
    for s in SCALES:
        T_col, ok_c = lookup_groundtruth(gt_ts, gt_poses, m.timestamps_s + s * delays)
        for i in range(m.n_frames):
            if not (ok_d[i] and ok_c[i]):
                continue
            d = m.read_depth_m(i, allow_empty=True)
            keep = (d > DEPTH_RANGE_M[0]) & (d < DEPTH_RANGE_M[1]) & central
            z = d[keep]
            Xc = np.stack([(xs[keep] - K[0, 2]) * z / K[0, 0], (ys[keep] - K[1, 2]) * z / K[1, 1], z], axis=1)
            X = Xc @ T_depth[i][:3, :3].T + T_depth[i][:3, 3]
            ui, vi, oki = _project(X, T_col[i], K, w, h)
            for j in range(i + 1, min(m.n_frames, i + 1 + PAIR_GAP)):
                if not ok_c[j]:
                    continue
                uj, vj, okj = _project(X, T_col[j], K, w, h)
                both = oki & okj
                if both.sum() < 100:
                    continue
                diff = np.abs(_sample(rgbs[i], ui[both], vi[both]) - _sample(rgbs[j], uj[both], vj[both]))
                sums[s][0] += float(diff.mean(axis=1).sum())
                sums[s][1] += int(both.sum())
    return {s: a / n if n else float("nan") for s, (a, n) in sums.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--synthetic", nargs="*", default=[], metavar="PRESET")
    ap.add_argument("--sensor", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--no-real", action="store_true")
    args = ap.parse_args()
    import tempfile

    from atlas_pipeline.config import parse_set_overrides
    from atlas_pipeline.sensors.registry import read_dataset_manifest
    from atlas_pipeline.sensors.tum import read_groundtruth

    sensor = parse_set_overrides(args.sensor, "--sensor")
    seqs = []
    if args.synthetic:
        from bench_robustness import _synthetic_sequences

        tmp = tempfile.TemporaryDirectory(prefix="atlas-colour-timing-") if sensor else None
        seqs += [(q.name, read_dataset_manifest(q.entry)) for q in
                 _synthetic_sequences(args.synthetic, sensor, Path(tmp.name) if tmp else None)]
    if not args.no_real:
        from bench_photometric import _load

        for name in ("fr1", "teddy"):
            m = _load(name)
            if m is not None:
                seqs.append((name, m))
    print("mean |colour_i - colour_j| (0-255) of frame pairs, colour placed at t_depth + s * delay\n")
    print("| sequence | median delay ms | " + " | ".join(f"s={s:+.1f}" for s in SCALES) + " | best s |")
    print("|---|---|" + "---|" * (len(SCALES) + 1))
    for name, m in seqs:
        gt_ts, gt_poses = read_groundtruth(m.root / "groundtruth.txt")
        c = consistency(m, gt_ts, gt_poses)
        delay = np.median([m.colour_delay_s(i) for i in range(m.n_frames)]) * 1000
        best = min(c, key=c.get)
        print(f"| {name} | {delay:+.1f} | " + " | ".join(f"{c[s]:.3f}" for s in SCALES) + f" | {best:+.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
