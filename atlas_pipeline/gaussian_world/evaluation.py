"""Photometric evaluation of a Gaussian world against the real images.

The world is rendered from the estimated pose of every held-out frame (a frame that is not a
keyframe, so it never contributed points to the map) and compared with what the sensor saw:

* PSNR (dB) of the colour image, 8-bit peak, over the whole frame and over the pixels with a sensor
  depth reading in range (``psnr_masked_db``: the part of the scene a depth-built map can hold;
  far walls beyond the depth range cannot be mapped and stay background);
* SSIM of the luma image, the standard 11x11 Gaussian window (sigma 1.5), constants
  ``(0.01 L)^2`` and ``(0.03 L)^2`` (Wang et al. 2004), averaged over the frame;
* depth L1 (m): mean absolute difference between rendered and sensor depth over pixels where both
  exist; the rendered depth is the median depth (where the accumulated opacity crosses 0.5, the
  first opaque surface), not the alpha-weighted mean that blends fore- and background at edges.

Frames are read and rendered one at a time.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.io_utils import atomic_path, write_json_atomic
from atlas_pipeline.safe_arrays import load_json_object_checked

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["psnr", "ssim", "depth_l1", "PhotometricReport", "evaluate_views", "evaluate_rendering", "preview_image"]

_LUMA = np.array([0.299, 0.587, 0.114])


def psnr(a: np.ndarray, b: np.ndarray, peak: float = 255.0) -> float:
    """PSNR in dB of two ``[H, W, C]`` (or ``[H, W]``) images; inf when identical."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


def _luma(img: np.ndarray) -> np.ndarray:
    x = np.asarray(img, np.float64)
    return x @ _LUMA if x.ndim == 3 else x


def ssim(a: np.ndarray, b: np.ndarray, peak: float = 255.0) -> float:
    """Mean SSIM of the luma of two images (11x11 Gaussian window, sigma 1.5; Wang et al. 2004)."""
    from scipy.ndimage import gaussian_filter

    x, y = _luma(a), _luma(b)
    if x.shape != y.shape:
        raise ValueError(f"images differ in shape: {x.shape} vs {y.shape}")

    def blur(z: np.ndarray) -> np.ndarray:
        # truncate 3.5 sigma = radius 5: the standard 11-tap window.
        return gaussian_filter(z, sigma=1.5, truncate=3.5, mode="reflect")

    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(s.mean())


def depth_l1(rendered_m: np.ndarray, sensor_m: np.ndarray) -> tuple[float, float]:
    """``(mean |rendered - sensor| in m, share of sensor pixels the render covers)`` over pixels
    where both have depth (> 0 and finite)."""
    r = np.asarray(rendered_m, np.float64)
    s = np.asarray(sensor_m, np.float64)
    sv = np.isfinite(s) & (s > 0)
    both = sv & np.isfinite(r) & (r > 0)
    cover = float(both.sum() / sv.sum()) if sv.any() else 0.0
    return (float(np.abs(r[both] - s[both]).mean()) if both.any() else float("nan")), cover


