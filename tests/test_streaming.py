"""Fused frames stream in chunks: bounded memory, exact round trip, deterministic bytes."""

from __future__ import annotations

import gc
import tracemalloc

import numpy as np
import pytest

from atlas_pipeline.config import FusionConfig
from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.perception.rgbd import FusedFrames, backproject, fuse_frames


def _expected(manifest, cfg, i):
    return backproject(manifest.read_depth_m(i), manifest.read_rgb(i), manifest.camera, cfg.stride,
                       cfg.min_depth_m, cfg.max_depth_m)


def test_chunked_fusion_gives_every_frames_points_and_round_trips(small_manifest, tmp_path):
    cfg = FusionConfig()
    fused = fuse_frames(small_manifest, cfg, log=lambda *_: None, chunk_frames=5)  # 12 frames: 5 + 5 + 2
    assert fused.points_cam is None and fused.n_chunks == 3 and fused.n_frames == small_manifest.n_frames
    for i in (11, 0, 7, 3):  # out of order: chunks reload
        pts, cols = fused.frame(i)
        ep, ec = _expected(small_manifest, cfg, i)
        np.testing.assert_array_equal(pts, ep)
        np.testing.assert_array_equal(cols, ec)
    files = fused.save(tmp_path / "a")
    assert sorted(p.name for p in files) == ["fused-00000.npz", "fused-00001.npz", "fused-00002.npz",
                                             "fused.json", "fused.npz"]
    back = FusedFrames.load(tmp_path / "a")
    assert back.n_points == fused.n_points and back.chunk_frames == 5
    for i in range(fused.n_frames):
        np.testing.assert_array_equal(back.frame(i)[0], fused.frame(i)[0])
    # each chunk is a plain npz any tool opens
    with np.load(tmp_path / "a" / "fused-00001.npz") as z:
        assert z["points_cam"].shape == (int(fused.offsets[10] - fused.offsets[5]), 3)


def test_equal_points_give_equal_bytes(small_manifest, tmp_path):
    """Content hashes are data versions: a second fusion of the same frames writes the same bytes."""
    cfg = FusionConfig()
    a = fuse_frames(small_manifest, cfg, log=lambda *_: None).save(tmp_path / "a")
    b = fuse_frames(small_manifest, cfg, log=lambda *_: None).save(tmp_path / "b")
    for pa, pb in zip(sorted(a), sorted(b)):
        if pa.suffix == ".npz":
            assert pa.read_bytes() == pb.read_bytes(), pa.name


def test_the_spool_goes_with_the_object_and_the_saved_copy_stays(small_manifest, tmp_path):
    fused = fuse_frames(small_manifest, FusionConfig(), log=lambda *_: None)
    spool = fused.chunk_dir
    assert spool.is_dir()
    del fused
    gc.collect()
    assert not spool.exists()  # the temporary folder this process made
    fused = fuse_frames(small_manifest, FusionConfig(), log=lambda *_: None)
    spool = fused.chunk_dir
    fused.save(tmp_path / "kept")
    # Saving hands the spool over: it goes now, so nothing later changes the saved files' identity
    # (link count, change time), and the object reads the saved chunks.
    assert not spool.exists()
    ident = [(p.stat().st_nlink, p.stat().st_ctime_ns) for p in sorted((tmp_path / "kept").iterdir())]
    assert fused.frame(0)[0].shape[1] == 3
    del fused
    gc.collect()
    assert [(p.stat().st_nlink, p.stat().st_ctime_ns) for p in sorted((tmp_path / "kept").iterdir())] == ident
    loaded = FusedFrames.load(tmp_path / "kept")
    assert loaded.frame(0)[0].shape[1] == 3
    del loaded
    gc.collect()
    assert (tmp_path / "kept" / "fused-00000.npz").is_file()  # an artifact folder is never removed


