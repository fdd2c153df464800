"""Global registration of a frame against a map, with no initial pose.

Four steps, as in Open3D's feature-matching pipeline (and Rusu et al., *Fast Point Feature
Histograms*, ICRA 2009): FPFH features of both sides (Open3D computes them), mutual nearest
neighbours in feature space, RANSAC over those matches (:mod:`._ransac`), and a coarse-to-fine
point-to-plane ICP of each pose found. Matching, RANSAC and ICP are here rather than Open3D's
``registration_ransac_based_on_feature_matching`` / ``registration_icp`` for two reasons:

- the map's side (features, their KD-tree, the KD-tree of the surfels) is built once per map,
  where Open3D rebuilds both KD-trees on every call (a second of a large map's full search each);
- the answer is repeatable: Open3D's RANSAC draws samples from threads in scheduling order, so a
  seeded run still varies, and a lost camera was placed in one room on one run, in its look-alike
  twin on the next.

Shapes: points ``[N, 3]`` (m), features ``[N, 33]``, poses ``[4, 4]`` (``T_world_cam``: frame
points in the camera frame, map points in the world frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from atlas_pipeline.localization._ransac import SAMPLE_SIZE, RansacParams, fit_rigid, iterations_needed, ransac_batch
from atlas_pipeline.localization._voxel_hash import VoxelTable, table_of_points
from atlas_pipeline.localization.tracker import apply_update, converged, poses_differ

__all__ = ["FeatureCloud", "GlobalRegistration", "feature_cloud", "mutual_matches", "ransac_poses", "icp_point_to_plane"]

# Feature scales, in units of the feature voxel (Open3D's tutorial values).
NORMAL_RADIUS_VOXELS = 2.5
NORMAL_MAX_NN = 30
FPFH_RADIUS_VOXELS = 5.0
FPFH_MAX_NN = 100
# RANSAC: a match is an inlier within this many voxels; sample edges agree to this ratio.
INLIER_VOXELS = 1.5
EDGE_RATIO = 0.9
MAX_ITERATIONS = 100_000
CONFIDENCE = 0.999
# Iterations run in parallel batches of this many; the stopping test runs between batches.
BATCH_ITERATIONS = 16_384
# Fewer mutual matches than this: use every frame point's nearest match (as Open3D does).
MIN_MUTUAL_MATCHES = 3 * SAMPLE_SIZE
# Several poses per search: the best, and others at least this far from every one kept, with at
# least this share of the best's support (a symmetric room's twin pose).
DISTINCT_M = 0.3
DISTINCT_DEG = 20.0
MIN_SHARE_OF_BEST = 0.5
# A pose must put at least this many frame points on the map.
MIN_SUPPORT = 30
# ICP: correspondence gates in voxels, coarse to fine; iterations per gate; the update below
# which it has converged.
ICP_GATES_VOXELS = (4.0, 2.0, 1.0)
ICP_MAX_ITERATIONS = 30
ICP_MIN_POINTS = 6
# ICP aligns at most this many of the frame's points (an even stride through them): six degrees of
# freedom need far fewer, and each costs a query of the map's KD-tree per iteration.
ICP_MAX_POINTS = 1500
ICP_CONVERGED_STEP = 1e-6  # m and rad


class FeatureCloud(NamedTuple):
    """A point cloud downsampled to the feature voxel, with its FPFH descriptors."""

    points: np.ndarray  # [N, 3]
    features: np.ndarray  # [N, 33]


def feature_cloud(points: np.ndarray, voxel_m: float) -> FeatureCloud:
    """``points [P, 3]`` downsampled to ``voxel_m`` (centroid per voxel), normals, FPFH."""
    from atlas_pipeline._open3d import open3d, point_cloud

    o3d = open3d()
    pc = point_cloud(np.asarray(points, np.float64)).voxel_down_sample(voxel_m)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_VOXELS * voxel_m, max_nn=NORMAL_MAX_NN))
    f = o3d.pipelines.registration.compute_fpfh_feature(
        pc, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_VOXELS * voxel_m, max_nn=FPFH_MAX_NN))
    return FeatureCloud(np.asarray(pc.points, np.float64), np.ascontiguousarray(np.asarray(f.data, np.float64).T))


def mutual_matches(src: np.ndarray, dst: np.ndarray, dst_tree: cKDTree) -> np.ndarray:
    """``[C, 2]`` (src index, dst index): each ``src [N, 33]`` feature's nearest in ``dst [M, 33]``
    (``dst_tree`` is its KD-tree), kept where that one's nearest in ``src`` is it again; every
    nearest pair when fewer than :data:`MIN_MUTUAL_MATCHES` are mutual."""
    if len(src) == 0 or len(dst) == 0:
        return np.zeros((0, 2), np.int64)
    _, j = dst_tree.query(src, k=1)
    j = np.asarray(j, np.int64)
    used = np.unique(j)
    _, back = cKDTree(src).query(dst[used], k=1)
    back_of = np.full(len(dst), -1, np.int64)
    back_of[used] = back
    i = np.arange(len(src), dtype=np.int64)
    mutual = back_of[j] == i
    keep = mutual if int(mutual.sum()) >= MIN_MUTUAL_MATCHES else np.ones_like(mutual)
    return np.stack([i[keep], j[keep]], axis=1)


def ransac_poses(src: np.ndarray, dst: np.ndarray, cloud: np.ndarray, table: VoxelTable, params: RansacParams,
                 n_poses: int, max_iterations: int = MAX_ITERATIONS) -> list[np.ndarray]:
    """Up to ``n_poses`` distinct poses ``[4, 4]`` mapping the frame onto the map, most
    supported first: ``src [C, 3]`` and ``dst [C, 3]`` are the matched points, ``cloud [N, 3]``
    the frame's points and ``table`` the map's occupied voxels that grade a pose (see
    :func:`._ransac.ransac_batch`). Each pose is refitted to the matches it agrees with. Runs until
    an all-agreeing sample of the best pose has been drawn with :data:`CONFIDENCE`, or for
    ``max_iterations``."""
    C = len(src)
    if C < SAMPLE_SIZE:
        return []
    src = np.ascontiguousarray(src, np.float64)
    dst = np.ascontiguousarray(dst, np.float64)
    cloud = np.ascontiguousarray(cloud, np.float64)
    poses, supports = [], []
    best_support, best_agreeing = -1, 0  # of the earliest best-supported iteration so far
    done = 0
    while done < max_iterations:
        n = min(BATCH_ITERATIONS, max_iterations - done)
        p, s, a = ransac_batch(src, dst, cloud, table, done, n, params)
        poses.append(p)
        supports.append(s)
        done += n
        k = int(np.argmax(s))
        if s[k] > best_support:
            best_support, best_agreeing = int(s[k]), int(a[k])
        if best_agreeing > 0 and done >= iterations_needed(best_agreeing / C, CONFIDENCE):
            break
    pose_all = np.concatenate(poses)
    support = np.concatenate(supports)
    # Most support first; ties by iteration number, so the order is fixed.
    order = np.lexsort((np.arange(len(support)), -support))
    best = int(support[order[0]])
    if best < MIN_SUPPORT:
        return []
    kept: list[np.ndarray] = []
    for k in order:
        if len(kept) >= n_poses or support[k] < max(MIN_SUPPORT, MIN_SHARE_OF_BEST * best):
            break
        T = _refit(pose_all[k], src, dst, params.inlier_m)
        if all(_far(T, o) for o in kept):
            kept.append(T)
    return kept


def _refit(pose: np.ndarray, src: np.ndarray, dst: np.ndarray, inlier_m: float) -> np.ndarray:
    """``[4, 4]``: ``pose [3, 4]`` refitted by least squares to its inliers."""
    T = np.eye(4)
    T[:3] = pose
    inl = np.linalg.norm(src @ pose[:, :3].T + pose[:, 3] - dst, axis=1) <= inlier_m
    if int(inl.sum()) >= SAMPLE_SIZE:
        T[:3] = fit_rigid(np.ascontiguousarray(src[inl]), np.ascontiguousarray(dst[inl]))
    return T


def _far(T_a: np.ndarray, T_b: np.ndarray) -> bool:
    return poses_differ(T_a, T_b, DISTINCT_M, DISTINCT_DEG)


def icp_point_to_plane(points: np.ndarray, T: np.ndarray, tree: cKDTree, map_points: np.ndarray,
                       map_normals: np.ndarray, gates_m: tuple[float, ...]) -> np.ndarray:
    """``[4, 4]``: ``T`` refined so ``points [N, 3]`` lie on the map's planes (point-to-plane
    Gauss-Newton, nearest map point within each gate of ``gates_m`` in turn; ``tree`` is the
    KD-tree of ``map_points [M, 3]``, whose unit normals are ``map_normals [M, 3]``). At most
    :data:`ICP_MAX_POINTS` of the points take part."""
    T = np.array(T, np.float64)
    points = np.asarray(points, np.float64)[:: max(1, -(-len(points) // ICP_MAX_POINTS))]
    for gate in gates_m:
        for _ in range(ICP_MAX_ITERATIONS):
            p = points @ T[:3, :3].T + T[:3, 3]
            d, j = tree.query(p, k=1, distance_upper_bound=gate)
            ok = np.isfinite(d)
            if int(ok.sum()) < ICP_MIN_POINTS:
                break
            p, q, n = p[ok], map_points[j[ok]], map_normals[j[ok]]
            r = np.einsum("ij,ij->i", p - q, n)  # [K]
            J = np.concatenate([n, np.cross(p, n)], axis=1)  # [K, 6], xi = (v, omega) as the tracker's
            try:
                xi = np.linalg.solve(J.T @ J, -J.T @ r)
            except np.linalg.LinAlgError:
                break
            T = apply_update(xi, T)
            if converged(xi, ICP_CONVERGED_STEP):
                break
    return T


@dataclass
class _MapSide:
    cloud: FeatureCloud
    feature_tree: cKDTree
    surfel_tree: cKDTree
    occupied: VoxelTable  # voxels of edge params.inlier_m holding a surfel


class GlobalRegistration:
    """Poses of frames in one map, the map's features and KD-trees built on first use.

    Args:
        map_points: ``[M, 3]`` surfel centres (world).
        map_normals: ``[M, 3]`` their unit normals.
        voxel_m: feature voxel (both sides are downsampled to it).
        seed: RANSAC's seed; the same seed gives the same poses.
    """

    def __init__(self, map_points: np.ndarray, map_normals: np.ndarray, voxel_m: float, seed: int = 0):
        self.map_points = np.asarray(map_points, np.float64)
        self.map_normals = np.asarray(map_normals, np.float64)
        self.voxel_m = float(voxel_m)
        self.params = RansacParams(INLIER_VOXELS * self.voxel_m, EDGE_RATIO, int(seed))
        self._map: _MapSide | None = None

    def _map_side(self) -> _MapSide:
        if self._map is None:
            cloud = feature_cloud(self.map_points, self.voxel_m)
            self._map = _MapSide(cloud, cKDTree(cloud.features), cKDTree(self.map_points),
                                 table_of_points(self.map_points, self.params.inlier_m))
        return self._map

    def hypotheses(self, points_cam: np.ndarray, n_poses: int) -> list[np.ndarray]:
        """Up to ``n_poses`` distinct ``T_world_cam [4, 4]`` placing ``points_cam [P, 3]`` (the
        frame's back-projected depth) on the map, each polished by ICP; best RANSAC support first."""
        side = self._map_side()
        frame = feature_cloud(points_cam, self.voxel_m)
        if len(frame.points) < MIN_SUPPORT:
            return []
        m = mutual_matches(frame.features, side.cloud.features, side.feature_tree)
        found = ransac_poses(frame.points[m[:, 0]], side.cloud.points[m[:, 1]], frame.points, side.occupied,
                             self.params, n_poses)
        gates = tuple(g * self.voxel_m for g in ICP_GATES_VOXELS)
        return [icp_point_to_plane(frame.points, T, side.surfel_tree, self.map_points, self.map_normals, gates)
                for T in found]
