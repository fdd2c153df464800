"""Big worlds: a world of millions of Gaussians saves, loads and renders in stated, bounded memory.

* a 200k-Gaussian world (the benchmark's synthetic room) round-trips exactly through the bundle
  (``gaussians.bin``, ``gaussians.ply``, ``world.npz``);
* the bounded-memory renderer (chunked projection, in-place sort, tile batches) gives the same
  image bit for bit as the one-pass stages the fits use, whatever the batch size, and each new
  stage equals its NumPy reference;
* the render's peak traced (NumPy) allocation stays under ``render.render_peak_bytes``
  (``tracemalloc``: deterministic, unlike wall time or RSS);
* slow: the 2,000,000-Gaussian world through ``benchmarks/bench_big_world.py``'s steps, each in a
  fresh process, every step's peak RSS under its stated bound.
"""

from __future__ import annotations

import importlib.util
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from atlas_pipeline.errors import ArtifactError, BundleFormatError
from atlas_pipeline.gaussian_world import _raster_reference as ref
from atlas_pipeline.gaussian_world import raster, raster_bounded
from atlas_pipeline.gaussian_world.composite import composite_tiles
from atlas_pipeline.gaussian_world.builder import GaussianWorld
from atlas_pipeline.gaussian_world.field import FIELD_BYTES_PER_GAUSSIAN, GaussianField, ids_unique
from atlas_pipeline.gaussian_world.render import render_gaussians, render_peak_bytes
from atlas_pipeline.scene_memory import ply as ply_mod
from atlas_pipeline.scene_memory.binary import read_gaussian_binary, write_gaussian_binary
from atlas_pipeline.scene_memory.bundle import bundle_disk_bytes, load_world_bundle, write_world_bundle
from atlas_pipeline.scene_memory.ply import read_gaussian_ply, write_gaussian_ply

ROOT = Path(__file__).resolve().parents[1]
MID_N = 200_000  # more than one projection chunk, PLY chunk and check chunk; a few seconds
BIG_N = 2_000_000


