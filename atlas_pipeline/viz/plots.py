"""Small PNG figures for the orchestrator's UI: the trajectory seen from above, a render preview.

Images are kept tiny (a few tens of kB) because they travel inside run metadata.
"""

from __future__ import annotations

import base64
import io

import numpy as np

from atlas_pipeline.gaussian_world.field import GaussianField

__all__ = ["trajectory_png", "render_preview_png", "png_bytes", "markdown_image", "preview_intrinsics"]


def png_bytes(rgb: np.ndarray) -> bytes:
    """An ``[H, W, 3]`` uint8 image as PNG bytes."""
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", np.ascontiguousarray(rgb, dtype=np.uint8), extension=".png")


def markdown_image(png: bytes, alt: str) -> str:
    """Markdown that shows ``png`` inline (data URL)."""
    return f"![{alt}](data:image/png;base64,{base64.b64encode(png).decode('ascii')})"


def trajectory_png(estimated_xyz: np.ndarray, groundtruth_xyz: np.ndarray | None = None,
                   title: str = "", size_px: int = 360) -> bytes:
    """Top view (x-y plane of the world) of the estimated trajectory, and ground truth where known.

    Rows with a NaN coordinate (unknown poses) are left out.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    est = np.asarray(estimated_xyz, np.float64)
    est = est[np.isfinite(est).all(axis=1)]
    if groundtruth_xyz is not None:
        gt = np.asarray(groundtruth_xyz, np.float64)
        gt = gt[np.isfinite(gt).all(axis=1)]
        if len(gt):
            ax.plot(gt[:, 0], gt[:, 1], "-", color="0.55", lw=2.0, label="ground truth")
    if len(est):
        ax.plot(est[:, 0], est[:, 1], "-", color="tab:blue", lw=1.0, label="estimated")
        ax.plot(est[:1, 0], est[:1, 1], "o", color="tab:green", ms=4, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)", fontsize=7)
    ax.set_ylabel("y (m)", fontsize=7)
    ax.tick_params(labelsize=6)
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=6, loc="best")
    if title:
        ax.set_title(title, fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def preview_intrinsics(width: int, height: int) -> np.ndarray:
    """A pinhole camera with the TUM Kinect's field of view (fx = 525 px at 640 px width)."""
    f = 525.0 / 640.0 * width
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], np.float64)


def render_preview_png(field: GaussianField, T_world_cam: np.ndarray, width: int = 160, height: int = 120) -> bytes:
    """Render ``field`` from ``T_world_cam`` at a small size with :func:`preview_intrinsics`."""
    from atlas_pipeline.gaussian_world.render import render_gaussians

    r = render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors, field.opacities,
                         np.asarray(T_world_cam, np.float64), preview_intrinsics(width, height), width, height)
    return png_bytes(r.rgb)
