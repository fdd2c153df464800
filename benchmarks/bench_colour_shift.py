"""Experiment (not in the pipeline): estimating a recording's colour-to-depth shift from its frames.

    python benchmarks/bench_colour_shift.py                 # presets, shared TUM frames, ablations
    python benchmarks/bench_colour_shift.py --frames 60 --no-ablation

Finding: exact on the clean room and on each sensor effect alone, but under the
full Kinect-like model (jittered, half-missing silhouettes) the surviving depth edges sit 1-2 px
off, and the estimate is confidently wrong or undetermined; applied to the shared TUM frames it did
not change tracking. So nothing here is applied to any frame.

An RGB-D frame pairs a colour pixel with a depth pixel. When the two are not registered exactly (a
factory calibration a little off, 7-Scenes' unregistered Kinect streams, a colour stream with its
own timing) every colour sample belongs to a neighbouring surface point: the map is painted a few
pixels off its geometry, and the tracker's photometric term pulls against its geometric one
(synthetic-loop: ATE 0.57 cm without the shift, 1.71 cm with a 1.5 px shift).

:func:`estimate_colour_shift` finds the shift ``(dx, dy)`` in pixels such that colour sampled at
``(u + dx, v + dy)`` belongs to depth pixel ``(u, v)``: depth discontinuities (occlusion edges)
are almost always colour edges too. Along each depth edge's normal the colour profile's steepest
change says how far the colour edge lies from it (one constraint ``n . d = t`` per edge pixel,
sub-pixel by a parabola); the shift is the mode of those constraints over the edges of a few
frames (a kernel vote over a grid, then mean-shift steps), so colour texture near an edge, a
robust outlier, does not pull it. The edge stencil is a central difference, symmetric about the
step, so a registered pair votes for zero. The estimate is trusted only when the two halves of
the frames agree and the peak stands out of the search window; otherwise it is undetermined.

The model is one shift for the whole image: exact for a misregistration in the image plane, the
mean parallax for two cameras side by side (7-Scenes: f b / z, a few pixels at 1-3 m).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

logger = logging.getLogger(__name__)

MAX_SHIFT_PX = 6  # search window half-width (whole pixels): beyond it the pair is not one RGB-D sensor
PROFILE_STEP_PX = 0.5  # samples of the colour profile along each depth edge's normal
GRID_STEP_PX = 0.25  # grid of the vote over shifts
KERNEL_PX = 0.75  # how far an edge's offset may miss the shift and still vote for it (Gaussian sigma)
MEAN_SHIFT_STEPS = 5
MAX_EDGES_PER_FRAME = 4000  # evenly strided; more add time, not accuracy
# A depth edge: relative depth jump over the 2-pixel central difference. A plane tilted 60 degrees
# at 2 m changes depth by ~0.3 %/px at f=525, so 5 % is an occlusion, not a slope.
DEPTH_EDGE_REL_JUMP = 0.05
CLEAN_STEP_PX = 3  # half-length of the depth profile that must be one clean step
MIN_EDGE_PIXELS = 2000  # over all frames: fewer edges than this and the peak is noise
# The two halves of the frames (even / odd) must agree to within this (pixels) ...
MAX_HALF_DISAGREEMENT_PX = 0.5
# ... and the peak must beat the median score of the window by this factor.
MIN_PEAK_CONTRAST = 1.15
DEFAULT_N_FRAMES = 12  # frames sampled evenly over the sequence


@dataclass(frozen=True)
class ColourShift:
    """What :func:`estimate_colour_shift` found.

    Attributes:
        dx_px, dy_px: the shift (colour sampled at ``(u + dx, v + dy)`` for depth pixel ``(u, v)``).
        determined: whether the estimate passed its checks.
        halves_px: ``[[dx, dy], [dx, dy]]`` the estimates from the even and the odd frames.
        peak_contrast: the peak score over the median score of the search window.
        n_edge_pixels: depth-edge pixels used.
        n_frames: frames used.
        reason: why it is undetermined ("" when determined).
    """

    dx_px: float
    dy_px: float
    determined: bool
    halves_px: tuple[tuple[float, float], tuple[float, float]]
    peak_contrast: float
    n_edge_pixels: int
    n_frames: int
    reason: str = ""

    def to_dict(self) -> dict:
        return {"dx_px": round(self.dx_px, 3), "dy_px": round(self.dy_px, 3), "determined": self.determined,
                "halves_px": [[round(a, 3), round(b, 3)] for a, b in self.halves_px],
                "peak_contrast": round(self.peak_contrast, 3), "n_edge_pixels": self.n_edge_pixels,
                "n_frames": self.n_frames, "reason": self.reason}


def depth_edges(depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The occlusion edges of ``depth_m`` ``[H, W]`` (0 = no reading): ``([M, 2]`` float (row, col),
    ``[M, 2]`` float unit normals (d_row, d_col) across the edge)``. An edge pixel's central
    differences in u and v have both neighbours measured and one of them jumps by more than
    ``DEPTH_EDGE_REL_JUMP`` of its depth; the normal is the direction of the depth gradient. The
    image border (``MAX_SHIFT_PX + 3``) is left out so every sample along the normal stays inside."""
    z = depth_m.astype(np.float32)
    H, W = z.shape
    zc = z[1:-1, 1:-1]
    gu = z[1:-1, 2:] - z[1:-1, :-2]  # [H-2, W-2]
    gv = z[2:, 1:-1] - z[:-2, 1:-1]
    ok = (z[1:-1, 2:] > 0) & (z[1:-1, :-2] > 0) & (z[2:, 1:-1] > 0) & (z[:-2, 1:-1] > 0) & (zc > 0)
    edge = np.zeros((H, W), bool)
    edge[1:-1, 1:-1] = ok & (np.maximum(np.abs(gu), np.abs(gv)) > DEPTH_EDGE_REL_JUMP * zc)
    m = MAX_SHIFT_PX + 3
    edge[:m], edge[-m:], edge[:, :m], edge[:, -m:] = False, False, False, False
    rc = np.argwhere(edge)  # [M, 2]
    g = np.stack([gv[rc[:, 0] - 1, rc[:, 1] - 1], gu[rc[:, 0] - 1, rc[:, 1] - 1]], axis=1).astype(np.float64)
    n = g / np.linalg.norm(g, axis=1, keepdims=True)
    # A clean step only: every reading along the normal within CLEAN_STEP_PX measured and
    # monotone (one jump). Jagged or half-missing silhouettes (lateral jitter, dropouts) put the
    # jump where the sensor failed, not where the surface ends.
    t = np.arange(-CLEAN_STEP_PX, CLEAN_STEP_PX + 1)  # [T]
    r = np.clip(np.rint(rc[:, :1] + t[None] * n[:, :1]).astype(np.int64), 0, H - 1)  # [M, T]
    c = np.clip(np.rint(rc[:, 1:] + t[None] * n[:, 1:]).astype(np.int64), 0, W - 1)
    prof = z[r, c]
    step = np.diff(prof, axis=1)
    clean = (prof > 0).all(axis=1) & ((step >= 0).all(axis=1) | (step <= 0).all(axis=1))
    return rc[clean].astype(np.float64), n[clean]


