"""Deterministic synthetic RGB-D sequences in TUM RGB-D layout.

The generator renders a textured room with a few objects from a smooth hand-held-like camera path
and writes exactly what the TUM loader reads, so synthetic data exercises the same code path as
real recordings::

    out_dir/rgb/<timestamp>.png      8-bit RGB, width x height
    out_dir/depth/<timestamp>.png    16-bit, metres * depth_scale, 0 = no reading
    out_dir/rgb.txt                  "# ..." header (3 lines), then "timestamp rgb/<ts>.png"
    out_dir/depth.txt                same for depth
    out_dir/groundtruth.txt          "timestamp tx ty tz qx qy qz qw", T_world_cam, TUM order
    out_dir/synthetic_spec.json      the spec and intrinsics (informational)
    out_dir/.complete                hash of the spec; written last, marks a finished dataset

Scene (world frame, metres, z up): the room is the box ``[-3, 3] x [-2.5, 2.5] x [0, 3]``, floor at
``z = 0``; 4-6 axis-aligned boxes, spheres and vertical cylinders stand on the floor in the middle
of the room. Every surface carries a procedural texture that is a function of the 3D surface point
(value-noise fBm + checker + stripes), so colour is identical from every view, with Lambertian
shading from fixed directional lights (no specular or view-dependent terms).

Camera path: an ellipse (semi-axes 2.2 m x 1.7 m) around the room centre at ~1.4 m height with a
gentle vertical bob, a wobbling look-at target (yaw/pitch variation) and a small roll, travelling
36 deg/s, i.e. 72 deg over the default 60 frames at 30 fps (~4 cm and ~1.3 deg per frame).

Timing: frame ``i`` has depth timestamp ``1000 + i / fps`` (the frame time: a frame's pose is its
depth image's, ``sensors/tum.py``) and both images are rendered at that pose, so colour and depth
are consistent. The sensor model's ``colour_delay_s`` takes the colour that much later instead,
rendered and stamped there, as an unsynchronised Kinect's (TUM fr1: ~15 ms). Ground truth is
sampled from the same continuous path at ``gt_rate_hz``, so it is exact.

Determinism: the same spec gives byte-identical files. Per-pixel code uses only IEEE-exact
elementwise arithmetic (no BLAS, no transcendental functions), so results do not depend on SIMD
code paths; PNGs are written by Pillow with fixed settings and no metadata.

Realistic sensor and motion (optional; every new :class:`SyntheticSpec` field defaults to "off",
and a spec that leaves them all at their defaults writes exactly the files it always did):

* **Depth** (Kinect v1 structured light, see :data:`KINECT_V1_SENSOR` for the constants and their
  sources): axial noise ``sigma_z = a + b (z - 0.4)^2 + c / sqrt(z) * theta^2 / (pi/2 - theta)^2``
  (Nguyen, Izadi, Lovell 2012, ``theta`` = angle of incidence), mostly spatially correlated (block
  matching over a 9x9 window); disparity quantisation (1/z rounded to a fixed step, so steps grow
  with z^2; the Gaussian part is reduced so that noise plus quantisation has the model's total
  std); projector shadows (no reading where the projector, a baseline to the side, cannot see
  the surface: left of foreground objects) and dropped or laterally jittered pixels at depth
  discontinuities; no reading on dark surfaces (low IR reflectance), on shiny surfaces seen
  head-on (spheres: saturated speckle) and at grazing incidence.
* **Colour**: motion blur (the mean of sub-frame renders over the exposure time), exposure drift
  with auto exposure, white-balance drift, Gaussian sensor noise, and a fixed shift of the colour
  image against depth (imperfect registration).
* **Timing**: dropped frames (bursts of 1-3 missing sensor frames: gaps in the timestamps).
* **Motion**: a slower walk with sustained pans (``pan_rate_deg_per_s``, camera yaw rate in the
  world during a pan) and hand shake (a few mm and a fraction of a degree at 5-10 Hz); or a closed
  loop (``loop_revolutions``) that goes around the room and ends 3 mm from its start pose.

All randomness comes from ``numpy.random.default_rng`` streams keyed by the seed (and the frame
index), so noisy datasets are as reproducible as clean ones.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from functools import lru_cache
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from atlas_pipeline.errors import ConfigError
from atlas_pipeline.geometry import look_at, rotmat_to_quat_xyzw
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.tum import MAX_ASSOCIATION_DT_S

__all__ = [
    "SyntheticSpec",
    "SyntheticScene",
    "SceneObject",
    "build_scene",
    "camera_path",
    "render_synthetic_frame",
    "generate_synthetic_dataset",
    "spec_hash",
    "frame_times_s",
    "depth_noise_sigma_m",
    "apply_depth_sensor_model",
    "KINECT_V1_SENSOR",
    "HANDHELD_MOTION",
    "LOOP_MOTION",
    "SYNTHETIC_PRESETS",
    "TIMESTAMP_START_S",
    "ROOM_MIN",
    "ROOM_MAX",
]

logger = logging.getLogger(__name__)

# Bump when the rendering or file layout changes, so cached datasets are regenerated.
GENERATOR_VERSION = 3  # 3: colour stamped with depth, at the render time (2: colour 3 ms later; 1: depth 3 ms later)

TIMESTAMP_START_S = 1000.0
GT_MARGIN_S = 0.1  # ground truth extends this far before the first and after the last stamp

ROOM_MIN = np.array([-3.0, -2.5, 0.0])
ROOM_MAX = np.array([3.0, 2.5, 3.0])

# Camera path geometry (fixed; the seed only picks the starting phase and wobble phases).
_PATH_A_M = 2.2  # ellipse semi-axis along x: 0.8 m from the x walls
_PATH_B_M = 1.7  # ellipse semi-axis along y: 0.8 m from the y walls
_PATH_HEIGHT_M = 1.4
_PATH_BOB_M = 0.12
_PATH_RATE_RAD_S = math.radians(36.0)  # 72 deg of orbit over 2 s

# Objects stand inside this footprint and > 0.55 m (horizontally) from the path ellipse.
_OBJ_REGION_XY = (1.4, 1.0)
_MIN_CLEARANCE_M = 0.55

# Surface ids: room surfaces first, then one per object.
_SID_FLOOR, _SID_CEILING = 0, 1
_SID_WALL_XMIN, _SID_WALL_XMAX, _SID_WALL_YMIN, _SID_WALL_YMAX = 2, 3, 4, 5
_N_ROOM_SURFACES = 6

# Lighting: ambient + a key light from above and a weak fill, both directional (view-independent).
_AMBIENT = 0.35
_LIGHTS = (
    (np.array([0.5, 0.35, 1.0]) / np.linalg.norm([0.5, 0.35, 1.0]), 0.55),
    (np.array([-0.6, -0.4, 0.3]) / np.linalg.norm([-0.6, -0.4, 0.3]), 0.2),
)

_NOISE_N = 64  # value-noise lattice is periodic with 64 cells per axis

# Rows of the packed per-surface texture table (SyntheticScene.texture_table()).
_T_C0, _T_C1, _T_SCALE, _T_OFF, _T_CHK, _T_STRIPE = 0, 3, 6, 7, 10, 12
_T_ROWS = 16
_EPS_T = 1e-6

# ---- Optional motion (hand-held pans and shakes, closed loop) ----------------------------------
_PAN_HALF_ANGLE_DEG = 40.0  # pans sweep 80 deg: from 40 deg one side of the room centre to the other
_PAN_RAMP_S = 0.15  # time to reach / leave the pan rate: a wrist starts a pan quickly (~400 deg/s^2)
_PAN_HOLD_S = 0.8  # looking to one side between two pans
_SHAKE_BAND_HZ = (5.0, 10.0)  # hand tremor and walking jitter frequencies
_LOOP_GAP_M = 0.003  # a loop ends this far from its start pose: a revisit, not the same frame
_LOOP_ENVELOPE_S = 1.0  # pans and shakes fade in/out over this long at the ends of a loop
_MOTION_STREAM = 104729  # rng stream ids: keep the streams of different effects independent
_DROP_STREAM = 130363
_SENSOR_STREAM = 155921
_MAX_DROP_BURST = 3  # a drop loses 1-3 consecutive sensor frames (USB hiccups come in bursts)

# ---- Optional sensor model ---------------------------------------------------------------------
_NGUYEN_Z0_M = 0.4  # Nguyen et al. 2012: sigma_z = a + b (z - 0.4 m)^2
_MAX_NOISE_ANGLE_RAD = math.radians(80.0)  # the angle term diverges at 90 deg: capped here
_EDGE_JUMP_REL = 0.04  # a neighbour farther by > 4 % of depth is a discontinuity (a slanted floor
#                        at 6 m changes < 1 % per pixel)
_CORRELATED_NOISE_FRACTION = 0.75  # of the noise variance, when correlated; the rest is per-pixel
#                                    flicker (an assumption: Nguyen et al. measured the total only)
_SHADOW_TOL_PX = 0.5  # projector-ordering tolerance: rounding on slanted planes is not a shadow
_SHINY_KINDS = ("sphere",)  # glossy objects: no depth where seen head-on
_AE_TARGET_LUMA = 0.45  # auto exposure pulls the mean luma toward this (halfway, in log terms)
_AE_GAIN_RANGE = (0.7, 1.4)
_EXPOSURE_DRIFT_HZ = (0.11, 0.29)  # slow gain wander on top of auto exposure
_WHITE_BALANCE_HZ = (0.07, 0.05)  # red and blue gains drift independently (green is the reference)


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
                  "shake_deg", "place", "route", "suite_speed_m_per_s")
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
# real kitchen sequence, issue 11) and shakes it by 3 mm / 0.15 deg at 5-10 Hz.
HANDHELD_MOTION: dict[str, float | int] = {
    "orbit_rate_deg_per_s": 12.0,
    "pan_rate_deg_per_s": 60.0,
    "shake_m": 0.003,
    "shake_deg": 0.15,
}

# One full turn around the room (~12 m of path) ending 3 mm from the start: loop closure tests.
LOOP_MOTION: dict[str, float | int] = {"loop_revolutions": 1}

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
    **SUITE_PRESETS,
}


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One object standing on the floor.

    Attributes:
        kind: ``"box"``, ``"sphere"`` or ``"cylinder"`` (vertical axis).
        centre: ``[3]`` box centre, sphere centre, or cylinder axis point at mid height.
        half_size: ``[3]`` box half extents; for a sphere ``(r, r, r)``; for a cylinder
            ``(r, r, h/2)``.
        surface_id: index into the scene's texture table.
    """

    kind: str
    centre: np.ndarray
    half_size: np.ndarray
    surface_id: int


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """Room, objects and per-surface textures of one seed.

    Attributes:
        seed: the seed it was built from.
        room_min, room_max: ``[3]`` corners of the room box.
        objects: the objects, each with its own surface id.
        noise: ``[65 * 65 * 65]`` float32 value-noise lattice in [0, 1], flattened; periodic with
            64 cells per axis (index 64 repeats index 0, so corner lookups need no wrap).
        tex_c0, tex_c1: ``[S, 3]`` the two colours each surface's noise blends between.
        tex_scale: ``[S]`` noise lattice cells per metre of the coarsest octave.
        tex_offset: ``[S, 3]`` lattice offset, so surfaces do not share noise.
        checker_size: ``[S]`` checker cell size in metres (0 = none).
        checker_contrast: ``[S]`` darkening of odd checker cells.
        stripe_dir: ``[S, 3]`` stripe wave vector in cycles per metre.
        stripe_contrast: ``[S]`` stripe darkening amplitude.
    """

    seed: int
    room_min: np.ndarray
    room_max: np.ndarray
    objects: tuple[SceneObject, ...]
    noise: np.ndarray = field(repr=False)
    tex_c0: np.ndarray
    tex_c1: np.ndarray
    tex_scale: np.ndarray
    tex_offset: np.ndarray
    checker_size: np.ndarray
    checker_contrast: np.ndarray
    stripe_dir: np.ndarray
    stripe_contrast: np.ndarray

    def texture_table(self) -> np.ndarray:
        """All texture parameters packed as ``[16, S]`` float32 (rows: c0 rgb, c1 rgb, scale,
        offset xyz, 1 / checker size (0 = none), checker contrast, stripe xyz, stripe contrast)."""
        tab = np.zeros((_T_ROWS, self.tex_c0.shape[0]), dtype=np.float32)
        tab[_T_C0:_T_C0 + 3] = self.tex_c0.T
        tab[_T_C1:_T_C1 + 3] = self.tex_c1.T
        tab[_T_SCALE] = self.tex_scale
        tab[_T_OFF:_T_OFF + 3] = self.tex_offset.T
        cs = self.checker_size
        tab[_T_CHK] = np.where(cs > 0, 1.0 / np.where(cs > 0, cs, 1.0), 0.0)
        tab[_T_CHK + 1] = self.checker_contrast
        tab[_T_STRIPE:_T_STRIPE + 3] = self.stripe_dir.T
        tab[_T_STRIPE + 3] = self.stripe_contrast
        return tab

    def clearance_m(self, points_xyz: np.ndarray) -> np.ndarray:
        """Distance ``[N]`` from points ``[N, 3]`` to the nearest wall or object surface.

        Points inside an object get 0, points outside the room a negative distance.
        """
        p = np.atleast_2d(np.asarray(points_xyz, dtype=np.float64))
        d = np.minimum(p - self.room_min, self.room_max - p).min(axis=1)
        for obj in self.objects:
            d = np.minimum(d, _object_distance(obj, p))
        return d


