"""Multiple maps. A run of lost frames starts a new map; recognising the old place
merges the maps, and every pose ends in the main map's frame."""


import numpy as np
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder, _moments_to_matrices
from atlas_pipeline.geometry import invert_se3
from atlas_pipeline.localization import sequence as seq
from atlas_pipeline.localization.relocalize import Relocalizer, RelocalizationResult
from atlas_pipeline.localization.tracker import RGBDTracker, TrackResult
from atlas_pipeline.mapping.keyframes import KeyframeSet, slam_poses


def _rot(axis: int, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def test_builder_merge_moves_the_statistics_exactly():
    """Merging a builder under T gives the count, first and second moments that integrating the
    moved points gives (summed over voxels: binning differs only at voxel borders), and every
    merged voxel holds its mean."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.5, 0.5, (5000, 3))
    cols = rng.integers(0, 255, (5000, 3))
    T = np.eye(4)
    T[:3, :3] = _rot(2, 30.0) @ _rot(0, 10.0)
    T[:3, 3] = [0.3, -0.2, 1.1]
    src = VoxelGaussianBuilder(0.05)
    src.integrate(pts, cols)
    merged = VoxelGaussianBuilder(0.05)
    merged.merge(src, T)
    direct = VoxelGaussianBuilder(0.05)
    direct.integrate(pts @ T[:3, :3].T + T[:3, 3], cols)
    assert merged.count.sum() == direct.count.sum() == 5000
    np.testing.assert_allclose(merged.sum_xyz.sum(0), direct.sum_xyz.sum(0), rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(merged.sum_sq.sum(0), direct.sum_sq.sum(0), rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(merged.sum_rgb.sum(0), direct.sum_rgb.sum(0))
    means = merged.sum_xyz / merged.count[:, None]
    from atlas_pipeline.gaussian_world.builder import unpack_voxel_ids
    np.testing.assert_array_equal(np.floor(means / 0.05).astype(np.int64), unpack_voxel_ids(merged.ids))
    # Covariances are SPD after the move (the cross terms are right, not just the sums).
    Q = _moments_to_matrices(merged.sum_sq)
    n = merged.count[:, None, None]
    mu = means[:, :, None]
    cov = Q / n - mu @ mu.transpose(0, 2, 1)
    assert (np.linalg.eigvalsh(cov)[:, 0] > -1e-9).all()


def test_builder_merge_into_an_occupied_builder_accumulates():
    a, b = VoxelGaussianBuilder(0.1), VoxelGaussianBuilder(0.1)
    p = np.array([[0.05, 0.05, 0.05], [0.05, 0.06, 0.05]])
    a.integrate(p, np.full((2, 3), 100))
    b.integrate(p, np.full((2, 3), 200))
    a.merge(b, np.eye(4))
    assert len(a) == 1 and a.count[0] == 4 and a.n_keyframes[0] == 2
    np.testing.assert_allclose(a.sum_rgb[0], [600, 600, 600])


class _Failures:
    """Make every alignment and relocalization fail on the frames in ``window`` (a sensor
    dropout the map cannot explain), and count the alignments to older maps."""

    def __init__(self, monkeypatch, window):
        self.window, self.current = set(window), None
        real_process, real_align = seq.SequenceTracker.process, RGBDTracker.align
        real_reloc = Relocalizer.relocalize
        state = self

        def process(tracker, index, *a, **k):
            state.current = index
            return real_process(tracker, index, *a, **k)

        def align(tracker, frame, model, T_init, *args, **kwargs):
            if state.current in state.window:
                return TrackResult(np.asarray(T_init, np.float64), 0.0, float("nan"), 0, False)
            return real_align(tracker, frame, model, T_init, *args, **kwargs)

        def relocalize(reloc, frame, extra=(), reach=None):
            if state.current in state.window:
                return RelocalizationResult(np.full((4, 4), np.nan), False, 0.0, 0.0, float("nan"), "global", 0)
            return real_reloc(reloc, frame, extra, reach)

        monkeypatch.setattr(seq.SequenceTracker, "process", process)
        monkeypatch.setattr(RGBDTracker, "align", align)
        monkeypatch.setattr(Relocalizer, "relocalize", relocalize)


def _cfg(new_map_after: int):
    cfg = load_profile("default")
    # every frame a keyframe: the 12-frame sequence then tries a merge on each frame of the new map
    mapping = cfg.mapping.model_copy(update=dict(keyframe_translation_m=0.0, keyframe_rotation_deg=0.0,
                                                 new_map_after_lost_frames=new_map_after, loop_closure=False))
    return cfg, mapping


def _errors_cm(manifest, poses, frames):
    T0 = manifest.T_world_cam_gt[0]
    return [100 * np.linalg.norm((invert_se3(T0) @ manifest.T_world_cam_gt[i])[:3, 3] - poses[i][:3, 3]) for i in frames]


@pytest.mark.slow
def test_lost_frames_start_a_new_map_that_merges_back(small_manifest, monkeypatch):
    m = small_manifest
    cfg, mapping = _cfg(new_map_after=2)
    _Failures(monkeypatch, window=(4, 5))
    slam = slam_poses(m, mapping, cfg.localization, (0.1, 4.0), 2)
    assert slam.status[4] == seq.STATUS_LOST
    assert slam.status[5] == seq.STATUS_NEW_MAP
    assert all(s in seq.PLACED_STATUSES for s in slam.status[6:]), slam.status
    maps = slam.maps
    assert maps["n_maps"] == 2 and maps["n_merged"] == 1 and maps["main"] == 0
    new = maps["maps"][1]
    assert new["first_frame"] == 5 and new["merged_into"] == 0 and new["merged_at_frame"] >= 6
    # the new map was seeded at frame 3's pose: the merge moved it by about the motion of 2 frames
    motion_cm = _errors_cm(m, np.repeat(slam.T_world_cam[3:4], 12, axis=0), [5])[0]
    assert new["correction_m"] * 100 == pytest.approx(motion_cm, abs=1.0)
    # every frame but the lost one is in the main map, within 1.5 cm of the truth (frame 0 = identity)
    assert slam.valid.tolist() == [i != 4 for i in range(12)]
    assert max(_errors_cm(m, slam.T_world_cam, [i for i in range(12) if i != 4])) < 1.5
    # the new map's keyframes joined the main map's, in frame order
    assert 5 in slam.keyframe_indices.tolist() and (np.diff(slam.keyframe_indices) > 0).all()


def test_without_new_maps_the_frames_stay_lost(small_manifest, monkeypatch):
    m = small_manifest
    cfg, mapping = _cfg(new_map_after=0)
    _Failures(monkeypatch, window=(4, 5))
    slam = slam_poses(m, mapping, cfg.localization, (0.1, 4.0), 2)
    assert slam.status[4:6] == [seq.STATUS_LOST, seq.STATUS_LOST]
    assert slam.maps["n_maps"] == 1


def test_a_map_never_recognised_stays_out_of_the_world(small_manifest, monkeypatch):
    """When the old place is never seen again (every alignment to the old map fails), the frames
    of the new map keep a pose but are not valid mapping poses, and the report says so."""
    m = small_manifest
    cfg, mapping = _cfg(new_map_after=2)
    _Failures(monkeypatch, window=(4, 5))
    monkeypatch.setattr(seq.SequenceTracker, "_try_merge", lambda self, index, fp, T: None)
    slam = slam_poses(m, mapping, cfg.localization, (0.1, 4.0), 2)
    assert slam.maps["n_maps"] == 2 and slam.maps["n_merged"] == 0
    assert slam.maps["main"] == 1  # the later map holds more keyframes (6..11 against 0..3)
    assert np.isfinite(slam.T_world_cam[5:]).all()
    assert not slam.valid[:4].any() and slam.valid[5:].all()


def test_keyframe_set_keeps_the_map_record(tmp_path, small_manifest, monkeypatch):
    m = small_manifest
    cfg, mapping = _cfg(new_map_after=2)
    _Failures(monkeypatch, window=(4, 5))
    slam = slam_poses(m, mapping, cfg.localization, (0.1, 4.0), 2)
    ks = KeyframeSet(slam.T_world_cam, slam.valid, slam.keyframe_indices, "estimated", None, slam.maps)
    ks.save(tmp_path)
    back = KeyframeSet.load(tmp_path)
    assert back.maps["n_merged"] == 1 and back.maps["maps"][1]["first_frame"] == 5