@dataclass
class PhotometricReport:
    """Per-view figures of a world rendered at held-out frames.

    Attributes:
        frames: ``[V]`` frame indices evaluated; psnr_db, psnr_masked_db, ssim, depth_l1_m,
            depth_coverage ``[V]``.
        pose_source: which poses the renders used (``estimated`` or ``ground_truth``).
        preview_png: PNG bytes of the median-PSNR view: real | rendered | depth error.
    """

    dataset: str
    map_id: str
    pose_source: str
    frames: np.ndarray
    psnr_db: np.ndarray
    psnr_masked_db: np.ndarray
    ssim: np.ndarray
    depth_l1_m: np.ndarray
    depth_coverage: np.ndarray
    preview_png: bytes = b""
    summary: dict = field(default_factory=dict)

    def summarize(self) -> dict:
        def m(x: np.ndarray) -> float | None:
            x = x[np.isfinite(x)]
            return float(x.mean()) if len(x) else None

        self.summary = {"n_views": int(len(self.frames)), "pose_source": self.pose_source,
                        "mean_psnr_db": m(self.psnr_db), "mean_psnr_masked_db": m(self.psnr_masked_db),
                        "mean_ssim": m(self.ssim),
                        "mean_depth_l1_m": m(self.depth_l1_m), "mean_depth_coverage": m(self.depth_coverage)}
        return self.summary

    def save(self, directory: Path) -> list[Path]:
        directory.mkdir(parents=True, exist_ok=True)
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        rows = [{"frame": int(f), "psnr_db": num(p), "psnr_masked_db": num(pm), "ssim": num(s),
                 "depth_l1_m": num(d), "depth_coverage": num(c)}
                for f, p, pm, s, d, c in zip(self.frames, self.psnr_db, self.psnr_masked_db, self.ssim,
                                             self.depth_l1_m, self.depth_coverage)]
        js = write_json_atomic(directory / "photometric.json", {
            "dataset": self.dataset, "map_id": self.map_id, "summary": self.summarize(), "views": rows})
        out = [js]
        if self.preview_png:
            png = directory / "preview.png"
            with atomic_path(png) as tmp:
                Path(tmp).write_bytes(self.preview_png)
            out.append(png)
        return out

    @classmethod
    def load(cls, directory: Path) -> "PhotometricReport":
        path = directory / "photometric.json"
        if not path.is_file():
            raise ArtifactError(f"{directory}: photometric.json missing")
        d = load_json_object_checked(path)  # bounded size, an object, errors naming the file
        v = d["views"]

        def col(k: str) -> np.ndarray:
            return np.array([np.nan if r[k] is None else r[k] for r in v], np.float64)

        prev = (directory / "preview.png").read_bytes() if (directory / "preview.png").is_file() else b""
        rep = cls(d["dataset"], d["map_id"], d["summary"].get("pose_source", "estimated"),
                  np.array([r["frame"] for r in v], np.int64), col("psnr_db"), col("psnr_masked_db"), col("ssim"),
                  col("depth_l1_m"),
                  col("depth_coverage"), prev)
        rep.summarize()
        return rep


PREVIEW_MAX_ERROR_M = 0.05  # the error preview's colour scale: 0 to 5 cm (more saturates)


def _error_colormap(err_m: np.ndarray, valid: np.ndarray, max_m: float = PREVIEW_MAX_ERROR_M) -> np.ndarray:
    """Depth error ``[H, W]`` as an RGB image: black (0) to red / yellow (``max_m``); blue = no depth."""
    t = np.clip(np.nan_to_num(err_m) / max_m, 0, 1)
    img = np.stack([np.clip(2 * t, 0, 1), np.clip(2 * t - 1, 0, 1), np.zeros_like(t)], axis=-1)
    img[~valid] = (0.1, 0.1, 0.35)
    return (img * 255).astype(np.uint8)


def preview_image(real_rgb: np.ndarray, rendered_rgb: np.ndarray, rendered_depth_m: np.ndarray,
                  sensor_depth_m: np.ndarray) -> np.ndarray:
    """``[H, 3W, 3]`` uint8: real | rendered | depth error (0 to 5 cm, blue where either has no depth)."""
    valid = (sensor_depth_m > 0) & np.isfinite(rendered_depth_m) & (rendered_depth_m > 0)
    err = np.where(valid, np.abs(rendered_depth_m - sensor_depth_m), 0.0)
    return np.concatenate([real_rgb, rendered_rgb, _error_colormap(err, valid)], axis=1)


