"""Small PNG figures for the orchestrator's UI: the trajectory seen from above, a render preview.

Images travel inside run metadata, so they are kept to a readable size, not more: the dataset's
image size, halved while wider than :data:`PREVIEW_MAX_WIDTH_PX` (640x480 -> 320x240).
"""

from __future__ import annotations

import base64
import io

import numpy as np

from atlas_pipeline.gaussian_world.field import GaussianField

__all__ = ["trajectory_png", "render_preview_png", "png_bytes", "markdown_image", "preview_intrinsics",
           "preview_size", "error_panels_png", "ERROR_NO_DEPTH_RGB"]

PREVIEW_MAX_WIDTH_PX = 400  # wider images are shown at half size (still readable in the UI, 4x fewer bytes)
ERROR_NO_DEPTH_RGB = (0.1, 0.1, 0.35)  # dark blue: a pixel where either depth is missing
FIGURE_DPI = 100


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


def preview_size(width: int, height: int) -> tuple[int, int]:
    """The size a preview of ``width`` x ``height`` images is shown at: the same, halved while wider
    than :data:`PREVIEW_MAX_WIDTH_PX`."""
    scale = 1
    while width // scale > PREVIEW_MAX_WIDTH_PX:
        scale *= 2
    return max(1, width // scale), max(1, height // scale)


def render_preview_png(field: GaussianField, T_world_cam: np.ndarray, width: int = 160, height: int = 120,
                       K: np.ndarray | None = None) -> bytes:
    """Render ``field`` from ``T_world_cam`` at ``width`` x ``height`` with intrinsics ``K`` (the
    dataset's camera, scaled to that size), else :func:`preview_intrinsics`."""
    from atlas_pipeline.gaussian_world.render import render_field

    K = preview_intrinsics(width, height) if K is None else np.asarray(K, np.float64)
    r = render_field(field, np.asarray(T_world_cam, np.float64), K, width, height)
    return png_bytes(r.rgb)


def error_panels_png(real_rgb: np.ndarray, rendered_rgb: np.ndarray, error_m: np.ndarray, valid: np.ndarray,
                     max_error_m: float, title: str = "") -> bytes:
    """real | rendered | depth error, side by side, each at the image's own size, with a colour bar
    in centimetres under the error panel (and a legend swatch for pixels without depth)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    h, w = real_rgb.shape[:2]
    cm_per_m = 100.0
    # Room under the panels for the colour bar, its labels and the legend (inches at FIGURE_DPI).
    bar_in, title_in = 0.9, (0.3 if title else 0.15)
    fig = Figure(figsize=(3 * w / FIGURE_DPI, h / FIGURE_DPI + bar_in + title_in), dpi=FIGURE_DPI)
    panel_h = (h / FIGURE_DPI) / fig.get_figheight()
    bottom = bar_in / fig.get_figheight()
    err = np.ma.masked_where(~valid, np.nan_to_num(error_m) * cm_per_m)
    cmap = ListedColormap(matplotlib.colormaps["inferno"](np.linspace(0, 1, 256))).with_extremes(bad=ERROR_NO_DEPTH_RGB)
    im = None
    for k, (img, name) in enumerate([(real_rgb, "real"), (rendered_rgb, "rendered"), (err, "depth error")]):
        ax = fig.add_axes((k / 3, bottom, 1 / 3, panel_h))
        ax.set_axis_off()
        if k < 2:
            ax.imshow(img, interpolation="nearest")
        else:
            im = ax.imshow(img, cmap=cmap, vmin=0.0, vmax=max_error_m * cm_per_m, interpolation="nearest")
        ax.text(0.02, 0.97, name, transform=ax.transAxes, va="top", fontsize=7, color="white",
                bbox={"facecolor": "black", "alpha": 0.5, "pad": 1.5, "lw": 0})
    cax = fig.add_axes((2 / 3 + 0.02, 0.55 * bottom, 1 / 3 - 0.04, 0.18 * bottom))
    bar = fig.colorbar(im, cax=cax, orientation="horizontal", extend="max")
    bar.set_label(f"|rendered - sensor depth| (cm), {max_error_m * cm_per_m:g}+ saturates", fontsize=6)
    bar.ax.tick_params(labelsize=6)
    fig.legend(handles=[Patch(color=ERROR_NO_DEPTH_RGB, label="no depth (sensor or render)")],
               loc="lower left", fontsize=6, frameon=False, bbox_to_anchor=(0.0, 0.05))
    if title:
        fig.suptitle(title, fontsize=8, y=1 - 0.05 * title_in)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
