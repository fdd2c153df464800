"""Being lost has a bounded cost, and mapping follows the camera into unmapped space."""

import numpy as np
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
from atlas_pipeline.localization import sequence as seq
from atlas_pipeline.localization.relocalize import RelocalizationResult
from atlas_pipeline.localization.tracker import TrackResult


def _failing_align(frame, model, T_init, *args, **kwargs):
    return TrackResult(np.asarray(T_init, np.float64), 0.0, float("nan"), 0, False)


def test_relocalization_backs_off_while_lost(small_manifest, monkeypatch):
    """40 frames nothing can place: global relocalization is tried at frames 0, 2, 5, 10, 19, 36
    (waits of 1, 2, 4, 8, 16 frames), not 40 times; a success resets the wait."""
    m = small_manifest
    cfg = load_profile("default")
    st = seq.SequenceTracker(m.camera, cfg.localization, (0.1, 4.0), builder=VoxelGaussianBuilder(0.02))
    rgb, depth = m.read_rgb(0), m.read_depth_m(0)
    st.process(0, rgb, depth, T_given=np.eye(4))
    calls = []

    def failing_reloc(fp, extra=()):
        calls.append(1)
        return RelocalizationResult(np.full((4, 4), np.nan), False, 0.0, 0.0, float("nan"), "global", 0)

    monkeypatch.setattr(st.tracker, "align", _failing_align)
    monkeypatch.setattr(st, "_align_to_last_frame", lambda fp, guess: None)
    monkeypatch.setattr(type(st.relocalizer), "relocalize", lambda self, fp, extra=(), reach=None: failing_reloc(fp, extra))
    notes = [st.process(1 + k, rgb, depth).note for k in range(40)]
    assert len(calls) == 6, len(calls)
    assert notes.count(seq.NOTE_BACKING_OFF) == 34
    assert seq.RELOCALIZATION_BACKOFF_MAX_FRAMES == 16


@pytest.mark.parametrize("new_surface, keyframe, note", [
    (1.0, True, seq.NOTE_FRAME_TO_FRAME),  # a pan into unmapped space: the map grows there
    (0.0, False, seq.NOTE_CONFLICT),  # mapped space the map disagrees with (drift): never merged
])
def test_mapping_tracks_frame_to_frame_where_the_map_ends(small_manifest, monkeypatch, new_surface, keyframe, note):
    """When the map does not explain a frame (here: the map-alignment is forced to fail), mapping
    aligns it to the previous frame and keeps it tracked; it becomes a keyframe only when it sees
    space the map has no surface in."""
    m = small_manifest
    cfg = load_profile("default")
    st = seq.SequenceTracker(m.camera, cfg.localization, (0.1, 4.0), builder=VoxelGaussianBuilder(0.02))
    st.process(0, m.read_rgb(0), m.read_depth_m(0), T_given=np.eye(4))
    real_align = st.tracker.align
    to_map = {"n": 0}

    def align(frame, model, T_init, *args, **kwargs):
        if model is st.model:  # the map: pretend it does not cover the frame
            to_map["n"] += 1
            return _failing_align(frame, model, T_init)
        return real_align(frame, model, T_init, *args, **kwargs)

    monkeypatch.setattr(st.tracker, "align", align)
    monkeypatch.setattr(st, "_new_surface", lambda fp, T: new_surface)
    est = st.process(1, m.read_rgb(1), m.read_depth_m(1), timestamp_s=float(m.timestamps_s[1]))
    assert to_map["n"] >= 1
    assert est.status == seq.STATUS_TRACKED and est.note == note and est.keyframe == keyframe
    assert len(st.keyframe_indices) == 1 + keyframe
    # the ground truth of the small synthetic sequence is exact; frame 0 is at the identity here
    T_gt = np.linalg.inv(m.T_world_cam_gt[0]) @ m.T_world_cam_gt[1]
    assert np.linalg.norm(est.T_world_cam[:3, 3] - T_gt[:3, 3]) < 0.01


def test_incremental_surfel_map_equals_the_full_recompute():
    """The tracker's surfel map follows the builder keyframe by keyframe (only voxels near what
    was added are recomputed) and is bit-identical to recomputing it from the whole map."""
    from atlas_pipeline.localization.tracker import SurfelCache, SurfelModel

    rng = np.random.default_rng(7)
    b = VoxelGaussianBuilder(0.02)
    cache = SurfelCache(b)
    assert len(cache.model()) == 0
    for k in range(6):
        # patches of a plane and a box corner, overlapping the earlier ones
        u, v = rng.uniform(-0.3, 0.3, (2, 4000))
        pts = np.stack([u + 0.1 * k, v, 0.002 * rng.standard_normal(4000) + 0.01 * u], axis=1)
        b.integrate(pts, np.full((len(pts), 3), 100))
        inc, full = cache.model(), SurfelModel.from_builder(b)
        assert inc is cache.model()  # unchanged builder: the same model, no work
        np.testing.assert_array_equal(inc.centres, full.centres)
        np.testing.assert_array_equal(inc.normals, full.normals)
    # two merges between calls: recomputed whole, still identical
    b.integrate(pts + 0.5, np.full((len(pts), 3), 100))
    b.integrate(pts - 0.5, np.full((len(pts), 3), 100))
    np.testing.assert_array_equal(cache.model().centres, SurfelModel.from_builder(b).centres)