def _luma(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)  # [H, W]


def _bilinear(img: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    r0 = np.floor(rows).astype(np.int64)
    c0 = np.floor(cols).astype(np.int64)
    fr = (rows - r0).astype(np.float32)
    fc = (cols - c0).astype(np.float32)
    top = img[r0, c0] * (1 - fc) + img[r0, c0 + 1] * fc
    bottom = img[r0 + 1, c0] * (1 - fc) + img[r0 + 1, c0 + 1] * fc
    return top * (1 - fr) + bottom * fr


def colour_edge_offsets(luma: np.ndarray, edges_rc: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the colour edge lies along each depth edge's normal: ``(t [M], strength [M])``.

    The luma ``[H, W]`` is sampled along ``p + t n`` for ``t`` in ``[-MAX_SHIFT_PX, MAX_SHIFT_PX]``
    (``PROFILE_STEP_PX`` apart); ``t`` is the sample with the steepest change, refined by a parabola
    through its neighbours; ``strength`` that change (grey levels per pixel)."""
    t = np.arange(-MAX_SHIFT_PX - PROFILE_STEP_PX, MAX_SHIFT_PX + 1.5 * PROFILE_STEP_PX, PROFILE_STEP_PX)  # [T]
    rows = edges_rc[:, :1] + t[None] * normals[:, :1]  # [M, T]
    cols = edges_rc[:, 1:] + t[None] * normals[:, 1:]
    prof = _bilinear(luma, rows, cols)  # [M, T]
    d = np.abs(np.diff(prof, axis=1)) / PROFILE_STEP_PX  # [M, T-1] at the midpoints t + step/2
    mid = t[:-1] + 0.5 * PROFILE_STEP_PX
    inner = (mid >= -MAX_SHIFT_PX) & (mid <= MAX_SHIFT_PX)
    k = np.argmax(np.where(inner[None], d, -1.0), axis=1)  # [M]
    kl, kr = np.maximum(k - 1, 0), np.minimum(k + 1, d.shape[1] - 1)
    i = np.arange(len(k))
    a, b, c = d[i, kl], d[i, k], d[i, kr]
    den = a - 2 * b + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return mid[k] + np.clip(frac, -0.5, 0.5) * PROFILE_STEP_PX, b


def _mode(normals: np.ndarray, offsets: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, float]:
    """The shift ``d`` (row, col) that most edges agree with, ``n_i . d = t_i``: a kernel density
    over a grid (Gaussian kernel of ``KERNEL_PX``), refined by mean-shift steps (weighted least
    squares with the same kernel). Also returns the peak contrast: the density at ``d`` over the
    median density of the grid."""
    g = np.arange(-MAX_SHIFT_PX, MAX_SHIFT_PX + 1e-6, GRID_STEP_PX)
    grid = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)  # [S, 2] (row, col)
    dens = np.zeros(len(grid))
    for s in range(0, len(grid), 256):  # chunks keep [256, M] small
        r = grid[s:s + 256] @ normals.T - offsets[None]
        dens[s:s + 256] = (np.exp(-0.5 * (r / KERNEL_PX) ** 2) * weights[None]).sum(axis=1)
    d = grid[int(np.argmax(dens))]
    for _ in range(MEAN_SHIFT_STEPS):
        w = weights * np.exp(-0.5 * ((normals @ d - offsets) / KERNEL_PX) ** 2)
        A = (normals * w[:, None]).T @ normals
        if np.linalg.cond(A) > 1e6:  # edges of one direction only: the other component is unknown
            break
        d = np.linalg.solve(A, (normals * (w * offsets)[:, None]).sum(axis=0))
    return d, float(dens.max() / max(np.median(dens), 1e-12))


def estimate_colour_shift(read_rgb: Callable[[int], np.ndarray], read_depth_m: Callable[[int], np.ndarray],
                          n_frames_total: int, n_frames: int = DEFAULT_N_FRAMES) -> ColourShift:
    """The colour-to-depth shift of a recording from ``n_frames`` frames spread over it.

    ``read_rgb(i)`` gives frame ``i``'s colour ``[H, W, 3]`` uint8 and ``read_depth_m(i)`` its depth
    ``[H, W]`` in metres (0 = no reading), on the same pixel grid.
    """
    idx = np.unique(np.linspace(0, n_frames_total - 1, min(n_frames, n_frames_total)).round().astype(int))
    normals, offsets, weights, frame_of = [], [], [], []
    for k, i in enumerate(idx):
        rc, n = depth_edges(read_depth_m(int(i)))
        if len(rc) > MAX_EDGES_PER_FRAME:
            keep = np.linspace(0, len(rc) - 1, MAX_EDGES_PER_FRAME).round().astype(int)
            rc, n = rc[keep], n[keep]
        if not len(rc):
            continue
        t, strength = colour_edge_offsets(_luma(read_rgb(int(i))), rc, n)
        normals.append(n)
        offsets.append(t)
        weights.append(np.sqrt(strength))  # a weak colour edge is mostly noise; sqrt: no single edge dominates
        frame_of.append(np.full(len(t), k))
    n_edges = int(sum(len(t) for t in offsets))
    n_used = len(offsets)

    def undetermined(reason: str, contrast: float = 0.0, halves=((0.0, 0.0), (0.0, 0.0))) -> ColourShift:
        logger.info("colour-to-depth shift undetermined: %s", reason)
        return ColourShift(0.0, 0.0, False, halves, contrast, n_edges, n_used, reason)

    if n_edges < MIN_EDGE_PIXELS or n_used < 2:
        return undetermined(f"{n_edges} depth-edge pixels in {n_used} frames (need {MIN_EDGE_PIXELS} in 2)")
    N, T, Wt, F = (np.concatenate(a) for a in (normals, offsets, weights, frame_of))
    d, contrast = _mode(N, T, Wt)
    halves = tuple((float(h[1]), float(h[0])) for h in (_mode(N[F % 2 == j], T[F % 2 == j], Wt[F % 2 == j])[0]
                                                          for j in (0, 1)))
    gap = float(np.hypot(halves[0][0] - halves[1][0], halves[0][1] - halves[1][1]))
    dx, dy = float(d[1]), float(d[0])
    if contrast < MIN_PEAK_CONTRAST:
        return undetermined(f"no clear peak (contrast {contrast:.2f} < {MIN_PEAK_CONTRAST})", contrast, halves)
    if gap > MAX_HALF_DISAGREEMENT_PX:
        return undetermined(f"the two halves of the frames disagree by {gap:.2f} px", contrast, halves)
    logger.info("colour-to-depth shift (%.2f, %.2f) px from %d frames, %d edge pixels (contrast %.2f)",
                dx, dy, n_used, n_edges, contrast)
    return ColourShift(dx, dy, True, halves, contrast, n_edges, n_used)


# ---- the benchmark ------------------------------------------------------------------------------

PRESETS = ("synthetic", "synthetic-noisy", "synthetic-handheld", "synthetic-loop")
SHARED = (("tum_fr1_xyz_10", "freiburg1"), ("tum_fr3_teddy_100", "freiburg3"))
# synthetic-noisy's depth effects, each alone (with its colour effects) on 12 frames
ABLATED = ("depth_lateral_noise_px", "edge_dropout_prob", "projector_baseline_m", "depth_noise_a_m")
DEPTH_PREFIXES = ("depth_", "edge", "projector", "inverse", "dark", "shiny", "grazing")


def _row(name: str, truth: str, r: ColourShift) -> str:
    h = "; ".join(f"({a:+.2f}, {b:+.2f})" for a, b in r.halves_px)
    est = f"({r.dx_px:+.2f}, {r.dy_px:+.2f})" if r.determined else "undetermined"
    return (f"| {name} | {truth} | {est} | {h} | {r.peak_contrast:.2f} | {r.n_edge_pixels} | {r.n_frames} | "
            f"{r.reason or '-'} |")


def main(argv: list[str] | None = None) -> int:
    import yaml

    from atlas_pipeline.config import load_profile
    from atlas_pipeline.sensors.registry import DatasetEntry, load_dataset, load_registry
    from benchmarks.common import shared_tum_manifest

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=DEFAULT_N_FRAMES, help="frames sampled per sequence")
    ap.add_argument("--no-ablation", action="store_true", help="skip the single-effect variants of synthetic-noisy")
    args = ap.parse_args(argv)
    cfg = load_profile("default")
    print(f"# reproduce: python benchmarks/bench_colour_shift.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print("| sequence | true shift px | estimate (dx, dy) px | even / odd frames | contrast | edge px | frames | "
          "undetermined because |")
    print("|---|---|---|---|---|---|---|---|")

    def run(name: str, manifest, truth: str) -> None:
        r = estimate_colour_shift(manifest.read_rgb, manifest.read_depth_m, manifest.n_frames, args.frames)
        print(_row(name, truth, r), flush=True)

    reg = load_registry()
    for name in PRESETS:
        p = reg[name].params
        run(name, load_dataset(reg[name], cfg), f"({p.get('rgb_shift_x_px', 0):+.2f}, {p.get('rgb_shift_y_px', 0):+.2f})")
    for folder, cam in SHARED:
        manifest = shared_tum_manifest(folder, cam)
        if manifest is not None:
            run(folder, manifest, "unknown")
    if not args.no_ablation:
        base = {k: v for k, v in reg["synthetic-noisy"].params.items()}
        colour_only = {k: v for k, v in base.items() if not k.startswith(DEPTH_PREFIXES)} | {"n_frames": 12}
        variants = {"noisy, colour effects only": colour_only, "noisy, all (12 frames)": base | {"n_frames": 12}}
        variants |= {f"noisy, colour + {k} only": colour_only | {k: base[k]} for k in ABLATED}
        variants["noisy, colour + lateral + dropout"] = colour_only | {k: base[k] for k in ABLATED[:2]}
        with tempfile.TemporaryDirectory(prefix="atlas-colour-shift-") as tmp:
            os.environ["ATLAS_DATA_DIR"] = tmp
            for i, (label, params) in enumerate(variants.items()):
                entry = DatasetEntry(f"ablation-{i}", "synthetic", Path(tmp) / f"ablation-{i}", params=params)
                truth = f"({params.get('rgb_shift_x_px', 0):+.2f}, {params.get('rgb_shift_y_px', 0):+.2f})"
                run(label, load_dataset(entry, cfg), truth)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