def _object_distance(obj: SceneObject, p: np.ndarray) -> np.ndarray:
    """Euclidean distance ``[N]`` from points ``[N, 3]`` to the object (0 inside)."""
    c, h = obj.centre, obj.half_size
    if obj.kind == "box":
        q = np.maximum(np.abs(p - c) - h, 0.0)
        return np.linalg.norm(q, axis=1)
    if obj.kind == "sphere":
        return np.maximum(np.linalg.norm(p - c, axis=1) - h[0], 0.0)
    # Cylinder: radial and axial excess combine like a 2D box distance.
    radial = np.maximum(np.linalg.norm(p[:, :2] - c[:2], axis=1) - h[0], 0.0)
    axial = np.maximum(np.abs(p[:, 2] - c[2]) - h[2], 0.0)
    return np.hypot(radial, axial)


def _footprint_radius(kind: str, half: np.ndarray) -> float:
    """Horizontal radius of a bounding circle (used for spacing and clearance checks)."""
    return float(np.hypot(half[0], half[1])) if kind == "box" else float(half[0])


def _ellipse_clearance(xy: np.ndarray, r: float) -> float:
    """Smallest horizontal distance from a disc (centre ``xy`` ``[2]``, radius ``r``) to the
    camera path ellipse."""
    th = np.linspace(0.0, 2.0 * np.pi, 2048, endpoint=False)
    ex = _PATH_A_M * np.cos(th)
    ey = _PATH_B_M * np.sin(th)
    return float(np.min(np.hypot(ex - xy[0], ey - xy[1]))) - r


def _place_objects(rng: np.random.Generator, kinds: list[str]) -> list[SceneObject] | None:
    """Rejection-sample non-overlapping objects of ``kinds`` standing on the floor.

    A draw that cannot fit every object starts over (up to 50 times), so a scene always has all
    of its objects; returns None if even that fails.
    """
    rx, ry = _OBJ_REGION_XY
    for _restart in range(50):
        objects: list[SceneObject] = []
        placed: list[tuple[np.ndarray, float]] = []
        for kind in kinds:
            for _attempt in range(300):
                if kind == "box":
                    half = np.array(
                        [rng.uniform(0.15, 0.35), rng.uniform(0.15, 0.3), rng.uniform(0.15, 0.5)]
                    )
                elif kind == "sphere":
                    r = rng.uniform(0.18, 0.35)
                    half = np.array([r, r, r])
                else:
                    r = rng.uniform(0.12, 0.25)
                    half = np.array([r, r, rng.uniform(0.25, 0.6)])
                xy = np.array([rng.uniform(-rx, rx), rng.uniform(-ry, ry)])
                # The whole footprint must lie inside the object region.
                if abs(xy[0]) + half[0] > rx or abs(xy[1]) + half[1] > ry:
                    continue
                fr = _footprint_radius(kind, half)
                if any(np.linalg.norm(xy - pxy) < fr + pr + 0.1 for pxy, pr in placed):
                    continue
                if _ellipse_clearance(xy, fr) < _MIN_CLEARANCE_M:
                    continue
                break
            else:  # too crowded for this draw
                break
            placed.append((xy, fr))
            centre = np.array([xy[0], xy[1], half[2]])  # resting on the floor
            objects.append(SceneObject(kind, centre, half, _N_ROOM_SURFACES + len(objects)))
        if len(objects) == len(kinds):
            return objects
        logger.debug("synthetic scene: %d of %d objects fit, retrying", len(objects), len(kinds))
    return None


def build_scene(seed: int) -> SyntheticScene:
    """Room and 4-6 objects placed from ``seed`` (``numpy.random.default_rng(seed)``).

    Objects (at least two boxes, a sphere and a cylinder) are rejection-sampled so they do not
    overlap and stay more than 0.55 m (horizontally) from the camera path ellipse for any phase,
    which keeps every camera pose clear of them.
    """
    rng = np.random.default_rng(seed)
    n_obj = int(rng.integers(4, 7))
    kinds = ["box", "box", "sphere", "cylinder"] + [
        str(k) for k in rng.choice(["box", "sphere", "cylinder"], size=n_obj - 4)
    ]
    kinds = [kinds[i] for i in rng.permutation(n_obj)]

    objects = _place_objects(rng, kinds)
    if objects is None:
        # Never observed (300 seeds checked); fail loudly rather than build a different scene.
        raise RuntimeError(f"synthetic scene {seed}: could not place {kinds}")
    return textured_scene(seed, rng, objects, ROOM_MIN, ROOM_MAX)