def test_relocalization_tries_a_bounded_number_of_viewpoints():
    """A map of 300 keyframes: relocalization screens at most MAX_PRIOR_VIEWPOINTS of them, the
    nearest to the caller's guess first and the rest spread over the map."""
    from atlas_pipeline.localization.relocalize import MAX_PRIOR_VIEWPOINTS, select_priors

    priors = np.repeat(np.eye(4)[None], 300, axis=0)
    priors[:, 0, 3] = np.linspace(0.0, 30.0, 300)  # a 30 m corridor
    guess = np.eye(4)
    guess[0, 3] = 12.0
    sel = select_priors(priors, [guess])
    assert len(sel) == MAX_PRIOR_VIEWPOINTS
    x = np.sort(sel[:, 0, 3])
    assert np.sum(np.abs(x - 12.0) < 1.0) >= MAX_PRIOR_VIEWPOINTS // 2 - 1  # the guess's neighbourhood
    assert x.min() < 1.0 and x.max() > 29.0  # and the ends of the map
    assert len(select_priors(priors[:10], [guess])) == 10  # small maps: every keyframe
    np.testing.assert_array_equal(select_priors(priors, [guess]), sel)  # deterministic


def test_voxels_near_a_merge_match_the_brute_force_neighbourhood():
    """``_near`` (nine sorted searches) marks exactly the voxels within one step of a touched one,
    also at the edge of the addressable range, where a shifted id may carry into another axis
    (it may then mark more, never fewer)."""
    from atlas_pipeline.gaussian_world.builder import _OFFSET, pack_voxel_ids, unpack_voxel_ids
    from atlas_pipeline.localization.tracker import _near

    rng = np.random.default_rng(3)
    ijk = rng.integers(-6, 6, (600, 3))
    edge = np.array([[_OFFSET - 1, 0, _OFFSET - 1], [-_OFFSET, -_OFFSET, -_OFFSET], [0, _OFFSET - 1, -_OFFSET]])
    beside = np.array([[_OFFSET - 2, 0, _OFFSET - 1], [_OFFSET - 1, 1, _OFFSET - 2], [-_OFFSET, -_OFFSET, 1 - _OFFSET],
                       [1 - _OFFSET, -_OFFSET, -_OFFSET], [0, _OFFSET - 2, -_OFFSET], [1, _OFFSET - 1, 1 - _OFFSET]])
    ijk = np.concatenate([ijk, edge, beside])
    ids = np.unique(pack_voxel_ids(ijk))
    touched = np.sort(rng.choice(ids, 40, replace=False))
    touched = np.unique(np.concatenate([touched, pack_voxel_ids(edge)]))
    t = unpack_voxel_ids(touched)
    a = unpack_voxel_ids(ids)
    truth = (np.abs(a[:, None, :] - t[None, :, :]).max(axis=2) <= 1).any(axis=1)
    got = _near(ids, touched)
    assert (got >= truth).all()  # never misses a neighbour
    inner = (np.abs(a) < _OFFSET - 2).all(axis=1)
    assert (got[inner] == truth[inner]).all()  # and is exact away from the range's edge
    assert not _near(ids, touched[:0]).any() and len(_near(ids[:0], touched)) == 0


def test_neighbourhood_surfels_match_a_numpy_reference():
    """The compiled neighbourhood statistics against a plain dictionary walk of every voxel's 27
    neighbours: same support, same centre, the same least-variance axis (up to sign), also for
    voxels at the edges of the addressable range."""
    from atlas_pipeline.gaussian_world._voxel_kernels import neighbourhood_surfels
    from atlas_pipeline.gaussian_world.builder import _BITS, _OFFSET, pack_voxel_ids, unpack_voxel_ids

    rng = np.random.default_rng(5)
    ijk = np.concatenate([rng.integers(-4, 4, (300, 3)),
                          [[_OFFSET - 1, 0, _OFFSET - 1], [_OFFSET - 1, 0, _OFFSET - 2], [_OFFSET - 2, 1, _OFFSET - 1],
                           [-_OFFSET, -_OFFSET, -_OFFSET], [-_OFFSET, 1 - _OFFSET, -_OFFSET], [1 - _OFFSET, -_OFFSET, 1 - _OFFSET]]])
    ids = np.unique(pack_voxel_ids(ijk))
    ijk = unpack_voxel_ids(ids)
    n = len(ids)
    count = rng.integers(1, 6, n).astype(np.float64)
    pts = [ijk[i] + rng.uniform(0, 1, (int(count[i]), 3)) * [1.0, 1.0, 0.2] for i in range(n)]  # flat-ish in z
    sum_xyz = np.stack([p.sum(axis=0) for p in pts])
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    sum_sq = np.stack([[np.sum(p[:, a] * p[:, b]) for a, b in pairs] for p in pts])
    centres, normals, support = neighbourhood_surfels(ids, ijk, count, sum_xyz, sum_sq, _OFFSET, _BITS)

    where = {tuple(v): i for i, v in enumerate(ijk)}
    for i in range(n):
        nb = [where[t] for t in (tuple(ijk[i] + d) for d in np.ndindex(3, 3, 3) for d in [np.array(d) - 1]) if t in where]
        p = np.concatenate([pts[j] for j in nb])
        assert support[i] == len(p)
        np.testing.assert_allclose(centres[i], pts[i].mean(axis=0), rtol=0, atol=1e-9)
        w, v = np.linalg.eigh(np.cov(p.T, bias=True))
        if w[1] - w[0] > 1e-6 * max(w[2], 1e-12):  # a well-defined least-variance axis
            assert abs(float(v[:, 0] @ normals[i])) > 0.999, (i, v[:, 0], normals[i])