def _bench():
    spec = importlib.util.spec_from_file_location("bench_big_world", ROOT / "benchmarks" / "bench_big_world.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


B = _bench()


@pytest.fixture(scope="module")
def mid_world() -> GaussianWorld:
    return B.make_world(MID_N)


def _render_args(fld: GaussianField, width: int, height: int, T=None):
    T = B.camera_pose() if T is None else T
    return (fld.positions, fld.scales, fld.rotations_xyzw, fld.colors, fld.opacities, T, B.camera(width, height),
            width, height)


def _one_pass(fld: GaussianField, width: int, height: int, T=None, background=(0, 0, 0)):
    """The image of the one-pass stages (``prepare_splats`` + ``composite_tiles``), as before batching."""
    inp = raster.validate_inputs(*_render_args(fld, width, height, T), background, raster.NEAR_M)
    view = raster.view_from_pose(inp.T_world_cam, inp.K, width, height)
    sp = raster.prepare_splats(inp.positions, inp.scales, inp.rotations_xyzw, inp.colors, inp.opacities, view)
    return composite_tiles(sp, inp.background), sp


def _same(images, res) -> bool:
    return all(np.array_equal(a, b) for a, b in zip(images, (res.rgb, res.depth_m, res.alpha, res.depth_median_m)))


# ---- save and load ------------------------------------------------------------------------------
def test_mid_world_round_trips_exactly(mid_world, tmp_path):
    folder = write_world_bundle(tmp_path / "w", mid_world.field, {"name": "mid"}, extras=(mid_world,))
    disk = bundle_disk_bytes(MID_N, MID_N)
    for name, limit in disk.items():
        assert (folder / name).stat().st_size <= limit, name
    assert (folder / "gaussians.bin").stat().st_size == disk["gaussians.bin"]  # exact for ATLASGS2
    for source in ("bin", "ply"):
        got = load_world_bundle(folder, source=source).field
        assert got.equals(mid_world.field), source
        assert got.nbytes == FIELD_BYTES_PER_GAUSSIAN * MID_N
    world = GaussianWorld.load(folder)
    assert world.field.equals(mid_world.field)
    for k in ("ids", "count", "sum_xyz", "sum_rgb", "sum_sq", "n_keyframes"):
        assert np.array_equal(getattr(world.tracking_voxels, k), getattr(mid_world.tracking_voxels, k)), k
    assert world.map_id == mid_world.map_id


def test_ply_chunks_do_not_change_the_bytes(monkeypatch, tmp_path):
    fld = B.make_field(5_000)
    whole = ply_mod._encode_vertices(fld).tobytes()  # every vertex in one array, as before chunking
    monkeypatch.setattr(ply_mod, "_CHUNK", 777)  # chunk boundaries everywhere
    path = write_gaussian_ply(fld, tmp_path / "g.ply")
    data = path.read_bytes()
    assert data.endswith(whole) and data[: -len(whole)].endswith(b"end_header\n")
    assert read_gaussian_ply(path).equals(fld)
    monkeypatch.setattr(ply_mod, "_CHUNK", 1 << 16)
    assert read_gaussian_ply(path).equals(fld)


def test_unsorted_and_duplicate_ids_are_checked(tmp_path):
    fld = B.make_field(3_000)
    shuffled = fld.subset(np.random.default_rng(0).permutation(len(fld)))
    assert ids_unique(shuffled.ids) and not ids_unique(np.array([5, 3, 9, 3], np.uint64))
    for write, read in ((write_gaussian_binary, read_gaussian_binary), (write_gaussian_ply, read_gaussian_ply)):
        path = write(shuffled, tmp_path / f"s.{write.__name__}")
        assert read(path).equals(shuffled)
        dup = GaussianField(fld.positions, fld.scales, fld.rotations_xyzw, fld.colors, fld.opacities,
                            np.where(np.arange(len(fld)) == 17, fld.ids[1000], fld.ids))
        path = write(dup, tmp_path / f"d.{write.__name__}")
        with pytest.raises(BundleFormatError, match="not unique"):
            read(path)


def test_world_load_refuses_decreasing_voxel_ids(tmp_path):
    world = B.make_world(2_000)
    world.save(tmp_path)
    GaussianWorld.load(tmp_path)  # sorted: fine
    world.tracking_voxels.ids = world.tracking_voxels.ids[::-1].copy()  # a uint64 difference would wrap and pass
    world.save(tmp_path)
    with pytest.raises(ArtifactError, match="strictly increasing"):
        GaussianWorld.load(tmp_path)


# ---- render: batched equals one pass ------------------------------------------------------------
@pytest.mark.parametrize("size", [(640, 480), (1280, 960)])
def test_batched_render_equals_one_pass(mid_world, size):
    w, h = size
    images, sp = _one_pass(mid_world.field, w, h)
    for budget in (None, 20_000, raster.MAX_TILE_PAIRS):
        assert _same(images, render_gaussians(*_render_args(mid_world.field, w, h), max_tile_pairs=budget)), budget
    if w == 640:  # a budget below a single tile's list: one tile per batch, still the same image
        assert _same(images, render_gaussians(*_render_args(mid_world.field, w, h),
                                              max_tile_pairs=int(np.diff(sp.tile_start).max()) - 1))


def test_close_up_with_large_footprints_equals_one_pass(mid_world):
    """Near a wall, footprints span many tiles (P >> M): many batches, same image."""
    T = B.camera_pose().copy()
    T[:3, 3] = [0.0, 3.3, 1.4]  # 0.7 m from the far wall
    fld = mid_world.field
    images, sp = _one_pass(fld, 640, 480, T, background=(10, 20, 30))
    assert len(sp.tile_ids) > 2 * len(sp.order)
    got = render_gaussians(*_render_args(fld, 640, 480, T), background=(10, 20, 30),
                           max_tile_pairs=len(sp.tile_ids) // 7)
    assert _same(images, got)


def test_float64_inputs_and_empty_views_match(mid_world):
    fld = mid_world.field.subset(slice(0, 20_000))
    args = list(_render_args(fld, 320, 240))
    images, _ = _one_pass(fld, 320, 240)
    args[:5] = [a.astype(np.float64) for a in args[:5]]  # converted copies, same image
    assert _same(images, render_gaussians(*args, max_tile_pairs=5_000))
    behind = np.eye(4)  # camera z (forward) along world z: looking up
    behind[:3, 3] = [0.0, 10.0, 1.4]  # outside the room, looking away from it
    res = render_gaussians(*_render_args(fld, 320, 240, behind), background=(7, 8, 9))
    assert (res.rgb == [7, 8, 9]).all() and not res.alpha.any()


# ---- the new stages against their references ----------------------------------------------------
def test_stages_equal_references(mid_world):
    fld = mid_world.field.subset(slice(0, 30_000))
    w, h = 320, 240
    view = raster.view_from_pose(B.camera_pose(), B.camera(w, h), w, h)
    proj = raster.project_gaussians(fld.positions, fld.scales, fld.rotations_xyzw, fld.colors.astype(np.float32),
                                    fld.opacities, view)
    vis = raster_bounded.project_visible(fld.positions, fld.scales, fld.rotations_xyzw, fld.colors, fld.opacities, view,
                                 chunk=4_096)
    valid = np.flatnonzero(proj.valid)
    assert np.array_equal(vis.feat, proj.feat[valid]) and np.array_equal(vis.box, proj.box[valid])
    assert np.array_equal(vis.depth, proj.depth[valid])
    order = raster_bounded.sort_visible(vis)
    feat_r, box_r, depth_r = ref.visible_reference(proj.valid, proj.depth, proj.feat, proj.box)
    assert np.array_equal(vis.feat, feat_r) and np.array_equal(vis.box, box_r) and np.array_equal(vis.depth, depth_r)
    assert np.array_equal(valid[order], raster.sort_by_depth(proj.valid, proj.depth))
    counts = raster_bounded.tile_pair_counts(vis.box, w, h)
    assert np.array_equal(counts, ref.tile_pair_counts_reference(vis.box, w, h))
    bins = raster.bin_tiles(vis.box, w, h)
    batches = raster_bounded.tile_batches(counts, 3_000)
    assert batches[0][0] == 0 and batches[-1][1] == len(counts)
    assert all(a[1] == b[0] for a, b in zip(batches, batches[1:]))
    assert all(counts[t0:t1].sum() <= 3_000 or t1 == t0 + 1 for t0, t1 in batches)
    for t0, t1 in batches:
        tile_start, tile_ids = raster_bounded.bin_tile_batch(vis.box, counts, w, t0, t1)
        ts_r, ti_r = ref.bin_tile_batch_reference(vis.box, w, h, t0, t1)
        assert np.array_equal(tile_start, ts_r) and np.array_equal(tile_ids, ti_r)
        assert np.array_equal(tile_ids, bins.tile_ids[bins.tile_start[t0]:bins.tile_start[t1]])


# ---- memory -------------------------------------------------------------------------------------
def test_render_traced_peak_within_stated_bound(mid_world):
    fld = mid_world.field
    args = _render_args(fld, 640, 480)
    render_gaussians(*[a[:1000] for a in args[:5]], *args[5:])  # compiled (or loaded) outside the trace
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        render_gaussians(*args)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    bound = render_peak_bytes(MID_N, 640, 480)
    # the projection's N-row buffers (64 bytes per Gaussian) are NumPy allocations: the trace sees them
    assert 64 * MID_N <= peak <= bound, (peak, bound)


def test_render_bound_formula():
    # worst case, every Gaussian drawn: 76 bytes per Gaussian plus fixed parts
    extra = render_peak_bytes(2 * BIG_N, 640, 480) - render_peak_bytes(BIG_N, 640, 480)
    assert extra == 76 * BIG_N  # both under the default pair budget
    assert render_peak_bytes(BIG_N, 1280, 960) < 256 << 20


@pytest.mark.slow
def test_two_million_gaussians_save_load_render_within_bounds(tmp_path):
    folder = tmp_path / "world"
    steps = {step: B._subprocess(step, BIG_N, folder) for step in ("save", "load", "render")}
    checks = [steps["save"], steps["load"], steps["render"]["render_640"], steps["render"]["render_1280"]]
    for c in checks:
        assert c["peak_mb"] - c["base_mb"] <= c["bound_mb"], c
    assert steps["save"]["files_ok"]
    assert steps["render"]["render_640"]["covered"] > 0.9
