"""Point-to-plane ICP against a fixed model (map or previous frame), coarse to fine.

The model's KD-tree and normals are built once and reused for every frame registered against it,
which is what makes frame-to-model tracking affordable on a CPU.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from atlas_pipeline._open3d import open3d
from atlas_pipeline.geometry import so3_exp

__all__ = ["PointModel", "IcpResult", "estimate_normals", "voxel_downsample", "icp_point_to_plane"]


def estimate_normals(points: np.ndarray, radius_m: float, max_nn: int = 20,
                     viewpoint: np.ndarray | None = None) -> np.ndarray:
    """Unit normals ``[N, 3]`` by local PCA (Open3D hybrid radius/KNN search).

    With ``viewpoint`` the normals are flipped to face it, which keeps point-to-plane residual
    signs consistent between frames.
    """
    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=max_nn))
    n = np.asarray(pcd.normals)
    if viewpoint is not None:
        flip = np.einsum("ij,ij->i", n, np.asarray(viewpoint)[None, :] - points) < 0
        n[flip] *= -1
    return n


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point (the first) per voxel of size ``voxel_m``: ``[M, 3]`` -> ``[K, 3]``, deterministic."""
    if len(points) == 0:
        return points
    keys = np.floor(points / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


class PointModel:
    """A registration target: points ``[N, 3]``, normals ``[N, 3]`` and a KD-tree over the points."""

    def __init__(self, points: np.ndarray, normals: np.ndarray | None = None, normal_radius_m: float = 0.05):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        if len(self.points) < 10:
            raise ValueError(f"a registration model needs at least 10 points, got {len(self.points)}")
        self.normals = (np.asarray(normals, np.float64) if normals is not None
                        else estimate_normals(self.points, normal_radius_m))
        self.tree = cKDTree(self.points)


@dataclass
class IcpResult:
    """Outcome of one registration.

    Attributes:
        T: ``[4, 4]`` estimated transform taking source points into the model frame.
        fitness: share of source points with a model neighbour within the final distance.
        inlier_rmse_m: RMS point-to-plane residual of those inliers.
        iterations: Gauss-Newton iterations run over all levels.
        n_inliers: number of inlier correspondences at the end.
    """

    T: np.ndarray
    fitness: float
    inlier_rmse_m: float
    iterations: int
    n_inliers: int


def icp_point_to_plane(
    model: PointModel,
    source: np.ndarray,
    T_init: np.ndarray,
    max_correspondence_m: float,
    iterations: int = 30,
    levels: tuple[float, ...] = (4.0, 2.0, 1.0),
    tol: float = 1e-6,
) -> IcpResult:
    """Register ``source`` points ``[M, 3]`` to ``model``, starting at ``T_init`` ``[4, 4]``.

    Coarse to fine: each level multiplies the correspondence distance (so a poor initial guess
    still finds partners) and gets ``iterations`` split across levels. Residuals are Huber-weighted
    so outliers (moving objects, depth edges) pull less.
    """
    src = np.asarray(source, dtype=np.float64)
    T = np.asarray(T_init, dtype=np.float64).copy()
    if len(src) < 6:
        return IcpResult(T, 0.0, float("inf"), 0, 0)
    per_level = max(1, iterations // len(levels))
    its = 0
    for li, factor in enumerate(levels):
        dmax = max_correspondence_m * factor
        n_it = per_level if li < len(levels) - 1 else max(1, iterations - per_level * (len(levels) - 1))
        for _ in range(n_it):
            its += 1
            p = src @ T[:3, :3].T + T[:3, 3]
            d, idx = model.tree.query(p, k=1, distance_upper_bound=dmax, workers=-1)
            ok = np.isfinite(d)
            if ok.sum() < 6:
                break
            pi, q, n = p[ok], model.points[idx[ok]], model.normals[idx[ok]]
            r = np.einsum("ij,ij->i", pi - q, n)
            # Huber weights with a threshold at a third of the correspondence distance.
            k = dmax / 3.0
            w = np.where(np.abs(r) <= k, 1.0, k / np.maximum(np.abs(r), 1e-12))
            J = np.concatenate([np.cross(pi, n), n], axis=1)  # [M, 6]: d r / d (omega, v)
            A = (J * w[:, None]).T @ J
            b = -(J * w[:, None]).T @ r
            try:
                xi = np.linalg.solve(A + 1e-9 * np.eye(6), b)
            except np.linalg.LinAlgError:
                break
            dT = np.eye(4)
            dT[:3, :3] = so3_exp(xi[:3])
            dT[:3, 3] = xi[3:]
            T = dT @ T
            if np.linalg.norm(xi) < tol:
                break
    # Final quality against the finest correspondence distance.
    p = src @ T[:3, :3].T + T[:3, 3]
    d, idx = model.tree.query(p, k=1, distance_upper_bound=max_correspondence_m, workers=-1)
    ok = np.isfinite(d)
    n_in = int(ok.sum())
    if n_in:
        r = np.einsum("ij,ij->i", p[ok] - model.points[idx[ok]], model.normals[idx[ok]])
        rmse = float(np.sqrt(np.mean(r**2)))
    else:
        rmse = float("inf")
    return IcpResult(T, n_in / len(src), rmse, its, n_in)