def test_memory_is_one_chunk_not_the_sequence(small_manifest):
    """Peak traced allocation while fusing with 1-frame chunks stays near one frame's points,
    while holding the whole sequence in memory takes the sum of all frames."""
    cfg = FusionConfig(stride=1)
    small_manifest.read_rgb(0), small_manifest.read_depth_m(0)  # warm readers and ray caches
    fuse_frames(small_manifest, cfg, log=lambda *_: None, chunk_frames=1)
    gc.collect()
    tracemalloc.start()
    try:
        fused = fuse_frames(small_manifest, cfg, log=lambda *_: None, chunk_frames=1)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    whole = fused.n_points * (3 * 4 + 3)  # float32 xyz + uint8 rgb of every frame
    assert fused.n_frames >= 10
    assert peak < 0.5 * whole, (peak, whole)


def test_a_missing_or_wrong_chunk_is_named(small_manifest, tmp_path):
    fuse_frames(small_manifest, FusionConfig(), log=lambda *_: None, chunk_frames=5).save(tmp_path / "f")
    (tmp_path / "f" / "fused-00002.npz").unlink()
    with pytest.raises(ArtifactError, match="missing chunk file.*fused-00002.npz"):
        FusedFrames.load(tmp_path / "f")
    fuse_frames(small_manifest, FusionConfig(), log=lambda *_: None, chunk_frames=5).save(tmp_path / "g")
    np.savez(tmp_path / "g" / "fused-00001.npz", points_cam=np.zeros((3, 3), np.float32),
             colors=np.zeros((3, 3), np.uint8))
    f = FusedFrames.load(tmp_path / "g")
    f.frame(0)
    with pytest.raises(ArtifactError, match=r"fused-00001.npz: points_cam \[3, 3\]"):
        f.frame(6)


class _CountingManifest:
    """A manifest stand-in whose frames are their index; frame ``bad`` cannot be read."""

    def __init__(self, n: int, bad: int | None = None):
        self.n, self.bad, self.reads = n, bad, []

    def read_rgb(self, i):
        if i == self.bad:
            raise ValueError(f"frame {i}: truncated PNG")
        self.reads.append(i)
        return np.full((2, 2, 3), i, np.uint8)

    def read_depth_m(self, i, allow_empty=False):
        assert allow_empty  # an all-zero depth frame is the tracker's to mark lost, not the reader's to refuse
        return np.full((2, 2), float(i), np.float32)


def test_read_ahead_yields_every_frame_in_order_and_reads_only_a_few_ahead():
    from atlas_pipeline.perception.rgbd import READ_AHEAD_FRAMES, read_ahead

    m = _CountingManifest(10)
    order = [5, 6, 7, 4, 3, 2, 1, 0]  # forward from an anchor, then backward
    got = []
    for i, rgb, depth in read_ahead(m, order):
        assert int(rgb[0, 0, 0]) == i and float(depth[0, 0]) == i
        got.append(i)
        assert len(m.reads) <= len(got) + READ_AHEAD_FRAMES  # memory: a few frames, not the sequence
    assert got == order
    # A caller that stops early leaves at most the frames in flight read.
    m = _CountingManifest(100)
    for i, _, _ in read_ahead(m, range(100)):
        if i == 3:
            break
    assert len(m.reads) <= 4 + READ_AHEAD_FRAMES


def test_read_ahead_raises_a_read_error_at_its_frame():
    from atlas_pipeline.perception.rgbd import read_ahead

    got = []
    with pytest.raises(ValueError, match="frame 4: truncated PNG"):
        for i, _, _ in read_ahead(_CountingManifest(10, bad=4), range(10)):
            got.append(i)
    assert got == [0, 1, 2, 3]


def test_read_ahead_runs_on_frame_on_the_reader_thread_in_order_before_yielding():
    import threading

    from atlas_pipeline.perception.rgbd import read_ahead

    seen, threads = [], set()

    def on_frame(i, rgb, depth):
        seen.append(i)
        threads.add(threading.current_thread().name)

    order = [3, 4, 2, 1, 0]
    for i, _, _ in read_ahead(_CountingManifest(10), order, on_frame):
        assert i in seen  # done before the frame reaches the caller
    assert seen == order
    assert threads and threading.current_thread().name not in threads


