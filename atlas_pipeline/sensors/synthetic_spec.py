"""What a synthetic sequence is: :class:`SyntheticSpec`, the sensor and motion presets, and the
spec's hash (which names a generated dataset).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, fields

from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.tum import MAX_ASSOCIATION_DT_S

__all__ = ["GENERATOR_VERSION", "TIMESTAMP_START_S", "GT_MARGIN_S", "SyntheticSpec", "PLACES", "spec_hash"]


# Bump when the rendering or file layout changes, so cached datasets are regenerated.
GENERATOR_VERSION = 3  # 3: colour stamped with depth, at the render time (2: colour 3 ms later; 1: depth 3 ms later)
TIMESTAMP_START_S = 1000.0
GT_MARGIN_S = 0.1  # ground truth extends this far before the first and after the last stamp


@dataclass(frozen=True)
class SyntheticSpec:
    """What to generate. Two equal specs give byte-identical datasets."""

    seed: int = 0
    n_frames: int = 60
    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    depth_scale: float = 5000.0
    fps: float = 30.0
    gt_rate_hz: float = 100.0
    max_depth_m: float = 8.0  # farther returns are written as 0 (no reading)

    # -- Motion (defaults: the smooth orbit above). See HANDHELD_MOTION and LOOP_MOTION. --
    orbit_rate_deg_per_s: float = 36.0  # speed along the ellipse (the wobbles keep their shape)
    loop_revolutions: int = 0  # > 0: exactly this many turns, the last frame 3 mm from the first
    pan_rate_deg_per_s: float = 0.0  # > 0: sustained pans, camera yaw rate in the world frame
    shake_m: float = 0.0  # hand shake: translation amplitude per axis, 5-10 Hz
    shake_deg: float = 0.0  # hand shake: rotation amplitude per axis, 5-10 Hz
    # Height of the point the orbit looks at (it wobbles 10 cm about it): at 0.55 m the objects in
    # the middle of the room; at the camera's height the view runs over them to the far walls.
    look_at_height_m: float = 0.55
    # -- Place (defaults: the one room). See synthetic_places.py. --
    place: str = "room"  # "room", or "suite": three rooms joined by doors, walked along a route
    route: int = 0  # suite: which route (0: a closed tour, 1: a second visit on another path)
    suite_speed_m_per_s: float = 0.0  # suite: walking speed; 0 = the whole route over the recording

    # -- Depth sensor model (defaults: exact depth). See KINECT_V1_SENSOR. --
    depth_noise_a_m: float = 0.0  # sigma_z = a + b (z - 0.4)^2 + c / sqrt(z) theta^2/(pi/2-theta)^2
    depth_noise_b_per_m: float = 0.0
    depth_noise_angle_m: float = 0.0  # c, metres * sqrt(metres)
    depth_noise_corr_px: float = 0.0  # > 0: noise correlated over a box this wide (px at 640 width)
    inverse_depth_step_per_m: float = 0.0  # disparity quantisation: 1/z rounded to this step
    depth_lateral_noise_px: float = 0.0  # std of the pixel jitter at depth discontinuities
    edge_dropout_prob: float = 0.0  # chance of no reading on a pixel at a depth discontinuity
    projector_baseline_m: float = 0.0  # projector shadows (projector to the camera's +x)
    dark_dropout_luma: float = 0.0  # below this surface luma [0, 1] readings drop out (ramp to 0)
    shiny_dropout_deg: float = 0.0  # no reading on shiny surfaces within this incidence angle
    grazing_dropout_deg: float = 0.0  # no reading beyond this incidence angle (0: off)

    # -- Colour sensor model (defaults: exact colour) --
    rgb_shift_x_px: float = 0.0  # colour image shifted against depth (registration error)
    rgb_shift_y_px: float = 0.0
    motion_blur_samples: int = 0  # >= 2: colour is the mean of this many renders over the exposure
    exposure_time_s: float = 0.0
    exposure_drift: float = 0.0  # > 0: auto exposure plus a slow relative gain wander of this size
    white_balance_drift: float = 0.0  # relative red / blue gain wander
    rgb_noise_std: float = 0.0  # Gaussian noise, 8-bit levels

    # -- Timing --
    dropped_frame_rate: float = 0.0  # chance per sensor frame that a drop burst (1-3 frames) starts
    colour_delay_s: float = 0.0  # colour taken this long after depth (unsynchronised streams), < 20 ms
    light_level: float = 1.0  # scale of all lighting: another time of day (0.5: dusk)

    def __post_init__(self) -> None:
        # Canonical types (YAML may give 525 for 525.0): equal specs hash equally, seeds are ints.
        if self.place not in PLACES:
            raise ConfigError(f"synthetic: place must be one of {list(PLACES)}, got {self.place!r}")
        for name in ("seed", "n_frames", "width", "height", "loop_revolutions", "motion_blur_samples", "route"):
            v = getattr(self, name)
            if isinstance(v, bool) or not float(v).is_integer():
                raise ConfigError(f"synthetic: {name} must be an integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("fx", "fy", "cx", "cy", "depth_scale", "fps", "gt_rate_hz", "max_depth_m"):
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in _EXTENSION_FLOAT_FIELDS:
            v = getattr(self, name)
            signed = name.startswith("rgb_shift_")
            if isinstance(v, bool) or not math.isfinite(float(v)) or (float(v) < 0 and not signed):
                raise ConfigError(f"synthetic: {name} must be a finite {'' if signed else 'non-negative '}"
                                  f"number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.place == "suite":
            from atlas_pipeline.sensors.synthetic_places import SUITE_ROUTES

            if self.route not in SUITE_ROUTES:
                raise ConfigError(f"synthetic: route must be one of {sorted(SUITE_ROUTES)}, got {self.route}")
            if self.loop_revolutions or self.pan_rate_deg_per_s:
                raise ConfigError("synthetic: place 'suite' follows its route: loop_revolutions and "
                                  "pan_rate_deg_per_s must be 0")
        if not 0.05 <= self.light_level <= 4.0:
            raise ConfigError(f"synthetic: light_level must be in [0.05, 4], got {self.light_level}")
        for name in ("loop_revolutions", "motion_blur_samples"):
            if getattr(self, name) < 0:
                raise ConfigError(f"synthetic: {name} must be >= 0, got {getattr(self, name)}")
        if self.colour_delay_s >= MAX_ASSOCIATION_DT_S:
            raise ConfigError(f"synthetic: colour_delay_s must be < {MAX_ASSOCIATION_DT_S} (the pairing gap), "
                              f"got {self.colour_delay_s}")
        if self.dropped_frame_rate >= 0.5:
            raise ConfigError(f"synthetic: dropped_frame_rate must be < 0.5, got {self.dropped_frame_rate}")
        if self.edge_dropout_prob > 1.0 or self.dark_dropout_luma > 1.0:
            raise ConfigError("synthetic: edge_dropout_prob and dark_dropout_luma must be <= 1")
        if self.shiny_dropout_deg >= 90.0 or self.grazing_dropout_deg > 90.0:
            raise ConfigError("synthetic: shiny_dropout_deg must be < 90 and grazing_dropout_deg <= 90")
        if self.orbit_rate_deg_per_s <= 0:
            raise ConfigError(
                f"synthetic: orbit_rate_deg_per_s must be positive, got {self.orbit_rate_deg_per_s}"
            )
        if self.loop_revolutions and self.n_frames < 2:
            raise ConfigError("synthetic: a loop needs at least 2 frames")
        if self.n_frames <= 0:
            raise ConfigError(f"synthetic: n_frames must be positive, got {self.n_frames}")
        if self.fps <= 0 or self.gt_rate_hz <= 0:
            raise ConfigError(
                f"synthetic: fps and gt_rate_hz must be positive, got {self.fps}, {self.gt_rate_hz}"
            )
        if self.max_depth_m <= 0:
            raise ConfigError(f"synthetic: max_depth_m must be positive, got {self.max_depth_m}")
        if self.max_depth_m * self.depth_scale > 65535:
            raise ConfigError(
                f"synthetic: max_depth_m={self.max_depth_m} does not fit 16 bits at "
                f"depth_scale={self.depth_scale}"
            )
        self.camera()  # validates size and focal lengths
        if self.pan_rate_deg_per_s > 0:
            from atlas_pipeline.sensors.synthetic_path import _orbit_rate_rad_s  # the path reads the spec

            orbit_deg_s = math.degrees(_orbit_rate_rad_s(self))
            if self.pan_rate_deg_per_s < orbit_deg_s + 5.0:
                raise ConfigError(
                    f"synthetic: pan_rate_deg_per_s={self.pan_rate_deg_per_s} must exceed the orbit "
                    f"rate ({orbit_deg_s:.1f} deg/s) by at least 5 deg/s"
                )

    @property
    def custom_motion(self) -> bool:
        """True when any motion field differs from the default orbit."""
        return any(getattr(self, n) != _FIELD_DEFAULTS[n] for n in _MOTION_FIELDS)

    @property
    def sensor_model(self) -> bool:
        """True when any sensor or timing effect is on (an ideal sensor otherwise)."""
        return any(getattr(self, n) != _FIELD_DEFAULTS[n] for n in _SENSOR_FIELDS)

    def camera(self) -> CameraIntrinsics:
        """Intrinsics of the rendered (undistorted) camera."""
        return CameraIntrinsics(
            width=self.width,
            height=self.height,
            fx=self.fx,
            fy=self.fy,
            cx=self.cx,
            cy=self.cy,
            depth_scale=self.depth_scale,
        )


# Fields of generator version 1; every later field is optional and left out of the hash and of
# synthetic_spec.json while at its default, so the default dataset stays byte-identical.
_V1_FIELDS = ("seed", "n_frames", "width", "height", "fx", "fy", "cx", "cy", "depth_scale", "fps",
              "gt_rate_hz", "max_depth_m")
_MOTION_FIELDS = ("orbit_rate_deg_per_s", "loop_revolutions", "pan_rate_deg_per_s", "shake_m",
                  "shake_deg", "look_at_height_m", "place", "route", "suite_speed_m_per_s")
PLACES = ("room", "suite")
_FIELD_DEFAULTS = {f.name: f.default for f in fields(SyntheticSpec)}
_SENSOR_FIELDS = tuple(n for n in _FIELD_DEFAULTS if n not in _V1_FIELDS and n not in _MOTION_FIELDS)
_EXTENSION_FLOAT_FIELDS = tuple(
    n for n in _FIELD_DEFAULTS
    if n not in _V1_FIELDS and n not in ("loop_revolutions", "motion_blur_samples", "place", "route")
)
# A Kinect v1 / Xtion-class structured-light RGB-D camera (the sensor of the TUM RGB-D benchmark).
KINECT_V1_SENSOR: dict[str, float | int] = {
    # Axial noise, Nguyen, Izadi & Lovell, "Modeling Kinect Sensor Noise for Improved 3D
    # Reconstruction and Tracking", 3DIMPVT 2012, eq. for theta < 60 deg:
    # sigma_z(z, theta) = 0.0012 + 0.0019 (z - 0.4)^2 + 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2
    # (metres): 1.9 mm at 1 m, 1.4 cm at 3 m.
    "depth_noise_a_m": 0.0012,
    "depth_noise_b_per_m": 0.0019,
    "depth_noise_angle_m": 0.0001,
    # Disparity comes from block matching with a 9x9 window, so neighbouring pixels share most of
    # their error: noise is mostly a smooth field (terraces once quantised), not per-pixel salt.
    "depth_noise_corr_px": 9.0,
    # Disparity is measured in 1/8 pixel steps by an IR camera with f = 580 px and a 7.5 cm
    # baseline (Khoshelham & Elberink, Sensors 2012): 1/z steps of 0.125 / (580 * 0.075) =
    # 0.002874 per metre, i.e. depth steps of 2.9 mm at 1 m and 2.6 cm at 3 m.
    "inverse_depth_step_per_m": 0.002874,
    # Nguyen et al.: lateral noise ~0.8 px; applied at depth discontinuities (jagged silhouettes).
    "depth_lateral_noise_px": 0.8,
    "edge_dropout_prob": 0.5,  # the 9x9 correlation window straddling an edge often fails
    "projector_baseline_m": 0.075,  # IR projector 7.5 cm from the IR camera: occlusion shadows
    "dark_dropout_luma": 0.12,  # very dark (low IR reflectance) texture drops out
    "shiny_dropout_deg": 15.0,  # glossy surfaces seen within 15 deg of head-on: saturated speckle
    "grazing_dropout_deg": 78.0,  # the speckle pattern is unreadable at grazing incidence
    # Colour camera: 1-2 px registration error against depth, ~10 ms exposure indoors (blur),
    # auto exposure and white balance that drift, ~2 levels of sensor noise, and a USB stream
    # that drops a frame now and then (TUM's fr1 sequences have gaps of 1-3 frames).
    "rgb_shift_x_px": 1.5,
    "rgb_shift_y_px": -1.0,
    "motion_blur_samples": 3,
    "exposure_time_s": 0.010,
    "exposure_drift": 0.15,
    "white_balance_drift": 0.05,
    "rgb_noise_std": 2.0,
    "dropped_frame_rate": 0.02,
}
# A person walking slowly around the room (12 deg/s of orbit: ~1.4 cm per frame at 30 fps) who
# pans the camera 80 deg at 60 deg/s (2 deg per frame, the speed at which tracking was lost on a
# real kitchen sequence) and shakes it by 3 mm / 0.15 deg at 5-10 Hz.
HANDHELD_MOTION: dict[str, float | int] = {
    "orbit_rate_deg_per_s": 12.0,
    "pan_rate_deg_per_s": 60.0,
    "shake_m": 0.003,
    "shake_deg": 0.15,
}
# One full turn around the room (~12 m of path) ending 3 mm from the start: loop closure tests.
LOOP_MOTION: dict[str, float | int] = {"loop_revolutions": 1}
# The same turn looking across the room at the camera's height, over the objects: most depth
# readings lie 3-5 m away, where the Kinect's noise is 1.4-4 cm, and loops close on far geometry.
FAR_LOOP_MOTION: dict[str, float | int] = {"loop_revolutions": 1, "look_at_height_m": 1.4}
# A walk through the three-room suite (~25 m, back to its start) and a second visit of it on
# another path, lower, at dusk (light_level 0.55, auto exposure on), with the noisy sensor.
SUITE_PRESETS: dict[str, dict[str, float | int | str]] = {
    "synthetic-suite": {"seed": 0, "n_frames": 1500, "width": 640, "height": 480, "place": "suite", "route": 0,
                        **KINECT_V1_SENSOR, "shake_m": 0.002, "shake_deg": 0.1},
    "synthetic-suite-visit2": {"seed": 0, "n_frames": 900, "width": 640, "height": 480, "place": "suite",
                               "route": 1, **KINECT_V1_SENSOR, "shake_m": 0.002, "shake_deg": 0.1,
                               "light_level": 0.55},
}
# The registry presets of configs/datasets.yaml, as spec keyword arguments (a test keeps them equal).
SYNTHETIC_PRESETS: dict[str, dict[str, float | int]] = {
    "synthetic-noisy": {"seed": 0, "n_frames": 60, "width": 640, "height": 480, **KINECT_V1_SENSOR},
    "synthetic-handheld": {"seed": 0, "n_frames": 150, "width": 640, "height": 480,
                           **KINECT_V1_SENSOR, **HANDHELD_MOTION},
    "synthetic-loop": {"seed": 0, "n_frames": 300, "width": 320, "height": 240, "fx": 262.5, "fy": 262.5,
                       "cx": 159.5, "cy": 119.5, **KINECT_V1_SENSOR, **LOOP_MOTION},
    "synthetic-loop-far": {"seed": 0, "n_frames": 300, "width": 320, "height": 240, "fx": 262.5, "fy": 262.5,
                           "cx": 159.5, "cy": 119.5, **KINECT_V1_SENSOR, **FAR_LOOP_MOTION},
    **SUITE_PRESETS,
}


def _spec_dict(spec: SyntheticSpec) -> dict:
    """The spec's fields, less the optional ones still at their defaults (a default spec gives the
    same dictionary, hash and ``synthetic_spec.json`` as generator version 1 always did)."""
    d = asdict(spec)
    return {k: v for k, v in d.items() if k in _V1_FIELDS or v != _FIELD_DEFAULTS[k]}


def spec_hash(spec: SyntheticSpec) -> str:
    """Hex sha256 of the spec and generator version: the content of the ``.complete`` marker."""
    payload = json.dumps({"generator_version": GENERATOR_VERSION, **_spec_dict(spec)}, sort_keys=True)
    return hashlib.sha256(payload.encode("utf-8")).hexdigest()