def _two_places_relocalizer(small_manifest, calls):
    """A relocalizer whose alignments stay where they start and score a pose 4 m along x (a
    look-alike room) better than the origin's: ``calls`` collects every pose aligned."""
    from atlas_pipeline.localization.relocalize import Relocalizer
    from atlas_pipeline.localization.tracker import RGBDTracker, SurfelModel

    cfg = load_profile("default").localization
    tracker = RGBDTracker(small_manifest.camera, cfg, (0.1, 4.0))
    model = SurfelModel(np.zeros((0, 3)), np.zeros((0, 3)), 0.01)  # no colours, no global search

    def align(frame, model, T_init, *args, **kwargs):
        calls.append(np.asarray(T_init, np.float64)[:3, 3].copy())
        far = T_init[0, 3] > 2.0
        return TrackResult(np.asarray(T_init, np.float64), 0.9 if far else 0.7, 0.004, 1000, True,
                           agreement=0.95, overlap=0.95)

    reloc = Relocalizer(tracker, model, np.zeros((0, 4, 4)))
    reloc.tracker.align = align
    reloc._coarse.align = align
    return reloc


def test_a_look_alike_place_beyond_reach_is_not_taken(small_manifest):
    """Of two poses that both fit, the better-scoring one 4 m away wins with no reach; with the
    camera's reach around the other (1 m) the near one is placed and the far one is never even
    screened; with the reach around neither, nothing is placed."""
    from atlas_pipeline.localization.relocalize import Reach

    near, far = np.eye(4), np.eye(4)
    far[0, 3] = 4.0
    calls: list[np.ndarray] = []
    reloc = _two_places_relocalizer(small_manifest, calls)
    r = reloc.relocalize_fast(None, [near, far])
    assert r.ok and r.T_world_cam[0, 3] == 4.0
    calls.clear()
    r = reloc.relocalize_fast(None, [near, far], Reach(np.zeros(3), 1.0))
    assert r.ok and r.T_world_cam[0, 3] == 0.0
    assert all(c[0] < 2.0 for c in calls) and calls
    r = reloc.relocalize(None, [near, far], Reach(np.array([10.0, 0.0, 0.0]), 1.0))
    assert not r.ok and not np.isfinite(r.T_world_cam).any()


def test_a_lost_frame_is_relocalized_within_reach_of_the_last_placed_one(small_manifest, monkeypatch):
    """The reach a relocalization gets: the last placed frame's position, and as far as the
    camera can move since at RELOCALIZATION_MAX_SPEED_M_S, plus the margin."""
    m = small_manifest
    cfg = load_profile("default")
    st = seq.SequenceTracker(m.camera, cfg.localization, (0.1, 4.0), builder=VoxelGaussianBuilder(0.02))
    rgb, depth = m.read_rgb(0), m.read_depth_m(0)
    T0 = np.eye(4)
    T0[:3, 3] = [1.0, 2.0, 3.0]
    st.process(0, rgb, depth, T_given=T0, timestamp_s=10.0)
    reaches = []

    def failing_fast(fp, extra=(), reach=None):
        reaches.append(reach)
        return RelocalizationResult(np.full((4, 4), np.nan), False, 0.0, 0.0, float("nan"), "place", 0)

    monkeypatch.setattr(st.tracker, "align", _failing_align)
    monkeypatch.setattr(st, "_align_to_last_frame", lambda fp, guess: None)
    monkeypatch.setattr(type(st.relocalizer), "relocalize_fast", lambda self, fp, extra=(), reach=None:
                        failing_fast(fp, extra, reach))
    est = st.process(1, rgb, depth, timestamp_s=10.25)
    assert est.status == seq.STATUS_LOST and len(reaches) == 1
    np.testing.assert_array_equal(reaches[0].centre_w, [1.0, 2.0, 3.0])
    assert reaches[0].radius_m == pytest.approx(seq.RELOCALIZATION_REACH_MARGIN_M + 0.25 * seq.RELOCALIZATION_MAX_SPEED_M_S)
    st.process(2, rgb, depth)  # no time: no reach
    assert reaches[-1] is None