def evaluate_views(field_: GaussianField, manifest, T_world_cam: np.ndarray, frame_indices: np.ndarray,
                   pose_source: str = "estimated", map_id: str = "", depth_range_m: tuple[float, float] = (0.1, 4.0),
                   background: tuple[int, int, int] = (0, 0, 0), log: Callable[[str], None] | None = None,
                   colour_poses: dict[int, np.ndarray] | None = None) -> PhotometricReport:
    """Render ``field_`` at ``T_world_cam[i]`` ``[N, 4, 4]`` for each ``i`` in ``frame_indices`` and
    compare with frame ``i`` of ``manifest``. Frames without a finite pose are skipped.
    ``colour_poses``: frame -> the camera's pose ``[4, 4]`` when that frame's colour image was
    taken, where it differs from its depth image's: the colour is compared with a render there,
    the depth with one at ``T_world_cam[i]``."""
    from atlas_pipeline.gaussian_world.render import render_field
    from atlas_pipeline.progress import Progress
    from atlas_pipeline.viz.plots import error_panels_png, preview_size

    cam = manifest.camera
    idx = [int(i) for i in frame_indices if np.isfinite(T_world_cam[int(i)]).all()]
    out = {k: np.full(len(idx), np.nan) for k in ("psnr", "psnr_m", "ssim", "l1", "cov")}
    progress = Progress("evaluating views", len(idx), log)
    keep_for_preview: list[tuple[float, int]] = []
    colour_poses = colour_poses or {}

    def render(T: np.ndarray):
        return render_field(field_, T, cam.K, cam.width, cam.height, background=background)

    for k, i in enumerate(idx):
        real = manifest.read_rgb(i)
        depth = manifest.read_depth_m(i, allow_empty=True)
        depth = np.where((depth > depth_range_m[0]) & (depth < depth_range_m[1]), depth, 0.0)
        r = render(T_world_cam[i])
        rgb = render(colour_poses[i]).rgb if i in colour_poses else r.rgb
        out["psnr"][k] = psnr(real, rgb)
        seen = depth > 0
        out["psnr_m"][k] = psnr(real[seen], rgb[seen]) if seen.any() else np.nan
        out["ssim"][k] = ssim(real, rgb)
        out["l1"][k], out["cov"][k] = depth_l1(r.depth_median_m, depth)
        keep_for_preview.append((out["psnr_m"][k], i))
        progress.update()
    rep = PhotometricReport(manifest.dataset, map_id, pose_source, np.array(idx, np.int64), out["psnr"],
                            out["psnr_m"], out["ssim"], out["l1"], out["cov"])
    if idx:
        # Preview: the view with the median PSNR (a typical one, neither the best nor the worst).
        _, i = sorted(keep_for_preview)[len(keep_for_preview) // 2]
        real = manifest.read_rgb(i)
        depth = manifest.read_depth_m(i, allow_empty=True)
        r = render(T_world_cam[i])
        rgb = render(colour_poses[i]).rgb if i in colour_poses else r.rgb
        # at the size the UI shows previews (the dataset's, halved while wide), with a colour bar
        pw, ph = preview_size(cam.width, cam.height)
        step = max(1, cam.width // pw)
        valid = (depth > 0) & np.isfinite(r.depth_median_m) & (r.depth_median_m > 0)
        err = np.where(valid, np.abs(r.depth_median_m - depth), 0.0)
        rep.preview_png = error_panels_png(real[::step, ::step], rgb[::step, ::step], err[::step, ::step],
                                           valid[::step, ::step], PREVIEW_MAX_ERROR_M,
                                           title=f"frame {i}: PSNR {psnr(real, rgb):.1f} dB")
    rep.summarize()
    logger.info("photometric evaluation of %s: %s", manifest.dataset, rep.summary)
    return rep


def evaluate_rendering(manifest: FrameManifest, world: GaussianWorld, report: LocalizationReport,
                       cfg: PipelineConfig, log: Callable[[str], None] | None = None) -> PhotometricReport:
    """The render-evaluation stage: render the world at the estimated pose of held-out frames (not
    keyframes: they never fed the map) and compare with the real images (:func:`evaluate_views`).
    A colour image taken at another time than its depth image (``localization.colour_delay_compensation``)
    is compared with a render at the estimated trajectory's pose at its own time."""
    from atlas_pipeline.perception.colour_timing import colour_time_poses
    from atlas_pipeline.scene_memory.recordings import keyframe_indices_of

    # held out: not a keyframe of this recording (an extended world's other keyframes are frames of others)
    held = np.setdiff1d(np.arange(manifest.n_frames), keyframe_indices_of(world, manifest))
    held = held[np.isfinite(report.T_world_cam[held]).all(axis=(1, 2))][:: cfg.evaluation.view_stride]
    if cfg.evaluation.max_views is not None:
        held = held[: cfg.evaluation.max_views]
    # a second render only where the two poses' views differ (not for TUM fr3's ~1 ms)
    colour_poses = (colour_time_poses(report.T_world_cam, manifest, held)
                    if cfg.localization.colour_delay_compensation else {})
    return evaluate_views(world.field, manifest, report.T_world_cam, held, "estimated", world.map_id,
                          (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m), log=log, colour_poses=colour_poses)