def test_read_ahead_raises_an_on_frame_error_at_its_frame_and_closing_waits_for_the_reader():
    import time

    from atlas_pipeline.perception.rgbd import read_ahead

    def on_frame(i, rgb, depth):
        if i == 2:
            raise OSError(f"frame {i}: chunk file not writable")

    got = []
    with pytest.raises(OSError, match="frame 2: chunk file not writable"):
        for i, _, _ in read_ahead(_CountingManifest(10), range(10), on_frame):
            got.append(i)
    assert got == [0, 1]
    # Closed early, the iterator returns only once the frame being worked on is done: the caller
    # may then remove what on_frame writes to.
    started, finished = [], []

    def slow(i, rgb, depth):
        started.append(i)
        if i == 1:
            time.sleep(0.3)
        finished.append(i)

    frames = read_ahead(_CountingManifest(10), range(10), slow)
    next(frames)
    deadline = time.monotonic() + 5.0
    while 1 not in started and time.monotonic() < deadline:
        time.sleep(0.005)
    assert 1 in started and 1 not in finished  # frame 1 in progress on the reader thread
    frames.close()
    assert 1 in finished and started == finished


def test_fusion_in_the_tracking_pass_equals_the_two_stages(small_manifest, tmp_path):
    """`atlas-gs build` fuses each frame as the tracker reads it: the same fused bytes and the
    same keyframes as fusion, then SLAM, each reading the frames."""
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.mapping.mapper import fuse_and_select_keyframes, select_keyframes_stage

    cfg = load_profile("default").with_overrides({"mapping.pose_source": "estimated"})
    fused, kf = fuse_and_select_keyframes(small_manifest, cfg)
    ref_fused = fuse_frames(small_manifest, cfg.fusion)
    ref_kf = select_keyframes_stage(small_manifest, ref_fused, cfg)
    for a, b in zip(sorted(fused.save(tmp_path / "one")), sorted(ref_fused.save(tmp_path / "two"))):
        assert a.name == b.name and a.read_bytes() == b.read_bytes(), a.name
    np.testing.assert_array_equal(kf.indices, ref_kf.indices)
    np.testing.assert_array_equal(kf.T_world_cam, ref_kf.T_world_cam)
    np.testing.assert_array_equal(kf.valid, ref_kf.valid)
    assert kf.pose_source == "estimated" and kf.maps == ref_kf.maps


def test_frame_fuser_takes_frames_in_order_and_cleans_up_on_failure(small_manifest):
    from atlas_pipeline.perception.rgbd import FrameFuser

    rgb, depth = small_manifest.read_rgb(0), small_manifest.read_depth_m(0)
    with pytest.raises(ValueError, match="frame 1 given where frame 0 was due"):
        with FrameFuser(small_manifest, FusionConfig()) as fuser:
            spool = fuser._spool.dir
            fuser.add(1, rgb, depth)
    assert not spool.exists()  # the temporary chunks of a failed pass go
    with FrameFuser(small_manifest, FusionConfig()) as fuser:
        spool = fuser._spool.dir
        fuser.add(0, rgb, depth)
        with pytest.raises(ValueError, match=f"1 of {small_manifest.n_frames} frames given"):
            fuser.finish()
    assert not spool.exists()  # a refused finish hands nothing over: the chunks go with the block
    with FrameFuser(small_manifest, FusionConfig()) as fuser:
        for i in range(small_manifest.n_frames):
            fuser.add(i, small_manifest.read_rgb(i), small_manifest.read_depth_m(i))
        fused = fuser.finish()
    assert fused.chunk_dir.exists()  # handed over: the artifact owns it now
    fused.frame(0)