def textured_scene(seed: int, rng: np.random.Generator, objects: list[SceneObject], room_min: np.ndarray,
                   room_max: np.ndarray, flat_ids: tuple[int, ...] = ()) -> SyntheticScene:
    """The scene of ``objects`` in the box ``room_min``..``room_max`` ``[3]`` with textures drawn
    from ``rng``; objects whose surface id is in ``flat_ids`` (partition walls) get wallpaper
    instead of an object's saturated colour."""
    n_surf = _N_ROOM_SURFACES + len(objects)
    noise = rng.random((_NOISE_N,) * 3, dtype=np.float32)
    noise = np.pad(noise, ((0, 1),) * 3, mode="wrap").ravel()  # [65^3], see SyntheticScene.noise

    # Room palette: warm floor, light walls with distinct tints, pale ceiling.
    c0 = np.zeros((n_surf, 3))
    c1 = np.zeros((n_surf, 3))
    c0[_SID_FLOOR], c1[_SID_FLOOR] = (0.55, 0.36, 0.2), (0.85, 0.65, 0.42)
    c0[_SID_CEILING], c1[_SID_CEILING] = (0.6, 0.6, 0.62), (0.95, 0.95, 0.9)
    wall_tints = [(0.75, 0.55, 0.5), (0.5, 0.65, 0.75), (0.6, 0.72, 0.5), (0.78, 0.72, 0.5)]
    for k, tint in enumerate(wall_tints):
        t = np.array(tint)
        c0[_SID_WALL_XMIN + k], c1[_SID_WALL_XMIN + k] = 0.45 * t, np.minimum(1.0, 1.25 * t)
    for obj in objects:
        base = rng.uniform(0.15, 0.95, size=3)
        base[rng.integers(3)] = rng.uniform(0.75, 1.0)  # one strong channel: saturated colour
        if obj.surface_id in flat_ids:
            base = 0.55 + 0.4 * base  # a painted wall: pale
        c0[obj.surface_id] = 0.35 * base if obj.surface_id not in flat_ids else 0.6 * base
        c1[obj.surface_id] = base

    tex_scale = np.full(n_surf, 2.0)
    tex_scale[_N_ROOM_SURFACES:] = rng.uniform(3.0, 5.0, size=len(objects))
    tex_offset = rng.uniform(0.0, _NOISE_N, size=(n_surf, 3))
    checker_size = np.zeros(n_surf)
    checker_contrast = np.zeros(n_surf)
    checker_size[_SID_FLOOR], checker_contrast[_SID_FLOOR] = 0.5, 0.25  # floor tiles
    checker_size[_SID_CEILING], checker_contrast[_SID_CEILING] = 0.6, 0.12
    stripe_dir = np.zeros((n_surf, 3))
    stripe_contrast = np.zeros(n_surf)
    # Wallpaper: vertical stripes on x walls, slanted ones on y walls.
    stripe_dir[_SID_WALL_XMIN] = stripe_dir[_SID_WALL_XMAX] = (0.0, 4.0, 0.0)
    stripe_dir[_SID_WALL_YMIN] = stripe_dir[_SID_WALL_YMAX] = (3.0, 0.0, 2.0)
    stripe_contrast[_SID_WALL_XMIN:_SID_WALL_YMAX + 1] = 0.3
    for obj in objects:
        sid = obj.surface_id
        if obj.kind == "sphere":
            checker_size[sid], checker_contrast[sid] = rng.uniform(0.08, 0.14), 0.35
        elif obj.kind == "cylinder":
            stripe_dir[sid] = (0.0, 0.0, rng.uniform(5.0, 8.0))  # horizontal rings
            stripe_contrast[sid] = 0.35
        else:
            v = rng.normal(size=3)
            stripe_dir[sid] = v / np.linalg.norm(v) * rng.uniform(4.0, 7.0)
            stripe_contrast[sid] = 0.25

    return SyntheticScene(
        seed=seed,
        room_min=np.asarray(room_min, np.float64).copy(),
        room_max=np.asarray(room_max, np.float64).copy(),
        objects=tuple(objects),
        noise=noise,
        tex_c0=c0.astype(np.float32),
        tex_c1=c1.astype(np.float32),
        tex_scale=tex_scale.astype(np.float32),
        tex_offset=tex_offset.astype(np.float32),
        checker_size=checker_size.astype(np.float32),
        checker_contrast=checker_contrast.astype(np.float32),
        stripe_dir=stripe_dir.astype(np.float32),
        stripe_contrast=stripe_contrast.astype(np.float32),
    )


# ----------------------------------------------------------------------------------------------
# Camera path


def _path_phases(seed: int) -> np.ndarray:
    """``[6]`` phases of the path: start angle, bob, target wobble x/y/z, roll."""
    # A separate stream from the scene's, so the path does not change if the scene code does.
    return np.random.default_rng([seed, 7919]).uniform(0.0, 2.0 * math.pi, size=6)


def _pose_at(t: float, ph: np.ndarray) -> np.ndarray:
    """``T_world_cam`` ``[4, 4]`` at time ``t`` seconds (scalar math: platform-independent)."""
    th = float(ph[0]) + _PATH_RATE_RAD_S * t
    eye = np.array(
        [
            _PATH_A_M * math.cos(th),
            _PATH_B_M * math.sin(th),
            _PATH_HEIGHT_M + _PATH_BOB_M * math.sin(2.0 * math.pi * 0.35 * t + float(ph[1])),
        ]
    )
    # Wobbling target: yaw +-~10 deg and pitch variation on top of the orbit.
    target = np.array(
        [
            0.35 * math.sin(2.0 * math.pi * 0.21 * t + float(ph[2])),
            0.30 * math.sin(2.0 * math.pi * 0.17 * t + float(ph[3])),
            0.55 + 0.10 * math.sin(2.0 * math.pi * 0.27 * t + float(ph[4])),
        ]
    )
    T = look_at(eye, target, up=(0.0, 0.0, 1.0))
    # Small roll about the optical axis so all three rotation axes are exercised.
    roll = math.radians(3.0) * math.sin(2.0 * math.pi * 0.23 * t + float(ph[5]))
    c, s = math.cos(roll), math.sin(roll)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R = T[:3, :3]
    # Explicit products instead of BLAS matmul: bitwise reproducible everywhere.
    T[:3, :3] = (R[:, :, None] * Rz[None, :, :]).sum(axis=1)
    return T


def frame_times_s(spec: SyntheticSpec) -> np.ndarray:
    """Capture times ``[n_frames]`` of the frames, seconds from the first.

    Frame ``i`` is at ``i / fps`` unless ``dropped_frame_rate`` > 0: then each sensor frame slot
    starts a drop burst of 1-3 slots with that probability (never before the first frame), and
    the frames that remain keep their slot times, so the timestamps have gaps.
    """
    n = spec.n_frames
    if spec.dropped_frame_rate <= 0.0:
        return np.arange(n, dtype=np.float64) / spec.fps
    rng = np.random.default_rng([spec.seed, _DROP_STREAM])
    slots = [0]
    k = 1
    while len(slots) < n:
        if rng.random() < spec.dropped_frame_rate:
            k += int(rng.integers(1, _MAX_DROP_BURST + 1))
        slots.append(k)
        k += 1
    return np.asarray(slots, dtype=np.float64) / spec.fps


def _orbit_rate_rad_s(spec: SyntheticSpec) -> float:
    """Angular speed along the ellipse: the spec's, or one that closes ``loop_revolutions`` turns
    exactly at the last frame."""
    if spec.loop_revolutions > 0:
        return 2.0 * math.pi * spec.loop_revolutions / float(frame_times_s(spec)[-1])
    return math.radians(spec.orbit_rate_deg_per_s)


@dataclass(frozen=True)
class _Motion:
    """Parameters of a non-default path (see :func:`_motion_of`)."""

    rate: float  # orbit, rad/s
    time_scale: float  # path-shape time per second: wobbles keep their shape at any orbit speed
    freqs: tuple[float, ...]  # bob, target x/y/z, roll (Hz of path-shape time)
    t_end: float  # loop: time of the last frame (0 otherwise)
    pan_up: float  # pan sweeps relative to the look-at direction, rad/s (0: no pans)
    pan_down: float
    pan_phase_s: float
    shake_m: float
    shake_rad: float
    shake_f: np.ndarray  # [6, 2] Hz: x, y, z, rx, ry, rz, two sines each
    shake_ph: np.ndarray  # [6, 2]


@lru_cache(maxsize=8)
def _motion_of(spec: SyntheticSpec) -> _Motion:
    """Path parameters of ``spec`` (cached: camera_path is called per frame and sub-frame)."""
    rate = _orbit_rate_rad_s(spec)
    scale = rate / _PATH_RATE_RAD_S
    freqs = (0.35, 0.21, 0.17, 0.27, 0.23)
    t_end = 0.0
    if spec.loop_revolutions > 0:
        t_end = float(frame_times_s(spec)[-1])
        # Whole cycles over the loop, so bob, wobble and roll return to their start values.
        tau_end = t_end * scale
        freqs = tuple(round(f * tau_end) / tau_end for f in freqs)
    rng = np.random.default_rng([spec.seed, _MOTION_STREAM])
    pan_phase = float(rng.uniform(0.0, 1.0))
    shake_f = rng.uniform(*_SHAKE_BAND_HZ, size=(6, 2))
    shake_ph = rng.uniform(0.0, 2.0 * math.pi, size=(6, 2))
    pan_up = pan_down = 0.0
    if spec.pan_rate_deg_per_s > 0:
        # The look-at direction itself turns with the orbit (+rate about z): sweeps against and
        # with it get different relative speeds, so the world yaw rate is the pan rate both ways.
        v = math.radians(spec.pan_rate_deg_per_s)
        pan_up, pan_down = v - rate, v + rate
    return _Motion(rate, scale, freqs, t_end, pan_up, pan_down, pan_phase, spec.shake_m,
                   math.radians(spec.shake_deg), shake_f, shake_ph)


def _sweep_rad(tau: float, v: float, amp2: float) -> float:
    """Angle covered ``tau`` s into a sweep of ``amp2`` rad at top speed ``v`` rad/s, with linear
    speed ramps of ``_PAN_RAMP_S`` at both ends (trapezoidal velocity: C1 angle)."""
    r = _PAN_RAMP_S
    c = amp2 / v - r  # cruise time: v (r + c) = amp2
    if tau <= 0.0:
        return 0.0
    if tau < r:
        return v * tau * tau / (2.0 * r)
    if tau < r + c:
        return v * r / 2.0 + v * (tau - r)
    if tau < 2.0 * r + c:
        u = tau - r - c
        return v * r / 2.0 + v * c + v * u - v * u * u / (2.0 * r)
    return amp2


