"""Speed of the compiled Gaussian rasteriser against the NumPy reference.

Scene: a 4 x 4.5 x 2.6 m room seen from inside (walls, floor, ceiling, three boxes), surface
Gaussians placed where random camera rays hit it (so most are in view, 1-4 m away), flat discs
oriented with the surface: tangential standard deviations log-uniform in [3 mm, 20 mm], 1 mm
along the normal; 10 % of the Gaussians are behind the camera (culled). 640x480, fx = fy = 525
(Kinect-like); opacities 70 % in [0.8, 1], 30 % in [0.1, 0.8].

Run: ``python benchmarks/bench_render.py [--gaussians 200000] [--repeats 20] [--ref-gaussians N]``.
Prints frames per second of both renderers on the same input, the ratio, the first-call time (JIT
compile or cache load) and the largest difference between the two images.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_pipeline.geometry import look_at, rotmat_to_quat_xyzw  # noqa: E402
from atlas_pipeline.gaussian_world.render import (  # noqa: E402
    render_gaussians,
    render_gaussians_reference,
)

WIDTH, HEIGHT = 640, 480
K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
ROOM_MIN = np.array([-2.0, -0.5, 0.0])
ROOM_MAX = np.array([2.0, 4.0, 2.6])
BOXES = [  # (min corner, max corner), world z up
    (np.array([-1.2, 1.2, 0.0]), np.array([-0.5, 1.8, 0.7])),
    (np.array([0.3, 2.0, 0.0]), np.array([1.3, 2.6, 1.1])),
    (np.array([-0.3, 3.0, 0.0]), np.array([0.4, 3.5, 1.5])),
]


def _ray_box(o, d, bmin, bmax):
    """Entry distance ``[M]`` of rays ``o + t d`` into an axis-aligned box (inf on a miss) and the
    axis ``[M]`` of the face hit."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (bmin - o) * inv
        t1 = (bmax - o) * inv
    tmin = np.minimum(t0, t1)
    tmax = np.maximum(t0, t1)
    tn = np.nanmax(tmin, axis=1)
    tf = np.nanmin(tmax, axis=1)
    hit = (tn <= tf) & (tn > 0)
    return np.where(hit, tn, np.inf), np.nanargmax(tmin, axis=1)


