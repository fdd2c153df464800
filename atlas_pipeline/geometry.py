"""Rigid-body geometry: SE(3) poses, quaternions, interpolation and trajectory alignment.

Conventions used throughout the project:

* ``T_world_cam`` is a 4x4 homogeneous camera-to-world transform: ``p_world = T_world_cam @ p_cam``.
* Camera frame follows OpenCV/TUM: x right, y down, z forward (depth along +z).
* Quaternions are stored as ``quat_xyzw`` (TUM order, Hamilton convention, unit norm).
* Batched poses are ``poses_se3`` with shape ``[N, 4, 4]``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "quat_xyzw_to_rotmat",
    "rotmat_to_quat_xyzw",
    "pose_from_tq",
    "tq_from_pose",
    "invert_se3",
    "rotation_angle_rad",
    "slerp_xyzw",
    "interpolate_pose",
    "so3_log",
    "so3_exp",
    "umeyama_alignment",
    "look_at",
]


def quat_xyzw_to_rotmat(quat_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``[..., 4]`` (x, y, z, w) to rotation matrices ``[..., 3, 3]``.

    The input is normalised first, so slightly denormalised quaternions from text files are fine.
    """
    q = np.asarray(quat_xyzw, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise ValueError("quaternion with zero norm")
    q = q / norm
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3), dtype=np.float64)
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotmat_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` to unit quaternions ``[..., 4]`` (x, y, z, w), w >= 0.

    Uses Shepperd's method (pick the largest diagonal term) for numerical stability.
    """
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    Rf = R.reshape(-1, 3, 3)
    q = np.empty((Rf.shape[0], 4), dtype=np.float64)
    tr = np.trace(Rf, axis1=1, axis2=2)
    d = np.stack([Rf[:, 0, 0], Rf[:, 1, 1], Rf[:, 2, 2]], axis=1)
    case = np.where(tr > d.max(axis=1), 3, d.argmax(axis=1))
    for c in range(4):
        m = case == c
        if not np.any(m):
            continue
        r = Rf[m]
        if c == 3:
            s = np.sqrt(1.0 + tr[m]) * 2.0
            w = 0.25 * s
            x = (r[:, 2, 1] - r[:, 1, 2]) / s
            y = (r[:, 0, 2] - r[:, 2, 0]) / s
            z = (r[:, 1, 0] - r[:, 0, 1]) / s
        elif c == 0:
            s = np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]) * 2.0
            w = (r[:, 2, 1] - r[:, 1, 2]) / s
            x = 0.25 * s
            y = (r[:, 0, 1] + r[:, 1, 0]) / s
            z = (r[:, 0, 2] + r[:, 2, 0]) / s
        elif c == 1:
            s = np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2]) * 2.0
            w = (r[:, 0, 2] - r[:, 2, 0]) / s
            x = (r[:, 0, 1] + r[:, 1, 0]) / s
            y = 0.25 * s
            z = (r[:, 1, 2] + r[:, 2, 1]) / s
        else:
            s = np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1]) * 2.0
            w = (r[:, 1, 0] - r[:, 0, 1]) / s
            x = (r[:, 0, 2] + r[:, 2, 0]) / s
            y = (r[:, 1, 2] + r[:, 2, 1]) / s
            z = 0.25 * s
        q[m] = np.stack([x, y, z, w], axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0  # canonical sign: one quaternion per rotation
    return q.reshape(batch + (4,))


def pose_from_tq(t_xyz: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Translation ``[..., 3]`` and quaternion ``[..., 4]`` to ``poses_se3`` ``[..., 4, 4]``."""
    t = np.asarray(t_xyz, dtype=np.float64)
    R = quat_xyzw_to_rotmat(quat_xyzw)
    T = np.zeros(t.shape[:-1] + (4, 4), dtype=np.float64)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def tq_from_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``poses_se3`` ``[..., 4, 4]`` to (translation ``[..., 3]``, quat_xyzw ``[..., 4]``)."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), rotmat_to_quat_xyzw(T[..., :3, :3])


def invert_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``[..., 4, 4]`` without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` to axis-angle vectors ``[..., 3]`` (radians)."""
    R = np.asarray(R, dtype=np.float64)
    q = rotmat_to_quat_xyzw(R)
    v = q[..., :3]
    w = q[..., 3]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    # For tiny angles angle/s -> 2 (first-order), avoid 0/0.
    scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0)
    return v * scale[..., None]


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Axis-angle vectors ``[..., 3]`` (radians) to rotation matrices ``[..., 3, 3]`` (Rodrigues)."""
    w = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)
    half = 0.5 * theta
    # sin(theta/2)/theta with its limit 1/2 at zero.
    k = np.where(theta > 1e-12, np.sin(half) / np.maximum(theta, 1e-300), 0.5)
    q = np.concatenate([w * k[..., None], np.cos(half)[..., None]], axis=-1)
    return quat_xyzw_to_rotmat(q)


def rotation_angle_rad(R: np.ndarray) -> np.ndarray:
    """Rotation angle in radians of rotation matrices ``[..., 3, 3]``."""
    return np.linalg.norm(so3_log(R), axis=-1)


def slerp_xyzw(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation between quaternions ``[..., 4]`` at ``alpha`` in [0, 1]."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    a = np.asarray(alpha, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)  # shortest arc
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_t = np.sin(theta)
    small = sin_t < 1e-9
    w0 = np.where(small, 1.0 - a, np.sin((1.0 - a) * theta) / np.where(small, 1.0, sin_t))
    w1 = np.where(small, a, np.sin(a * theta) / np.where(small, 1.0, sin_t))
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def interpolate_pose(
    t0: float, T0: np.ndarray, t1: float, T1: np.ndarray, t: float
) -> np.ndarray:
    """Pose at time ``t`` between ``(t0, T0)`` and ``(t1, T1)``: linear translation, slerp rotation."""
    if t1 == t0:
        return np.asarray(T0, dtype=np.float64).copy()
    a = (t - t0) / (t1 - t0)
    p0, q0 = tq_from_pose(T0)
    p1, q1 = tq_from_pose(T1)
    return pose_from_tq((1 - a) * p0 + a * p1, slerp_xyzw(q0, q1, a))


def umeyama_alignment(
    src_xyz: np.ndarray, dst_xyz: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991).

    Args:
        src_xyz: ``[N, 3]`` source points (e.g. estimated positions).
        dst_xyz: ``[N, 3]`` target points (e.g. ground-truth positions).
        with_scale: estimate the scale ``s`` as well (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns:
        ``(R [3, 3], t [3], s)``.
    """
    src = np.asarray(src_xyz, dtype=np.float64)
    dst = np.asarray(dst_xyz, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"expected two [N, 3] arrays, got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 3:
        raise ValueError(f"need at least 3 point pairs for alignment, got {n}")
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    if with_scale:
        var_s = np.mean(np.sum(xs**2, axis=1))
        s = float(np.trace(np.diag(D) @ S) / var_s) if var_s > 0 else 1.0
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam`` ``[4, 4]`` of an OpenCV camera at ``eye`` looking at ``target``.

    ``up`` is the world's up direction; the camera's -y axis is aligned with it as far as possible.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = target - eye
    nz = np.linalg.norm(z)
    if nz < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z /= nz
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T
