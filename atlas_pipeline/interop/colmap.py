"""A COLMAP sparse model (``cameras``, ``images``, ``points3D``; text and binary) of known poses.

COLMAP stores each image's world-to-camera transform (``cam_from_world``) as a unit quaternion
``QW QX QY QZ`` and a translation ``TX TY TZ``, in the OpenCV camera convention (x right, y down,
z forward) that our ``T_world_cam`` (camera-to-world, 4x4) uses too: ``R = R_wc^T``,
``t = -R_wc^T t_wc``. Cameras are ``PINHOLE`` (``fx fy cx cy``): frames are undistorted before
export. ``points3D`` are seeded from the Gaussians (centres and colours) with an empty track and
error 0: trainers (Inria's ``train.py``, gsplat, nerfstudio's colmap parser) read them as the
initial point cloud; there are no 2D feature observations.

Binary layout (little endian; COLMAP's ``Reconstruction::Write*Binary``): ``cameras.bin``: uint64
count, then per camera int32 id, int32 model id, uint64 width, uint64 height, float64 params;
``images.bin``: uint64 count, then per image int32 id, float64 qw qx qy qz, float64 tx ty tz, int32
camera id, the name NUL-terminated, uint64 number of 2D points (0); ``points3D.bin``: uint64 count,
then per point uint64 id, float64 x y z, uint8 r g b, float64 error, uint64 track length (0).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from atlas_pipeline.geometry import rotmat_to_quat_xyzw
from atlas_pipeline.io_utils import atomic_path
from atlas_pipeline.sensors.camera import CameraIntrinsics

__all__ = ["COLMAP_PINHOLE", "colmap_cam_from_world", "write_colmap_model", "COLMAP_FILES"]

COLMAP_PINHOLE = ("PINHOLE", 1)  # model name and id (COLMAP's CameraModelId)
CAMERA_ID = 1  # one camera: every frame has the same intrinsics
POINT_ERROR = 0.0  # reprojection error of a seeded point: none measured
COLMAP_FILES = ("cameras.txt", "images.txt", "points3D.txt", "cameras.bin", "images.bin", "points3D.bin")
# One points3D.bin record without a track: id, xyz, rgb, error, track length (51 bytes, packed).
_POINT_DTYPE = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("track", "<u8")])
_ROWS_PER_WRITE = 1 << 16


def colmap_cam_from_world(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T_world_cam`` ``[N, 4, 4]`` (camera-to-world) as COLMAP's world-to-camera
    ``(quat_wxyz [N, 4], t_cam_world_m [N, 3])``; quaternions with ``qw >= 0``."""
    T = np.asarray(T_world_cam, np.float64).reshape(-1, 4, 4)
    R_cw = np.transpose(T[:, :3, :3], (0, 2, 1))
    t_cw = -np.einsum("nij,nj->ni", R_cw, T[:, :3, 3])
    q_xyzw = rotmat_to_quat_xyzw(R_cw)
    q_wxyz = np.concatenate([q_xyzw[:, 3:], q_xyzw[:, :3]], axis=1)
    q_wxyz *= np.where(q_wxyz[:, :1] < 0, -1.0, 1.0)  # q and -q are one rotation: COLMAP's own sign
    return q_wxyz, t_cw


def _text(directory: Path, camera: CameraIntrinsics, names: list[str], q: np.ndarray, t: np.ndarray,
          xyz: np.ndarray, rgb: np.ndarray) -> None:
    # repr() of a float is the shortest text that reads back to the same double: exact round trip
    with atomic_path(directory / "cameras.txt") as tmp:
        params = " ".join(repr(float(v)) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
        tmp.write_text("# Camera list with one line of data per camera:\n"
                       "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
                       f"{CAMERA_ID} {COLMAP_PINHOLE[0]} {camera.width} {camera.height} {params}\n")
    with atomic_path(directory / "images.txt") as tmp:
        lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                 f"# Number of images: {len(names)}, mean observations per image: 0"]
        for i, name in enumerate(names):
            pose = " ".join(repr(float(v)) for v in (*q[i], *t[i]))
            lines += [f"{i + 1} {pose} {CAMERA_ID} {name}", ""]  # no 2D points: an empty second line
        tmp.write_text("\n".join(lines) + "\n")
    with atomic_path(directory / "points3D.txt") as tmp, open(tmp, "w") as f:
        f.write("# 3D point list with one line of data per point:\n"
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                f"# Number of points: {len(xyz)}, mean track length: 0\n")
        for i in range(0, len(xyz), _ROWS_PER_WRITE):
            block = slice(i, i + _ROWS_PER_WRITE)
            ids = np.arange(i + 1, i + 1 + len(xyz[block]))
            f.writelines(f"{k} {x!r} {y!r} {z!r} {r} {g} {b} {POINT_ERROR!r}\n" for k, (x, y, z), (r, g, b) in
                         zip(ids.tolist(), xyz[block].tolist(), rgb[block].tolist()))


def _binary(directory: Path, camera: CameraIntrinsics, names: list[str], q: np.ndarray, t: np.ndarray,
            xyz: np.ndarray, rgb: np.ndarray) -> None:
    with atomic_path(directory / "cameras.bin") as tmp:
        tmp.write_bytes(struct.pack("<QiiQQ4d", 1, CAMERA_ID, COLMAP_PINHOLE[1], camera.width, camera.height,
                                    camera.fx, camera.fy, camera.cx, camera.cy))
    with atomic_path(directory / "images.bin") as tmp:
        out = [struct.pack("<Q", len(names))]
        for i, name in enumerate(names):
            out.append(struct.pack("<i7di", i + 1, *q[i], *t[i], CAMERA_ID) + name.encode("utf-8") + b"\0"
                       + struct.pack("<Q", 0))
        tmp.write_bytes(b"".join(out))
    with atomic_path(directory / "points3D.bin") as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<Q", len(xyz)))
        for i in range(0, len(xyz), _ROWS_PER_WRITE):
            block = slice(i, i + _ROWS_PER_WRITE)
            rows = np.zeros(len(xyz[block]), _POINT_DTYPE)
            rows["id"] = np.arange(i + 1, i + 1 + len(rows))
            rows["xyz"], rows["rgb"], rows["error"] = xyz[block], rgb[block], POINT_ERROR
            f.write(rows.tobytes())


def write_colmap_model(directory: str | Path, camera: CameraIntrinsics, image_names: list[str],
                       T_world_cam: np.ndarray, points_xyz: np.ndarray, points_rgb: np.ndarray) -> list[Path]:
    """Write the text and the binary model into ``directory`` (created): one ``PINHOLE`` camera
    (``camera`` must be undistorted), image ``i + 1`` named ``image_names[i]`` at ``T_world_cam[i]``
    (``[N, 4, 4]``, camera-to-world), point ``j + 1`` at ``points_xyz[j]`` (``[P, 3]`` metres) with
    colour ``points_rgb[j]`` (``[P, 3]`` uint8). Returns the six files."""
    if camera.distortion:
        raise ValueError("COLMAP export writes PINHOLE cameras: undistort the frames first")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    q, t = colmap_cam_from_world(T_world_cam)
    xyz = np.asarray(points_xyz, np.float64).reshape(-1, 3)
    rgb = np.asarray(points_rgb, np.uint8).reshape(-1, 3)
    _text(directory, camera, list(image_names), q, t, xyz, rgb)
    _binary(directory, camera, list(image_names), q, t, xyz, rgb)
    return [directory / n for n in COLMAP_FILES]