def make_scene(n: int, seed: int = 0):
    """Gaussians of the benchmark room. Returns (positions, scales, quats, colors, opacities, T)."""
    rng = np.random.default_rng(seed)
    eye = np.array([0.0, -0.3, 1.4])
    T_wc = look_at(eye, np.array([0.0, 3.0, 0.8]))
    n_view = int(0.9 * n)
    # rays through random points of the image (slightly beyond it, as a map would extend)
    u = rng.uniform(-20, WIDTH + 20, n_view)
    v = rng.uniform(-20, HEIGHT + 20, n_view)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(n_view)], 1)
    d = d_cam @ T_wc[:3, :3].T
    o = np.broadcast_to(eye, d.shape)
    # room: exit distance through its walls (ray starts inside)
    with np.errstate(divide="ignore"):
        tw = np.where(d > 0, (ROOM_MAX - o) / d, (ROOM_MIN - o) / d)
    t_best = tw.min(axis=1)
    axis = tw.argmin(axis=1)
    for bmin, bmax in BOXES:
        tb, ab = _ray_box(o, d, bmin, bmax)
        closer = tb < t_best
        t_best = np.where(closer, tb, t_best)
        axis = np.where(closer, ab, axis)
    p = o + t_best[:, None] * d
    # normals along the hit axis; tangent frame from it
    nrm = np.zeros_like(p)
    nrm[np.arange(n_view), axis] = 1.0
    helper = np.where(np.abs(nrm[:, 2:3]) > 0.9, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    t1 = np.cross(nrm, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    ang = rng.uniform(0, 2 * np.pi, n_view)[:, None]
    t2 = np.cross(nrm, t1)
    t1, t2 = np.cos(ang) * t1 + np.sin(ang) * t2, -np.sin(ang) * t1 + np.cos(ang) * t2
    R = np.stack([t1, t2, nrm], axis=2)  # columns: local x, y, z (normal)
    quat = rotmat_to_quat_xyzw(R)
    scl = np.empty((n_view, 3))
    scl[:, :2] = np.exp(rng.uniform(np.log(0.003), np.log(0.02), (n_view, 2)))
    scl[:, 2] = 0.001
    # a few out of view: behind the camera
    n_out = n - n_view
    p_out = eye + rng.uniform(-1, 1, (n_out, 3)) * [1.5, 0.2, 1.0] + [0.0, -0.4, 0.0]
    q_out = rng.normal(size=(n_out, 4))
    s_out = rng.uniform(0.003, 0.02, (n_out, 3))
    positions = np.concatenate([p, p_out]).astype(np.float32)
    quats = np.concatenate([quat, q_out]).astype(np.float32)
    scales = np.concatenate([scl, s_out]).astype(np.float32)
    texture = 0.5 + 0.5 * np.sin(positions[:, :1] * 9.0 + positions[:, 1:2] * 5.0 + [0.0, 2.0, 4.0])
    colors = np.clip(texture * 220 + rng.normal(0, 15, (n, 3)), 0, 255).astype(np.uint8)
    opacities = np.where(rng.random(n) < 0.7, rng.uniform(0.8, 1.0, n), rng.uniform(0.1, 0.8, n))
    return positions, scales, quats, colors, opacities.astype(np.float32), T_wc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--ref-gaussians", type=int, default=None,
                    help="run the reference (and compiled, for the ratio) on the first N only")
    args = ap.parse_args()

    scene = make_scene(args.gaussians)
    *gauss, T_wc = scene
    print(f"scene: {args.gaussians} Gaussians, {WIDTH}x{HEIGHT}")

    t0 = time.perf_counter()
    fast = render_gaussians(*gauss, T_wc, K, WIDTH, HEIGHT)
    print(f"compiled first call (JIT compile or cache load): {time.perf_counter() - t0:.2f} s")
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        fast = render_gaussians(*gauss, T_wc, K, WIDTH, HEIGHT)
        times.append(time.perf_counter() - t0)
    t_fast = float(np.median(times))
    print(f"compiled:  {1.0 / t_fast:7.2f} fps  (median {t_fast * 1e3:.1f} ms over {args.repeats}, "
          f"min {min(times) * 1e3:.1f} ms)  covered pixels {np.mean(fast.alpha > 0.5):.3f}")

    ref_in = gauss
    if args.ref_gaussians is not None:
        ref_in = [a[: args.ref_gaussians] for a in gauss]
        print(f"reference on the first {args.ref_gaussians} Gaussians only")
        fast = render_gaussians(*ref_in, T_wc, K, WIDTH, HEIGHT)
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            render_gaussians(*ref_in, T_wc, K, WIDTH, HEIGHT)
            times.append(time.perf_counter() - t0)
        t_fast = float(np.median(times))
        print(f"compiled on that input: {1.0 / t_fast:7.2f} fps")
    t0 = time.perf_counter()
    ref = render_gaussians_reference(*ref_in, T_wc, K, WIDTH, HEIGHT)
    t_ref = time.perf_counter() - t0
    print(f"reference: {1.0 / t_ref:7.3f} fps  ({t_ref:.2f} s, one run)")
    print(f"speed ratio compiled/reference: {t_ref / t_fast:.0f}x")
    drgb = np.abs(fast.rgb.astype(int) - ref.rgb.astype(int))
    both = (fast.depth_m > 0) & (ref.depth_m > 0)
    ddep = np.abs(fast.depth_m - ref.depth_m)[both]
    print(f"max |rgb diff| {drgb.max()} (pixels differing: {np.mean(drgb.max(axis=2) > 0):.4f}), "
          f"max |depth diff| {ddep.max() if ddep.size else 0.0:.2e} m, "
          f"max |alpha diff| {np.abs(fast.alpha - ref.alpha).max():.2e}")


if __name__ == "__main__":
    main()
