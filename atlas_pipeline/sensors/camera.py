"""Pinhole camera intrinsics with the depth encoding of the sensor."""

from __future__ import annotations

import math

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from atlas_pipeline.errors import ConfigError

# The principal point lies in the image, [0, width] x [0, height] (pixel centres at whole numbers or
# at halves: either convention); a point outside it (cx 900 on a 640-wide image) is a typo or another
# camera's calibration.
# A pinhole camera's horizontal and vertical fields of view: RGB-D sensors see 45-120 degrees; past
# 170 the focal length is not in pixels (millimetres, or normalised by the image size: fx 0.9) or
# the lens is a fisheye that needs a model of its own. Under 1 degree it has a digit too many.
MAX_FIELD_OF_VIEW_DEG = 170.0
MIN_FIELD_OF_VIEW_DEG = 1.0
# Pixels of every RGB-D sensor are square to a few parts in a thousand (fx / fy); a ratio beyond 2
# is fx, fy, cx, cy given in another order or a focal length of another image size.
MAX_FOCAL_RATIO = 2.0


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of one RGB-D sensor (depth registered to colour, as in TUM).

    Attributes:
        width, height: image size in pixels.
        fx, fy, cx, cy: focal lengths and principal point in pixels.
        depth_scale: raw 16-bit depth units per metre (TUM: 5000, i.e. ``depth_m = raw / 5000``).
        distortion: radial-tangential coefficients ``(k1, k2, p1, p2, k3)``; empty when the images
            are already undistorted.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 5000.0
    distortion: tuple[float, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"camera size must be positive, got {self.width}x{self.height}")
        # "not x > 0" also refuses NaN, which every comparison answers False
        if not (math.isfinite(self.fx) and math.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise ConfigError(f"focal lengths must be finite and positive, got fx={self.fx} fy={self.fy}")
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ConfigError(f"principal point must be finite, got cx={self.cx} cy={self.cy}")
        self._check_meaning()
        if not (math.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise ConfigError(f"depth_scale must be finite and positive, got {self.depth_scale}")
        if not all(math.isfinite(k) for k in self.distortion):
            raise ConfigError(f"distortion coefficients must be finite, got {list(self.distortion)}")
        if len(self.distortion) not in (0, 4, 5):
            raise ConfigError(
                f"distortion needs 0, 4 or 5 coefficients (k1 k2 p1 p2 [k3]), got {len(self.distortion)}"
            )

    def _check_meaning(self) -> None:
        """Refuse intrinsics that are numbers but no camera of this image size: the principal point
        outside the image, a field of view outside [MIN, MAX]_FIELD_OF_VIEW_DEG, pixels far from
        square. Each message names the field, its value and the image size."""
        for name, c, size, axis in (("cx", self.cx, self.width, "wide"), ("cy", self.cy, self.height, "high")):
            if not 0.0 <= c <= size:
                raise ConfigError(f"principal point {name}={c:g} lies outside the image ({size} pixels {axis}: "
                                  f"{name} must be in [0, {size}]); are fx fy cx cy in that order and of this "
                                  f"{self.width}x{self.height} image?")
        for name, f, size in (("fx", self.fx, self.width), ("fy", self.fy, self.height)):
            fov_deg = math.degrees(2.0 * math.atan(size / (2.0 * f)))
            if fov_deg > MAX_FIELD_OF_VIEW_DEG:
                raise ConfigError(f"focal length {name}={f:g} gives a {fov_deg:.1f} degree field of view on "
                                  f"{size} pixels (at most {MAX_FIELD_OF_VIEW_DEG:g}): focal lengths are in "
                                  "pixels (not millimetres, not divided by the image size)")
            if fov_deg < MIN_FIELD_OF_VIEW_DEG:
                raise ConfigError(f"focal length {name}={f:g} gives a {fov_deg:.2f} degree field of view on "
                                  f"{size} pixels (at least {MIN_FIELD_OF_VIEW_DEG:g}): a digit too many, or "
                                  "the focal length of a larger image?")
        ratio = max(self.fx, self.fy) / min(self.fx, self.fy)
        if ratio > MAX_FOCAL_RATIO:
            raise ConfigError(f"focal lengths fx={self.fx:g} and fy={self.fy:g} differ by a factor {ratio:.2f} (at "
                              f"most {MAX_FOCAL_RATIO:g}: camera pixels are square); are fx fy cx cy in that order?")

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def scaled(self, factor: float) -> "CameraIntrinsics":
        """Intrinsics of the same camera with images resized by ``factor`` (e.g. 0.5 for half size)."""
        return CameraIntrinsics(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            # Pixel centres: (c + 0.5) * f - 0.5 keeps the optical axis on the same scene point.
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            depth_scale=self.depth_scale,
            distortion=self.distortion,
        )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["distortion"] = list(self.distortion)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "CameraIntrinsics":
        known = {"width", "height", "fx", "fy", "cx", "cy", "depth_scale", "distortion"}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(f"unknown camera fields: {sorted(unknown)}")
        missing = {"width", "height", "fx", "fy", "cx", "cy"} - set(d)
        if missing:
            raise ConfigError(f"camera is missing fields: {sorted(missing)}")
        try:
            return cls(
                width=int(d["width"]),
                height=int(d["height"]),
                fx=float(d["fx"]),
                fy=float(d["fy"]),
                cx=float(d["cx"]),
                cy=float(d["cy"]),
                depth_scale=float(d.get("depth_scale", 5000.0)),
                distortion=tuple(float(x) for x in (d.get("distortion") or ())),
            )
        except (TypeError, ValueError, OverflowError) as exc:
            raise ConfigError(f"camera field has a non-numeric value: {exc}") from exc


# Official TUM RGB-D calibrations (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).
# The depth images of all three are registered to the colour camera; depth scale 5000 per metre.
TUM_CAMERAS: dict[str, CameraIntrinsics] = {
    "freiburg1": CameraIntrinsics(
        640, 480, 517.306408, 516.469215, 318.643040, 255.313989, 5000.0,
        (0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
    ),
    "freiburg2": CameraIntrinsics(
        640, 480, 520.908620, 521.007327, 325.141442, 249.701764, 5000.0,
        (0.231222, -0.784899, -0.003257, -0.000105, 0.917205),
    ),
    # freiburg3 images in the archives are already undistorted.
    "freiburg3": CameraIntrinsics(640, 480, 535.4, 539.2, 320.1, 247.6, 5000.0, ()),
    # TUM's suggestion when the sensor is unknown.
    "default": CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5, 5000.0, ()),
}
