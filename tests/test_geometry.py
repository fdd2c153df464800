import numpy as np
import pytest

from atlas_pipeline.geometry import (
    interpolate_pose, invert_se3, look_at, pose_from_tq, quat_xyzw_to_rotmat, rotation_angle_rad,
    rotmat_to_quat_xyzw, so3_exp, so3_log, tq_from_pose, umeyama_alignment,
)


def _random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q


def test_quaternion_roundtrip_and_orthonormal():
    q = _random_quats(200)
    R = quat_xyzw_to_rotmat(q)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(rotmat_to_quat_xyzw(R), q, atol=1e-12)


def test_quaternion_convention_is_xyzw_hamilton():
    # 90 degrees about z: x axis goes to y axis.
    q = np.array([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    assert np.allclose(quat_xyzw_to_rotmat(q) @ [1, 0, 0], [0, 1, 0])


def test_so3_exp_log_inverse():
    w = np.random.default_rng(1).normal(size=(100, 3))
    w *= (np.pi * 0.99 / np.maximum(np.linalg.norm(w, axis=1), np.pi))[:, None]
    assert np.allclose(so3_log(so3_exp(w)), w, atol=1e-9)
    assert np.allclose(rotation_angle_rad(so3_exp(w)), np.linalg.norm(w, axis=1))


def test_invert_and_tq():
    T = pose_from_tq(np.random.default_rng(2).normal(size=(10, 3)), _random_quats(10, 3))
    assert np.allclose(invert_se3(T) @ T, np.eye(4), atol=1e-12)
    t, q = tq_from_pose(T)
    assert np.allclose(pose_from_tq(t, q), T)


def test_interpolate_pose_midpoint():
    T0 = np.eye(4)
    T1 = pose_from_tq(np.array([1.0, 0, 0]), np.array([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]))
    Tm = interpolate_pose(0.0, T0, 1.0, T1, 0.5)
    assert np.allclose(Tm[:3, 3], [0.5, 0, 0])
    assert np.isclose(np.degrees(rotation_angle_rad(Tm[:3, :3])), 45.0)


def test_umeyama_recovers_rigid_transform():
    rng = np.random.default_rng(4)
    src = rng.normal(size=(50, 3))
    R = quat_xyzw_to_rotmat(_random_quats(1, 5)[0])
    t = np.array([0.3, -1.0, 2.0])
    R_est, t_est, s = umeyama_alignment(src, src @ R.T + t)
    assert np.allclose(R_est, R, atol=1e-10) and np.allclose(t_est, t, atol=1e-10) and s == 1.0
    with pytest.raises(ValueError):
        umeyama_alignment(src[:2], src[:2])


def test_look_at_points_z_at_target_and_y_down():
    T = look_at([0, 0, 1], [2, 0, 1])
    assert np.allclose(T[:3, 2], [1, 0, 0])  # optical axis towards the target
    assert np.allclose(T[:3, 1], [0, 0, -1])  # image y points down the world
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
