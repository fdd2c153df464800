"""nerfstudio's ``transforms.json`` of known poses (its data conventions: docs.nerf.studio, "Data
conventions").

Intrinsics shared by every frame sit at the top (``camera_model``, ``fl_x``, ``fl_y``, ``cx``,
``cy``, ``w``, ``h`` and the distortion ``k1 k2 p1 p2``, all 0: frames are undistorted first). Each
frame has ``file_path``, ``depth_file_path`` and ``transform_matrix``: camera-to-world in the
OpenGL/Blender camera convention nerfstudio uses (x right, y up, the camera looking down -z), i.e.
our OpenCV ``T_world_cam`` with its y and z columns negated. Depth images are 16-bit PNGs in
millimetres, the unit nerfstudio's ``depth_unit_scale_factor`` (default 0.001, a dataparser option)
expects; the file also says so in ``depth_unit_scale_factor``. ``ply_file_path`` names the initial
point cloud (the Gaussians' centres and colours) that splatfacto starts from.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from atlas_pipeline.sensors.camera import CameraIntrinsics

__all__ = ["OPENCV_TO_OPENGL", "NERFSTUDIO_CAMERA_MODEL", "nerfstudio_transforms", "opengl_c2w"]

# Negating the camera's y and z axes turns an OpenCV camera frame into an OpenGL one.
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
NERFSTUDIO_CAMERA_MODEL = "OPENCV"  # nerfstudio's perspective model; distortion coefficients 0 = a pinhole


def opengl_c2w(T_world_cam: np.ndarray) -> np.ndarray:
    """``[N, 4, 4]`` OpenGL-convention camera-to-world of OpenCV ``T_world_cam`` ``[N, 4, 4]``."""
    return np.asarray(T_world_cam, np.float64) @ OPENCV_TO_OPENGL


def nerfstudio_transforms(camera: CameraIntrinsics, file_paths: list[str], depth_file_paths: list[str],
                          T_world_cam: np.ndarray, ply_file_path: str | None, depth_unit_scale_factor: float,
                          extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The content of ``transforms.json``; paths relative to the file's folder."""
    if camera.distortion:
        raise ValueError("nerfstudio export writes undistorted frames: undistort them first")
    c2w = opengl_c2w(T_world_cam)
    frames = [{"file_path": f, "depth_file_path": d, "transform_matrix": m.tolist()}
              for f, d, m in zip(file_paths, depth_file_paths, c2w)]
    out: dict[str, Any] = {
        "camera_model": NERFSTUDIO_CAMERA_MODEL,
        "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "w": camera.width, "h": camera.height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "depth_unit_scale_factor": depth_unit_scale_factor,
        "frames": frames,
    }
    if ply_file_path:
        out["ply_file_path"] = ply_file_path
    out.update(extra or {})
    return out