def _pan_rad(t: float, m: _Motion) -> float:
    """Pan yaw offset (rad) at time ``t``: sweep left, hold, sweep right, hold, periodically."""
    a = math.radians(_PAN_HALF_ANGLE_DEG)
    d_up = 2.0 * a / m.pan_up + _PAN_RAMP_S
    d_down = 2.0 * a / m.pan_down + _PAN_RAMP_S
    period = d_up + d_down + 2.0 * _PAN_HOLD_S
    tau = (t + m.pan_phase_s * period) % period  # Python's % is non-negative for period > 0
    if tau < d_up:
        return -a + _sweep_rad(tau, m.pan_up, 2.0 * a)
    tau -= d_up
    if tau < _PAN_HOLD_S:
        return a
    tau -= _PAN_HOLD_S
    if tau < d_down:
        return a - _sweep_rad(tau, m.pan_down, 2.0 * a)
    return -a


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def _rot3(axis: int, ang: float) -> np.ndarray:
    """``[3, 3]`` rotation by ``ang`` rad about coordinate axis ``axis``."""
    c, s = math.cos(ang), math.sin(ang)
    i, j = (axis + 1) % 3, (axis + 2) % 3
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _mul3(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    # Explicit products instead of BLAS matmul: bitwise reproducible everywhere.
    return (A[:, :, None] * B[None, :, :]).sum(axis=1)


def _pose_at_motion(t: float, ph: np.ndarray, m: _Motion) -> np.ndarray:
    """``T_world_cam`` ``[4, 4]`` of a non-default path at time ``t`` (scalar math).

    The orbit of :func:`_pose_at` travelled at ``m.rate``, with the bob, wobble and roll on a time
    axis scaled to the same shape; then pans (yaw about the vertical through the eye), hand shake,
    and for loops a 3 mm linear offset and an envelope that keeps the ends free of pans and shake.
    """
    tau = t * m.time_scale
    f_bob, f_x, f_y, f_z, f_roll = m.freqs
    th = float(ph[0]) + m.rate * t
    eye = np.array(
        [
            _PATH_A_M * math.cos(th),
            _PATH_B_M * math.sin(th),
            _PATH_HEIGHT_M + _PATH_BOB_M * math.sin(2.0 * math.pi * f_bob * tau + float(ph[1])),
        ]
    )
    target = np.array(
        [
            0.35 * math.sin(2.0 * math.pi * f_x * tau + float(ph[2])),
            0.30 * math.sin(2.0 * math.pi * f_y * tau + float(ph[3])),
            0.55 + 0.10 * math.sin(2.0 * math.pi * f_z * tau + float(ph[4])),
        ]
    )
    env = 1.0
    if m.t_end > 0.0:
        ramp = min(_LOOP_ENVELOPE_S, m.t_end / 4.0)
        env = _smoothstep(t / ramp) * _smoothstep((m.t_end - t) / ramp)
        frac = min(max(t / m.t_end, 0.0), 1.0)
        eye = eye + _LOOP_GAP_M * frac * np.array([0.6, 0.0, 0.8])
    T = look_at(eye, target, up=(0.0, 0.0, 1.0))
    R = T[:3, :3]
    if m.pan_up > 0.0:
        R = _mul3(_rot3(2, env * _pan_rad(t, m)), R)  # world yaw about the eye
    roll = math.radians(3.0) * math.sin(2.0 * math.pi * f_roll * tau + float(ph[5]))
    R = _mul3(R, _rot3(2, roll))
    if m.shake_m > 0.0 or m.shake_rad > 0.0:
        w = [
            0.5 * env * sum(math.sin(2.0 * math.pi * float(m.shake_f[a, k]) * t + float(m.shake_ph[a, k]))
                            for k in range(2))
            for a in range(6)
        ]
        for a in range(3):
            R = _mul3(R, _rot3(a, m.shake_rad * w[3 + a]))
        T[:3, 3] = eye + m.shake_m * np.array(w[:3])
    T[:3, :3] = R
    return T


def camera_path(spec: SyntheticSpec, t_s: np.ndarray) -> np.ndarray:
    """Camera poses ``T_world_cam`` ``[N, 4, 4]`` at times ``t_s`` ``[N]`` (seconds from start).

    Smooth (C-infinity) in time for the default motion (pans are C1), defined for any real ``t``
    (negative included), and always more than 0.5 m from every wall and object of
    ``build_scene(spec.seed)``. A loop (``loop_revolutions``) returns to within 3 mm of its start
    pose at the last frame time.
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    if spec.place == "suite":
        return _suite_camera_path(spec, t)
    ph = _path_phases(spec.seed)
    out = np.empty((t.shape[0], 4, 4), dtype=np.float64)
    if spec.custom_motion:
        m = _motion_of(spec)
        for i, ti in enumerate(t):
            out[i] = _pose_at_motion(float(ti), ph, m)
        return out
    for i, ti in enumerate(t):
        out[i] = _pose_at(float(ti), ph)
    return out


def _suite_camera_path(spec: SyntheticSpec, t: np.ndarray) -> np.ndarray:
    """Poses ``[N, 4, 4]`` along the suite route of ``spec`` (hand shake on top when set)."""
    from atlas_pipeline.sensors.synthetic_places import route_length_m, suite_path

    speed = spec.suite_speed_m_per_s
    if speed <= 0:  # the whole route over the recording
        speed = route_length_m(spec.route) / max(float(frame_times_s(spec)[-1]), 1.0 / spec.fps)
    out = suite_path(spec.route, speed, t)
    if spec.shake_m > 0.0 or spec.shake_deg > 0.0:
        m = _motion_of(spec)
        for i, ti in enumerate(t):
            w = [0.5 * sum(math.sin(2.0 * math.pi * float(m.shake_f[a, k]) * float(ti) + float(m.shake_ph[a, k]))
                           for k in range(2)) for a in range(6)]
            R = out[i, :3, :3]
            for a in range(3):
                R = _mul3(R, _rot3(a, m.shake_rad * w[3 + a]))
            out[i, :3, :3] = R
            out[i, :3, 3] += m.shake_m * np.array(w[:3])
    return out


def scene_of(spec: SyntheticSpec) -> SyntheticScene:
    """The scene ``spec`` renders: the room of ``build_scene(seed)`` or the suite of that seed."""
    if spec.place == "suite":
        from atlas_pipeline.sensors.synthetic_places import build_suite_scene

        return build_suite_scene(spec.seed)
    return build_scene(spec.seed)


# ----------------------------------------------------------------------------------------------
# Rendering


@lru_cache(maxsize=8)
def _pixel_rays(width: int, height: int, fx: float, fy: float, cx: float, cy: float):
    """Camera-frame ray directions with unit z: ``(x [H*W], y [H*W])`` float64.

    With ``d_cam = (x, y, 1)`` the ray parameter of a hit equals its camera z (depth).
    """
    u = np.arange(width, dtype=np.float64)
    v = np.arange(height, dtype=np.float64)
    x = np.broadcast_to((u - cx) / fx, (height, width)).ravel()
    y = np.broadcast_to(((v - cy) / fy)[:, None], (height, width)).ravel()
    x.flags.writeable = False
    y.flags.writeable = False
    return x, y


def _safe_inv(d: np.ndarray) -> np.ndarray:
    # Rays parallel to a slab: a huge finite inverse avoids 0 * inf = nan in the slab test.
    return 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)


def _slab(o: np.ndarray, inv: tuple, lo: np.ndarray, hi: np.ndarray):
    """Ray/AABB slab test: (t_near [N], t_far [N]) for rays ``o + t d``, ``inv = 1 / d``."""
    t_near = None
    t_far = None
    for a in range(3):
        t1 = (lo[a] - o[a]) * inv[a]
        t2 = (hi[a] - o[a]) * inv[a]
        lo_t = np.minimum(t1, t2)
        hi_t = np.maximum(t1, t2)
        t_near = lo_t if t_near is None else np.maximum(t_near, lo_t)
        t_far = hi_t if t_far is None else np.minimum(t_far, hi_t)
    return t_near, t_far


def _intersect_object(obj: SceneObject, o: np.ndarray, d: tuple, inv: tuple) -> np.ndarray:
    """Hit parameter ``t`` ``[N]`` of each ray with the object, ``inf`` where it misses."""
    c, h = obj.centre, obj.half_size
    if obj.kind == "box":
        t_near, t_far = _slab(o, inv, c - h, c + h)
        return np.where((t_near <= t_far) & (t_near > _EPS_T), t_near, np.inf)
    if obj.kind == "sphere":
        oc = o - c
        a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        b = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2]
        cc = float(oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2]) - h[0] * h[0]
        disc = b * b - a * cc
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
        return np.where((disc > 0.0) & (t > _EPS_T), t, np.inf)
    # Vertical cylinder: side (quadratic in xy, z within range) and the two flat caps.
    oc = o - c
    a = d[0] * d[0] + d[1] * d[1]
    b = oc[0] * d[0] + oc[1] * d[1]
    cc = oc[0] * oc[0] + oc[1] * oc[1] - h[0] * h[0]
    disc = b * b - a * cc
    a_safe = np.where(a > 1e-12, a, 1.0)
    t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a_safe
    z_side = oc[2] + t_side * d[2]
    ok_side = (disc > 0.0) & (a > 1e-12) & (t_side > _EPS_T) & (np.abs(z_side) <= h[2])
    t = np.where(ok_side, t_side, np.inf)
    r2 = h[0] * h[0]
    for zc in (h[2], -h[2]):
        t_cap = (zc - oc[2]) * inv[2]
        px = oc[0] + t_cap * d[0]
        py = oc[1] + t_cap * d[1]
        ok = (t_cap > _EPS_T) & (px * px + py * py <= r2)
        t = np.minimum(t, np.where(ok, t_cap, np.inf))
    return t


def _value_noise(lattice: np.ndarray, qx, qy, qz) -> np.ndarray:
    """Trilinear value noise ``[N]`` in [0, 1] at lattice coordinates ``q*`` ``[N]`` (float32).

    ``lattice`` is the flattened ``[65, 65, 65]`` padded lattice (period 64), so the ``+1``
    corners never need a second wrap.
    """
    n, s = _NOISE_N, _NOISE_N + 1
    fx, fy, fz = np.floor(qx), np.floor(qy), np.floor(qz)
    ux, uy, uz = qx - fx, qy - fy, qz - fz
    # Smoothstep weights: C1 continuous noise, so image gradients have no seams at cell borders.
    ux = ux * ux * (3.0 - 2.0 * ux)
    uy = uy * uy * (3.0 - 2.0 * uy)
    uz = uz * uz * (3.0 - 2.0 * uz)
    base = ((fx.astype(np.int32) & (n - 1)) * s + (fy.astype(np.int32) & (n - 1))) * s + (
        fz.astype(np.int32) & (n - 1)
    )
    g = lattice
    v000, v001 = g.take(base), g.take(base + 1)
    v010, v011 = g.take(base + s), g.take(base + s + 1)
    v100, v101 = g.take(base + s * s), g.take(base + s * s + 1)
    v110, v111 = g.take(base + s * s + s), g.take(base + s * s + s + 1)
    a = v000 + (v001 - v000) * uz
    b = v010 + (v011 - v010) * uz
    c = v100 + (v101 - v100) * uz
    d = v110 + (v111 - v110) * uz
    a = a + (b - a) * uy
    c = c + (d - c) * uy
    return a + (c - a) * ux


def _tri(x: np.ndarray) -> np.ndarray:
    """Triangle wave in [0, 1] with period 1 (a sine look-alike without transcendental calls)."""
    return np.abs(2.0 * (x - np.floor(x)) - 1.0)


def _albedo(scene: SyntheticScene, P: np.ndarray, sid: np.ndarray) -> np.ndarray:
    """Surface colour ``[N, 3]`` float32 at world points ``P`` ``[N, 3]`` with surface ids ``[N]``.

    A pure function of the 3D point and surface, hence identical from every viewpoint.
    """
    # One gather of all per-surface parameters: rows are contiguous [N] arrays.
    tab = scene.texture_table()[:, sid]  # [16, N]
    px, py, pz = (P[:, a].astype(np.float32) for a in range(3))
    scale = tab[_T_SCALE]
    qx = px * scale + tab[_T_OFF]
    qy = py * scale + tab[_T_OFF + 1]
    qz = pz * scale + tab[_T_OFF + 2]
    # fBm, 4 octaves; lacunarity 2.37 (non-integer) so lattices of different octaves do not align.
    f = _value_noise(scene.noise, qx, qy, qz)
    amp, total = 1.0, 1.0
    for k in range(1, 4):
        amp *= 0.7  # strong fine octaves: gradients at pixel scale, not only large blotches
        m = np.float32(2.37**k)
        shift = np.float32(13.7 * k)
        octave = _value_noise(scene.noise, qx * m + shift, qy * m + shift, qz * m + shift)
        f += np.float32(amp) * octave
        total += amp
    # Stretch the fBm (which clusters near 0.5) to use the full colour range.
    w = np.clip(f * np.float32(2.6 / total) - np.float32(0.8), 0.0, 1.0)

    # Checker (offset by 0.37 cells so planes at round coordinates do not sit on a cell border)
    # and stripes multiply the colour.
    inv_cs = tab[_T_CHK]
    parity = (
        np.floor(px * inv_cs + 0.37) + np.floor(py * inv_cs + 0.37) + np.floor(pz * inv_cs + 0.37)
    )
    odd = parity - 2.0 * np.floor(parity * 0.5)
    phase = px * tab[_T_STRIPE] + py * tab[_T_STRIPE + 1] + pz * tab[_T_STRIPE + 2]
    mod = 1.0 - tab[_T_CHK + 1] * odd - tab[_T_STRIPE + 3] * _tri(phase)
    col = np.empty((P.shape[0], 3), dtype=np.float32)
    for c in range(3):
        c0 = tab[_T_C0 + c]
        col[:, c] = (c0 + (tab[_T_C1 + c] - c0) * w) * mod
    return col


def _surface_normals(
    scene: SyntheticScene, P: np.ndarray, prim: np.ndarray, room_axis: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ``[N, 3]`` (facing free space) and surface ids ``[N]`` of hit points ``[N, 3]``.

    Points on flat faces are snapped exactly onto their plane (in place), so rounding in
    ``o + t d`` cannot flip checker cells from pixel to pixel.
    """
    N = P.shape[0]
    nrm = np.zeros((N, 3), dtype=np.float64)
    sid = np.zeros(N, dtype=np.int64)

    m = np.flatnonzero(prim == 0)  # room interior; room_axis = 0..2 (min wall) or 3..5 (max wall)
    if m.size:
        k = room_axis[m]
        axis = k % 3
        is_min = k < 3
        nrm[m, axis] = np.where(is_min, 1.0, -1.0)
        P[m, axis] = np.where(is_min, scene.room_min[axis], scene.room_max[axis])
        sid_lut = np.array(
            [_SID_WALL_XMIN, _SID_WALL_YMIN, _SID_FLOOR,
             _SID_WALL_XMAX, _SID_WALL_YMAX, _SID_CEILING]
        )
        sid[m] = sid_lut[k]

    for j, obj in enumerate(scene.objects, start=1):
        m = np.flatnonzero(prim == j)
        if not m.size:
            continue
        c, h = obj.centre, obj.half_size
        Q = P[m] - c
        if obj.kind == "box":
            axis = np.argmax(np.abs(Q) / h, axis=1)  # the face hit: relatively farthest axis
            sgn = np.sign(Q[np.arange(m.size), axis])
            nrm[m, axis] = sgn
            P[m, axis] = c[axis] + sgn * h[axis]
        elif obj.kind == "sphere":
            nrm[m] = Q / np.sqrt(Q[:, 0] * Q[:, 0] + Q[:, 1] * Q[:, 1] + Q[:, 2] * Q[:, 2])[:, None]
        else:
            radial = np.sqrt(Q[:, 0] * Q[:, 0] + Q[:, 1] * Q[:, 1])
            cap = np.abs(np.abs(Q[:, 2]) - h[2]) < np.abs(radial - h[0])
            rs = np.where(radial > 1e-12, radial, 1.0)
            n_obj = np.zeros_like(Q)
            n_obj[:, 0] = np.where(cap, 0.0, Q[:, 0] / rs)
            n_obj[:, 1] = np.where(cap, 0.0, Q[:, 1] / rs)
            n_obj[:, 2] = np.where(cap, np.sign(Q[:, 2]), 0.0)
            nrm[m] = n_obj
            P[m, 2] = np.where(cap, c[2] + np.sign(Q[:, 2]) * h[2], P[m, 2])
        sid[m] = obj.surface_id
    return nrm, sid


def _shade(nrm: np.ndarray) -> np.ndarray:
    """Lambertian irradiance ``[N]`` float32 from the fixed lights (view-independent)."""
    s = np.full(nrm.shape[0], _AMBIENT, dtype=np.float64)
    for ldir, w in _LIGHTS:
        ndl = nrm[:, 0] * ldir[0] + nrm[:, 1] * ldir[1] + nrm[:, 2] * ldir[2]
        s += w * np.maximum(ndl, 0.0)
    return s.astype(np.float32)


def _screen_rect(
    obj: SceneObject, R: np.ndarray, o: np.ndarray, spec: SyntheticSpec
) -> tuple[slice, slice] | None:
    """Pixel rectangle ``(rows, cols)`` containing the object's image; None if it cannot be seen.

    The object lies inside its bounding box, so (with every corner in front of the camera) the
    projections of the 8 corners bound its image. A 2-pixel margin absorbs rounding.
    """
    H, W = spec.height, spec.width
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    rel = obj.centre + signs * obj.half_size - o  # [8, 3] corners relative to the camera
    # Camera coordinates p_cam = R^T (p - o), written out elementwise (no BLAS).
    pc = [rel[:, 0] * R[0, k] + rel[:, 1] * R[1, k] + rel[:, 2] * R[2, k] for k in range(3)]
    z = pc[2]
    if np.all(z <= 0.0):
        return None  # wholly behind the camera: hits need camera z = t > 0
    if np.any(z < 1e-3):
        return slice(0, H), slice(0, W)  # straddles the image plane: test every ray
    u = spec.fx * pc[0] / z + spec.cx
    v = spec.fy * pc[1] / z + spec.cy
    u0, u1 = max(int(np.floor(u.min())) - 2, 0), min(int(np.ceil(u.max())) + 3, W)
    v0, v1 = max(int(np.floor(v.min())) - 2, 0), min(int(np.ceil(v.max())) + 3, H)
    if u0 >= u1 or v0 >= v1:
        return None
    return slice(v0, v1), slice(u0, u1)


def _trace(spec: SyntheticSpec, scene: SyntheticScene, T_world_cam: np.ndarray):
    """Nearest hit of every pixel's ray.

    Returns ``(idx [M], t [M], d, nrm [M, 3], sid [M], col [M, 3])``: flat indices of the pixels
    with a hit, their ray parameter (= camera z), the world ray directions ``d`` (3 arrays
    ``[H*W]``, camera z = 1), unit normals, surface ids and shaded colour (float32, unclipped).
    """
    H, W = spec.height, spec.width
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_world_cam must be [4, 4], got {T.shape}")
    xc, yc = _pixel_rays(W, H, float(spec.fx), float(spec.fy), float(spec.cx), float(spec.cy))
    R = T[:3, :3]
    o = T[:3, 3].copy()
    # World directions of d_cam = (x, y, 1): elementwise so results are bitwise reproducible.
    d = tuple(xc * R[a, 0] + yc * R[a, 1] + R[a, 2] for a in range(3))
    inv = tuple(_safe_inv(da) for da in d)

    # The room box seen from inside: every ray leaves it through the nearest exit plane.
    t_best = None
    room_axis = None
    for a in range(3):
        pos = inv[a] > 0  # heading to the max wall (sign of the safe inverse: d = 0 counts as +)
        t_a = np.where(pos, scene.room_max[a] - o[a], scene.room_min[a] - o[a]) * inv[a]
        k_a = np.where(pos, a + 3, a)
        if t_best is None:
            t_best, room_axis = t_a, k_a
        else:
            nearer = t_a < t_best
            t_best = np.where(nearer, t_a, t_best)
            room_axis = np.where(nearer, k_a, room_axis)
    t_best = np.where(t_best > _EPS_T, t_best, np.inf)  # camera outside the room: no room hit
    prim = np.zeros(t_best.shape, dtype=np.int64)
    t2, prim2 = t_best.reshape(H, W), prim.reshape(H, W)  # views for per-object rectangles
    for j, obj in enumerate(scene.objects, start=1):
        rect = _screen_rect(obj, R, o, spec)
        if rect is None:
            continue
        # Only rays inside the object's image rectangle can hit it: same result, less work.
        d_r = tuple(da.reshape(H, W)[rect].ravel() for da in d)
        inv_r = tuple(ia.reshape(H, W)[rect].ravel() for ia in inv)
        tb = t2[rect]
        t = _intersect_object(obj, o, d_r, inv_r).reshape(tb.shape)
        closer = t < tb
        t2[rect] = np.where(closer, t, tb)
        prim2[rect][closer] = j

    hit = np.isfinite(t_best)
    idx = np.flatnonzero(hit)
    th = t_best[idx]
    P = np.stack([o[a] + th * d[a][idx] for a in range(3)], axis=1)  # [M, 3] world points
    nrm, sid = _surface_normals(scene, P, prim[idx], room_axis[idx])
    col = _albedo(scene, P, sid) * _shade(nrm)[:, None]
    if spec.light_level != 1.0:
        col = col * np.float32(spec.light_level)
    return idx, th, d, nrm, sid, col


def render_synthetic_frame(
    spec: SyntheticSpec, scene: SyntheticScene, T_world_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast one RGB-D frame from ``T_world_cam`` ``[4, 4]`` (camera inside the room).

    Returns:
        ``(rgb, depth_m)``: ``rgb`` uint8 ``[H, W, 3]``; ``depth_m`` float32 ``[H, W]``, the camera
        z of the hit (not the ray length), 0 where there is no hit or the hit is farther than
        ``spec.max_depth_m``. Colour and depth come from the same nearest hit per pixel, whose
        centre is at integer pixel coordinates. An ideal sensor: no noise, blur or dropouts.
    """
    H, W = spec.height, spec.width
    idx, th, _d, _nrm, _sid, col = _trace(spec, scene, T_world_cam)
    rgb = np.zeros((H * W, 3), dtype=np.uint8)
    depth = np.zeros(H * W, dtype=np.float32)
    if idx.size:
        rgb[idx] = np.round(np.clip(col, 0.0, 1.0) * 255.0).astype(np.uint8)
        # d_cam has z = 1, so t is the camera-frame depth directly.
        depth[idx] = np.where(th <= spec.max_depth_m, th, 0.0).astype(np.float32)
    return rgb.reshape(H, W, 3), depth.reshape(H, W)


@dataclass
class _Layers:
    """What the sensor model needs from one render (all ``[H, W]`` unless noted).

    Attributes:
        col: ``[H, W, 3]`` float32 shaded colour in [0, ~1.1] (unclipped), 0 where no hit.
        depth_m: float32 camera z, 0 where no hit or beyond ``max_depth_m``.
        cos_incidence: float32 cosine of the angle between the ray and the surface normal.
        shiny: bool, the pixel shows a glossy surface (:data:`_SHINY_KINDS`).
    """

    col: np.ndarray
    depth_m: np.ndarray
    cos_incidence: np.ndarray
    shiny: np.ndarray


def _render_colour(spec: SyntheticSpec, scene: SyntheticScene, T_world_cam: np.ndarray) -> np.ndarray:
    """Unclipped float32 colour ``[H, W, 3]`` (a motion-blur sub-frame)."""
    H, W = spec.height, spec.width
    idx, _th, _d, _nrm, _sid, col = _trace(spec, scene, T_world_cam)
    out = np.zeros((H * W, 3), dtype=np.float32)
    out[idx] = col
    return out.reshape(H, W, 3)


def _render_layers(spec: SyntheticSpec, scene: SyntheticScene, T_world_cam: np.ndarray) -> _Layers:
    H, W = spec.height, spec.width
    idx, th, d, nrm, sid, col = _trace(spec, scene, T_world_cam)
    out_col = np.zeros((H * W, 3), dtype=np.float32)
    depth = np.zeros(H * W, dtype=np.float32)
    cos_inc = np.zeros(H * W, dtype=np.float32)
    shiny = np.zeros(H * W, dtype=bool)
    if idx.size:
        out_col[idx] = col
        depth[idx] = np.where(th <= spec.max_depth_m, th, 0.0).astype(np.float32)
        dx, dy, dz = d[0][idx], d[1][idx], d[2][idx]
        dn = dx * nrm[:, 0] + dy * nrm[:, 1] + dz * nrm[:, 2]
        cos_inc[idx] = np.clip(-dn / np.sqrt(dx * dx + dy * dy + dz * dz), 0.0, 1.0)
        shiny_ids = [o.surface_id for o in scene.objects if o.kind in _SHINY_KINDS]
        shiny[idx] = np.isin(sid, shiny_ids)
    return _Layers(out_col.reshape(H, W, 3), depth.reshape(H, W), cos_inc.reshape(H, W),
                   shiny.reshape(H, W))


# ----------------------------------------------------------------------------------------------
# Sensor model (only for specs with sensor fields set; see KINECT_V1_SENSOR)


def _acos01(x: np.ndarray) -> np.ndarray:
    """arccos of ``x`` in [0, 1], Abramowitz & Stegun 4.4.45 (|error| < 7e-5 rad): only IEEE-exact
    operations, so noisy datasets stay bitwise reproducible across SIMD code paths."""
    x = np.clip(x, 0.0, 1.0)
    return np.sqrt(1.0 - x) * (1.5707288 + x * (-0.2121144 + x * (0.0742610 + x * -0.0187293)))


def depth_noise_sigma_m(
    spec: SyntheticSpec, z_m: np.ndarray, cos_incidence: np.ndarray | float = 1.0
) -> np.ndarray:
    """Axial depth noise std (metres) at depth ``z_m`` and incidence cosine (same shapes):
    ``a + b (z - 0.4)^2 + c / sqrt(z) * theta^2 / (pi/2 - theta)^2`` (Nguyen et al. 2012), with
    ``theta`` capped at 80 deg. Includes the disparity quantisation (the std that is written)."""
    z = np.asarray(z_m, dtype=np.float64)
    dz = z - _NGUYEN_Z0_M
    sigma = spec.depth_noise_a_m + spec.depth_noise_b_per_m * dz * dz
    if spec.depth_noise_angle_m > 0:
        theta = np.minimum(_acos01(np.asarray(cos_incidence, dtype=np.float64)), _MAX_NOISE_ANGLE_RAD)
        q = theta / (0.5 * math.pi - theta)
        sigma = sigma + spec.depth_noise_angle_m / np.sqrt(np.maximum(z, 1e-3)) * q * q
    return sigma


def _depth_edges(z: np.ndarray) -> np.ndarray:
    """Pixels ``[H, W]`` next to a depth discontinuity (relative jump > 4 %, or valid next to
    missing)."""
    edge = np.zeros(z.shape, dtype=bool)
    for a, b, sl_a, sl_b in (
        (z[:, :-1], z[:, 1:], (slice(None), slice(None, -1)), (slice(None), slice(1, None))),
        (z[:-1, :], z[1:, :], (slice(None, -1), slice(None)), (slice(1, None), slice(None))),
    ):
        jump = np.abs(a - b) > _EDGE_JUMP_REL * np.minimum(a, b)
        jump |= (a > 0) != (b > 0)
        edge[sl_a] |= jump
        edge[sl_b] |= jump
    return edge


def _dilate(mask: np.ndarray) -> np.ndarray:
    """3x3 binary dilation of ``mask`` ``[H, W]``."""
    out = mask.copy()
    out[1:, :] |= mask[:-1, :]
    out[:-1, :] |= mask[1:, :]
    m = out.copy()
    out[:, 1:] |= m[:, :-1]
    out[:, :-1] |= m[:, 1:]
    return out


def _projector_shadow(z: np.ndarray, fx: float, baseline_m: float) -> np.ndarray:
    """Pixels ``[H, W]`` the projector (``baseline_m`` to the camera's +x) cannot light.

    A point at column ``u`` and depth ``z`` is lit from projector column ``u - fx b / z``; along a
    row a nearer surface to the right that reaches a smaller projector column hides it (the
    ordering test of stereo matching). Shadows fall left of foreground objects, ``fx b (1/z_near -
    1/z_far)`` pixels wide.
    """
    W = z.shape[1]
    u = np.arange(W, dtype=np.float64)[None, :]
    up = np.where(z > 0, u - fx * baseline_m / np.where(z > 0, z, 1.0), np.inf)
    suffix_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]  # min over q >= p
    right_min = np.full_like(up, np.inf)
    right_min[:, :-1] = suffix_min[:, 1:]  # min over q > p
    return (z > 0) & (up > right_min + _SHADOW_TOL_PX)


def _box_sum(a: np.ndarray, k: int) -> np.ndarray:
    """Sums over every k x k window of ``a`` ``[H + k - 1, W + k - 1]``: ``[H, W]`` (cumulative
    sums: exact order, deterministic)."""
    c = np.zeros((a.shape[0] + 1, a.shape[1]))
    np.cumsum(a, axis=0, out=c[1:])
    rows = c[k:] - c[:-k]
    c = np.zeros((rows.shape[0], rows.shape[1] + 1))
    np.cumsum(rows, axis=1, out=c[:, 1:])
    return c[:, k:] - c[:, :-k]


def _unit_noise(spec: SyntheticSpec, shape: tuple[int, int], frame_index: int) -> np.ndarray:
    """Zero-mean unit-variance noise ``[H, W]``: per pixel, or (``depth_noise_corr_px`` > 0) mostly a
    box-filtered field correlated over ``depth_noise_corr_px * W / 640`` pixels."""
    H, W = shape
    white = _effect_rng(spec, frame_index, 4).standard_normal((H, W))
    k = int(round(spec.depth_noise_corr_px * W / 640.0))
    if k <= 1:
        return white
    field = _effect_rng(spec, frame_index, 6).standard_normal((H + k - 1, W + k - 1))
    smooth = _box_sum(field, k) / k  # a sum of k^2 unit normals has std k
    f = _CORRELATED_NOISE_FRACTION
    return math.sqrt(f) * smooth + math.sqrt(1.0 - f) * white


def _effect_rng(spec: SyntheticSpec, frame_index: int, effect: int) -> np.random.Generator:
    # One stream per (frame, effect): switching one effect off leaves the others' noise unchanged.
    return np.random.default_rng([spec.seed, _SENSOR_STREAM, frame_index, effect])


def apply_depth_sensor_model(
    spec: SyntheticSpec,
    depth_m: np.ndarray,
    cos_incidence: np.ndarray,
    luma: np.ndarray,
    shiny: np.ndarray,
    frame_index: int = 0,
) -> np.ndarray:
    """The depth a structured-light sensor reports for an exact depth map.

    Args:
        depth_m: ``[H, W]`` exact camera z, 0 = no surface.
        cos_incidence: ``[H, W]`` cosine of the incidence angle at each pixel.
        luma: ``[H, W]`` surface brightness in [0, 1] (albedo x shading, a proxy of IR reflectance).
        shiny: ``[H, W]`` bool, glossy surface.
        frame_index: keys the random streams (with ``spec.seed``).

    Returns:
        ``[H, W]`` float64 depth in metres, 0 = no reading (not yet rounded to ``depth_scale``).
    """
    z0 = np.asarray(depth_m, dtype=np.float64)
    H, W = z0.shape
    z = z0.copy()
    cos_i = np.array(cos_incidence, dtype=np.float64)  # copies: the jitter below writes into them
    lum = np.array(luma, dtype=np.float64)
    shn = np.array(shiny, dtype=bool)
    edge = _depth_edges(z0)
    if spec.depth_lateral_noise_px > 0:
        # Jagged silhouettes: pixels near a discontinuity read a neighbour's depth.
        band = np.flatnonzero(_dilate(edge))
        rng = _effect_rng(spec, frame_index, 1)
        off = np.rint(rng.standard_normal((2, band.size)) * spec.depth_lateral_noise_px).astype(np.int64)
        v, u = np.divmod(band, W)
        src = np.clip(v + off[0], 0, H - 1) * W + np.clip(u + off[1], 0, W - 1)
        for arr in (z, cos_i, lum, shn):
            flat = arr.reshape(-1)
            flat[band] = flat[src] if arr is not z else z0.reshape(-1)[src]
    valid = z > 0
    if spec.edge_dropout_prob > 0:
        valid &= ~(edge & (_effect_rng(spec, frame_index, 2).random((H, W)) < spec.edge_dropout_prob))
    if spec.projector_baseline_m > 0:
        valid &= ~_projector_shadow(z0, spec.fx, spec.projector_baseline_m)
    if spec.dark_dropout_luma > 0:
        # Certain loss at black, none at or above the threshold, a linear ramp between.
        p_drop = np.clip(1.0 - lum / spec.dark_dropout_luma, 0.0, 1.0)
        valid &= ~(_effect_rng(spec, frame_index, 3).random((H, W)) < p_drop)
    if spec.shiny_dropout_deg > 0:
        valid &= ~(shn & (cos_i > math.cos(math.radians(spec.shiny_dropout_deg))))
    if spec.grazing_dropout_deg > 0:
        valid &= cos_i >= math.cos(math.radians(spec.grazing_dropout_deg))
    z = np.where(valid, z, 0.0)

    q = spec.inverse_depth_step_per_m
    if spec.depth_noise_a_m > 0 or spec.depth_noise_b_per_m > 0 or spec.depth_noise_angle_m > 0:
        sigma = depth_noise_sigma_m(spec, np.where(valid, z, 1.0), np.where(valid, cos_i, 1.0))
        # The model's std is the sensor's total: the Gaussian part leaves room for the
        # quantisation below (uniform steps of q z^2 have variance (q z^2)^2 / 12).
        step = q * z * z
        sd = np.sqrt(np.maximum(sigma * sigma - step * step / 12.0, 0.0))
        z = np.where(valid, z + sd * _unit_noise(spec, (H, W), frame_index), 0.0)
        valid &= z > 0
    if q > 0:
        inv_q = np.rint(1.0 / np.where(valid, z, 1.0) / q)
        z = np.where(valid & (inv_q > 0), 1.0 / (np.maximum(inv_q, 1.0) * q), 0.0)
    return np.where((z > 0) & (z <= spec.max_depth_m), z, 0.0)


def _shift_image(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``img`` ``[H, W, C]`` moved by ``(dx, dy)`` pixels (bilinear, edges repeated):
    ``out[v, u] = img[v - dy, u - dx]``."""
    H, W = img.shape[:2]
    out = img
    for axis, shift, n in ((1, dx, W), (0, dy, H)):
        if shift == 0.0:
            continue
        i = math.floor(shift)
        f = np.float32(shift - i)
        idx = np.arange(n)
        a = np.take(out, np.clip(idx - i, 0, n - 1), axis=axis)  # weight 1 - f
        b = np.take(out, np.clip(idx - i - 1, 0, n - 1), axis=axis)  # weight f
        out = a * (np.float32(1.0) - f) + b * f
    return out


def _colour_gain(spec: SyntheticSpec, t: float, mean_luma: float) -> np.ndarray:
    """Per-channel gain ``[3]`` float32 at time ``t``: auto exposure, exposure and white-balance
    drift (slow sines with phases from the seed)."""
    ph = np.random.default_rng([spec.seed, _SENSOR_STREAM, 0xC0]).uniform(0.0, 2.0 * math.pi, size=4)
    gain = np.ones(3)
    if spec.exposure_drift > 0:
        # Auto exposure halves the log distance to the target brightness (no lag), then drifts.
        ae = math.sqrt(_AE_TARGET_LUMA / max(mean_luma, 1e-3))
        ae = min(max(ae, _AE_GAIN_RANGE[0]), _AE_GAIN_RANGE[1])
        f1, f2 = _EXPOSURE_DRIFT_HZ
        drift = 0.6 * math.sin(2 * math.pi * f1 * t + ph[0]) + 0.4 * math.sin(2 * math.pi * f2 * t + ph[1])
        gain *= ae * (1.0 + spec.exposure_drift * drift)
    if spec.white_balance_drift > 0:
        fr, fb = _WHITE_BALANCE_HZ
        gain[0] *= 1.0 + spec.white_balance_drift * math.sin(2 * math.pi * fr * t + ph[2])
        gain[2] *= 1.0 + spec.white_balance_drift * math.sin(2 * math.pi * fb * t + ph[3])
    return gain.astype(np.float32)


def _luma(col: np.ndarray) -> np.ndarray:
    """Rec. 601 luma ``[H, W]`` of a colour image ``[H, W, 3]``."""
    return (np.float32(0.299) * col[..., 0] + np.float32(0.587) * col[..., 1]
            + np.float32(0.114) * col[..., 2])


def _sensor_frame(
    spec: SyntheticSpec, scene: SyntheticScene, t: float, frame_index: int
) -> tuple[np.ndarray, np.ndarray]:
    """One frame through the sensor model: ``(rgb uint8 [H, W, 3], depth_m float64 [H, W])``.

    Depth is sensed at the pose of time ``t``; colour integrates the exposure around
    ``t + colour_delay_s``.
    """
    T = camera_path(spec, np.array([t]))[0]
    lay = _render_layers(spec, scene, T)
    luma = _luma(lay.col)
    depth = apply_depth_sensor_model(spec, lay.depth_m, lay.cos_incidence, luma, lay.shiny, frame_index)

    t_col = t + spec.colour_delay_s
    col = lay.col if t_col == t else _render_colour(spec, scene, camera_path(spec, np.array([t_col]))[0])
    n = spec.motion_blur_samples
    if n >= 2 and spec.exposure_time_s > 0:
        offsets = [spec.exposure_time_s * (k / (n - 1) - 0.5) for k in range(n)]
        sub = camera_path(spec, t_col + np.array(offsets))
        acc = np.zeros_like(col)
        for off, Tk in zip(offsets, sub):  # fixed order: deterministic float sums
            acc += col if off == 0.0 else _render_colour(spec, scene, Tk)
        col = acc * np.float32(1.0 / n)
    if spec.exposure_drift > 0 or spec.white_balance_drift > 0:
        col = col * _colour_gain(spec, t, float(_luma(col).mean()))
    if spec.rgb_shift_x_px or spec.rgb_shift_y_px:
        col = _shift_image(col, spec.rgb_shift_x_px, spec.rgb_shift_y_px)
    if spec.rgb_noise_std > 0:
        noise = _effect_rng(spec, frame_index, 5).standard_normal(col.shape, dtype=np.float32)
        col = col + noise * np.float32(spec.rgb_noise_std / 255.0)
    rgb = np.round(np.clip(col, 0.0, 1.0) * 255.0).astype(np.uint8)
    return rgb, depth


# ----------------------------------------------------------------------------------------------
# Dataset writing


def _spec_dict(spec: SyntheticSpec) -> dict:
    """The spec's fields, less the optional ones still at their defaults (a default spec gives the
    same dictionary, hash and ``synthetic_spec.json`` as generator version 1 always did)."""
    d = asdict(spec)
    return {k: v for k, v in d.items() if k in _V1_FIELDS or v != _FIELD_DEFAULTS[k]}


def spec_hash(spec: SyntheticSpec) -> str:
    """Hex sha256 of the spec and generator version: the content of the ``.complete`` marker."""
    payload = json.dumps({"generator_version": GENERATOR_VERSION, **_spec_dict(spec)}, sort_keys=True)
    return hashlib.sha256(payload.encode("utf-8")).hexdigest()


def _is_complete(path: Path, digest: str) -> bool:
    marker = path / ".complete"
    try:
        return marker.is_file() and marker.read_text(encoding="utf-8").strip() == digest
    except OSError:
        return False


def _ts(t: float) -> str:
    return f"{t:.6f}"


def _write_png(path: Path, img: np.ndarray) -> None:
    # Fixed Pillow settings and no metadata chunks: byte-identical output for identical pixels.
    # Level 3: ~2.5x faster than the default 6 for ~10% larger files.
    iio.imwrite(path, img, extension=".png", plugin="pillow", compress_level=3, optimize=False)


def _write_frame(root: Path, ts_rgb: str, ts_depth: str, rgb: np.ndarray, raw: np.ndarray) -> None:
    _write_png(root / "rgb" / f"{ts_rgb}.png", rgb)
    _write_png(root / "depth" / f"{ts_depth}.png", raw)


def _write_list(path: Path, header: list[str], rows: list[str]) -> None:
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        for h in header:
            f.write(f"# {h}\n")
        for r in rows:
            f.write(r + "\n")


def _write_dataset(root: Path, spec: SyntheticSpec) -> None:
    """Render and write every file of the dataset into ``root`` (an empty folder)."""
    scene = scene_of(spec)
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    label = f"atlas-gs synthetic seed={spec.seed}"

    t_rel = frame_times_s(spec)  # [F] seconds from start (i / fps unless frames are dropped)
    sensor = spec.sensor_model
    poses = None if sensor else camera_path(spec, t_rel)  # [F, 4, 4]
    if sensor:
        logger.info("synthetic: sensor model on (%s)", ", ".join(
            f"{k}={getattr(spec, k):g}" for k in _SENSOR_FIELDS if getattr(spec, k) != _FIELD_DEFAULTS[k]))
    rgb_rows: list[str] = []
    depth_rows: list[str] = []
    t0 = time.perf_counter()
    # PNG encoding (zlib releases the GIL) runs in one background thread while the next frame
    # renders; each file depends only on its own pixels, so the output stays deterministic.
    pending: deque[Future] = deque()
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="synthetic-png") as pool:
        for i in range(spec.n_frames):
            ts_depth = _ts(TIMESTAMP_START_S + t_rel[i])
            ts_rgb = _ts(TIMESTAMP_START_S + t_rel[i] + spec.colour_delay_s)
            if sensor:
                # Depth at the depth timestamp pose, colour exposed around it.
                rgb, depth_m = _sensor_frame(spec, scene, float(t_rel[i]), i)
            else:
                # Both images at the depth timestamp pose: colour and depth stay exactly consistent.
                rgb, depth_m = render_synthetic_frame(spec, scene, poses[i])
            raw = np.round(depth_m.astype(np.float64) * spec.depth_scale)
            raw = np.where((depth_m > 0) & (depth_m <= spec.max_depth_m), raw, 0.0)
            pending.append(
                pool.submit(_write_frame, root, ts_rgb, ts_depth, rgb, raw.astype(np.uint16))
            )
            while len(pending) > 2:  # bound memory if encoding is slower than rendering
                pending.popleft().result()
            rgb_rows.append(f"{ts_rgb} rgb/{ts_rgb}.png")
            depth_rows.append(f"{ts_depth} depth/{ts_depth}.png")
            done = i + 1
            if done % 10 == 0 or done == spec.n_frames:
                dt = time.perf_counter() - t0
                logger.info(
                    "synthetic: %d/%d frames rendered (%.1f frames/s)",
                    done, spec.n_frames, done / max(dt, 1e-9),
                )
        while pending:
            pending.popleft().result()  # re-raises any write error

    _write_list(
        root / "rgb.txt", ["color images", f"file: '{label}'", "timestamp filename"], rgb_rows
    )
    _write_list(
        root / "depth.txt", ["depth maps", f"file: '{label}'", "timestamp filename"], depth_rows
    )

    # Ground truth on a regular grid k / rate covering all stamps plus a margin, from the same path.
    t_last = t_rel[-1] + spec.colour_delay_s
    k0 = -int(math.ceil(GT_MARGIN_S * spec.gt_rate_hz))
    k1 = int(math.ceil((t_last + GT_MARGIN_S) * spec.gt_rate_hz))
    t_gt = np.arange(k0, k1 + 1, dtype=np.float64) / spec.gt_rate_hz
    gt = camera_path(spec, t_gt)
    quat = rotmat_to_quat_xyzw(gt[:, :3, :3])
    gt_rows = []
    for k in range(t_gt.shape[0]):
        tx, ty, tz = gt[k, :3, 3]
        qx, qy, qz, qw = quat[k]
        gt_rows.append(
            f"{_ts(TIMESTAMP_START_S + t_gt[k])} {tx:.6f} {ty:.6f} {tz:.6f} "
            f"{qx:.7f} {qy:.7f} {qz:.7f} {qw:.7f}"
        )
    _write_list(
        root / "groundtruth.txt",
        ["ground truth trajectory", f"file: '{label}'", "timestamp tx ty tz qx qy qz qw"],
        gt_rows,
    )
    info = {
        "generator_version": GENERATOR_VERSION,
        "spec": _spec_dict(spec),
        "camera": spec.camera().to_dict(),
    }
    (root / "synthetic_spec.json").write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")
    # The marker goes last: its presence means every other file is complete.
    (root / ".complete").write_text(spec_hash(spec) + "\n", encoding="utf-8")


SYNTHETIC_KIND = "synthetic_dataset"  # output-policy kind (io_utils marker)


def generate_synthetic_dataset(out_dir: str | Path, spec: SyntheticSpec = SyntheticSpec()) -> Path:
    """Write the dataset of ``spec`` to ``out_dir`` (TUM layout) and return ``out_dir``.

    An existing ``out_dir`` whose ``.complete`` marker holds this spec's hash is returned as is.
    Otherwise the dataset is written into a temporary sibling folder and swapped into place at the
    end (:func:`atlas_pipeline.io_utils.commit_dir`), so an interrupted run never leaves a
    half-written dataset at ``out_dir``. Only an empty folder or an earlier synthetic dataset is
    replaced; any other folder at ``out_dir`` (a user's files) is refused.
    """
    from atlas_pipeline.io_utils import check_output_dir, commit_dir, discard_dir, stage_dir

    out = Path(out_dir)
    digest = spec_hash(spec)
    if _is_complete(out, digest):
        logger.info("synthetic: %s is up to date, not regenerating", out)
        return out
    check_output_dir(out, SYNTHETIC_KIND, what="synthetic dataset folder")
    tmp = stage_dir(out)
    t0 = time.perf_counter()
    try:
        logger.info("synthetic: generating %d frames %dx%d into %s", spec.n_frames, spec.width,
                    spec.height, out)
        _write_dataset(tmp, spec)
        if _is_complete(out, digest):  # another process finished the same dataset first: keep theirs
            return out
        commit_dir(tmp, out, SYNTHETIC_KIND)
    finally:
        if tmp.exists():
            discard_dir(tmp)
    logger.info("synthetic: wrote %s in %.1f s", out, time.perf_counter() - t0)
    return out
