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

The code, by concern: ``synthetic_spec`` (the spec and presets), ``synthetic_scene`` (room, objects,
texture table), ``synthetic_path`` (camera path and frame times), ``synthetic_raytrace`` (the ray
tracer), ``synthetic_textures`` (surface colour and shading), ``synthetic_kinect`` (the depth
sensor model), ``synthetic_colour`` (the colour camera model), ``synthetic_writer`` (the TUM-layout
writer); ``synthetic_places`` (the three-room suite). This module gathers their public names.
"""


from __future__ import annotations

from atlas_pipeline.sensors.synthetic_kinect import apply_depth_sensor_model, depth_noise_sigma_m
from atlas_pipeline.sensors.synthetic_path import camera_path, frame_times_s
from atlas_pipeline.sensors.synthetic_raytrace import render_synthetic_frame
from atlas_pipeline.sensors.synthetic_scene import (
    ROOM_MAX, ROOM_MIN, SceneObject, SyntheticScene, build_scene, scene_of,
)
from atlas_pipeline.sensors.synthetic_spec import (
    GENERATOR_VERSION, HANDHELD_MOTION, KINECT_V1_SENSOR, LOOP_MOTION, PLACES, SUITE_PRESETS, SYNTHETIC_PRESETS,
    TIMESTAMP_START_S, SyntheticSpec, spec_hash,
)
from atlas_pipeline.sensors.synthetic_writer import SYNTHETIC_KIND, generate_synthetic_dataset

__all__ = [
    "SyntheticSpec",
    "SyntheticScene",
    "SceneObject",
    "build_scene",
    "scene_of",
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
    "SUITE_PRESETS",
    "PLACES",
    "GENERATOR_VERSION",
    "SYNTHETIC_KIND",
    "TIMESTAMP_START_S",
    "ROOM_MIN",
    "ROOM_MAX",
]
