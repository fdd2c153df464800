"""A world bundle's stored place index (``places.npz``): written by both routes, read back exactly,
used by a later session only when it was made for that session's map, keyframes and camera, and
refused with the file and member named when malformed."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from assets.cli import main
from atlas_pipeline.config import load_profile
from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.localization.localizer import localize_sequence
from atlas_pipeline.localization.places import PLACES_FILE, PlaceIndex, descriptor_level, map_key
from atlas_pipeline.localization.tracker import SurfelModel, pyramid_levels
from atlas_pipeline.safe_arrays import save_npz_deterministic
from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses, load_world_bundle

FAST = ["--set", "mapping.fit.epochs=0", "--set", "mapping.colour_refinement.iterations=0"]


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A project holding ``synth-small`` (environment pointed at it for the module's tests)."""
    from conftest import isolate_project

    with pytest.MonkeyPatch.context() as mp:
        yield isolate_project(tmp_path_factory.mktemp("places"), mp)


@pytest.fixture(scope="module")
def built(project):
    """A bundle built by the CLI from the small synthetic recording."""
    world = project / "world"
    assert main(["build", "--input", "synth-small", "--output", str(world), *FAST]) == 0
    return world


def _session(world):
    from atlas_pipeline.sensors.registry import load_dataset, load_registry

    cfg = load_profile()
    bundle = load_world_bundle(world)
    manifest = load_dataset(load_registry()["synth-small"], cfg)
    return cfg, bundle, manifest, bundle.tracking_model(), bundle_keyframe_poses(bundle.metadata)


def test_a_built_bundle_stores_the_index_a_session_would_build(built):
    cfg, bundle, manifest, model, poses = _session(built)
    assert PLACES_FILE in bundle.metadata["files"]  # listed, so checksum-verified like every file
    stored = bundle.stored_places(manifest.camera)
    level = descriptor_level(manifest.camera.width, pyramid_levels(cfg.localization))
    assert stored.key == map_key(model, poses, manifest.camera, level)
    fresh = PlaceIndex(manifest.camera, level)
    for k, T in enumerate(poses):
        fresh.add_keyframe(model, T, k)
    assert len(stored) == len(fresh) > 0
    np.testing.assert_array_equal(np.stack(stored._codes), np.stack(fresh._codes))
    np.testing.assert_array_equal(np.stack(stored._poses), np.stack(fresh._poses))
    assert stored._keyframe == fresh._keyframe
    # the same hypotheses for a frame of the recording
    depth = manifest.read_depth_m(5)[:: 2 ** level, :: 2 ** level]
    assert stored.query(depth, 3) and [m.keyframe for m in stored.query(depth, 3)] == \
        [m.keyframe for m in fresh.query(depth, 3)]


def test_a_verified_bundle_hashes_each_part_once(built, tmp_path, monkeypatch):
    """Loading checks every checksum; the tracking map and the place index read after it are not
    hashed again, but a file whose size changed since is still refused, named."""
    import shutil

    import atlas_pipeline.scene_memory.bundle as bundle_mod

    camera = _session(built)[2].camera
    world = shutil.copytree(built, tmp_path / "world")
    hashed: list[str] = []
    real = bundle_mod.sha256_file
    monkeypatch.setattr(bundle_mod, "sha256_file", lambda path: hashed.append(path.name) or real(path))
    bundle = load_world_bundle(world)
    bundle.tracking_model()
    assert bundle.stored_places(camera) is not None
    assert sorted(hashed) == sorted(bundle.metadata["files"])  # each listed file exactly once
    hashed.clear()
    load_world_bundle(world, verify=False).tracking_model()
    assert hashed == ["surfels.npz"]  # not verified at load: checked where it is read
    with open(world / PLACES_FILE, "ab") as f:
        f.write(b"\0")
    with pytest.raises(BundleFormatError, match=PLACES_FILE):
        bundle.stored_places(camera)


def test_a_session_with_no_start_pose_uses_the_stored_index_and_places_the_same(built, monkeypatch):
    cfg, bundle, manifest, model, poses = _session(built)
    rendered: list[int] = []
    original = PlaceIndex.add_keyframe

    def counting(self, *args, **kwargs):
        rendered.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(PlaceIndex, "add_keyframe", counting)
    run = dict(manifest=manifest, cfg=cfg.localization, T_world_cam_start=None, anchor_index=0,
               depth_range_m=(cfg.fusion.min_depth_m, cfg.fusion.max_depth_m), prior_poses=poses,
               stop_on_mismatch=False)
    stored = localize_sequence(model=model, places=bundle.stored_places(manifest.camera), **run)
    assert rendered == []  # nothing indexed again: the first frame was relocalized with the stored index
    assert stored.summary["n_relocalized"] >= 1
    built_here = localize_sequence(model=bundle.tracking_model(), **run)
    assert len(rendered) == len(poses)  # the same session without it renders every keyframe's views
    np.testing.assert_array_equal(stored.T_world_cam, built_here.T_world_cam)
    assert stored.status == built_here.status


def test_an_index_made_for_another_camera_is_not_used(built, monkeypatch, caplog):
    cfg, bundle, manifest, model, poses = _session(built)
    other = dataclasses.replace(manifest.camera, fx=manifest.camera.fx * 1.1)
    stored = bundle.stored_places(manifest.camera)
    from atlas_pipeline.localization.sequence import SequenceTracker

    st = SequenceTracker(other, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m), model=model,
                         prior_poses=poses, places=stored)
    with caplog.at_level(logging.INFO, logger="atlas_pipeline.localization.places"):
        index = st.places
    assert index is not stored and len(index) > 0
    assert "stored place index is of another map, camera or layout" in caplog.text
    # nor for a map that has changed since (the key covers the surfels and the viewpoints)
    moved = SurfelModel(model.centres + 0.01, model.normals, model.radius_m)
    assert map_key(moved, poses, manifest.camera, stored.level) != stored.key
    assert map_key(model, poses[:-1], manifest.camera, stored.level) != stored.key


@pytest.mark.slow
def test_both_routes_store_the_same_index(isolated):
    """The Dagster graph's world bundle holds a byte-identical places.npz for the same recording
    (mapped from tracked poses, which both routes give bit for bit: tests/test_one_path.py)."""
    settings = [*FAST, "--set", "mapping.pose_source=estimated"]
    assert main(["build", "--input", "synth-small", "--output", str(isolated / "world"), *settings]) == 0
    assert main(["run", "synth-small", *settings]) == 0
    graph = isolated / "artifacts" / "world_bundle" / "synth-small"
    assert (graph / PLACES_FILE).read_bytes() == (isolated / "world" / PLACES_FILE).read_bytes()


@pytest.mark.parametrize("member, value, message", [
    ("codes", np.zeros((3, 5), np.float32), "codes"),
    ("codes", np.full((3, 192), np.inf, np.float32), "codes"),
    ("T_world_cam", np.full((3, 4, 4), np.nan), "T_world_cam"),
    ("T_world_cam", np.tile(np.eye(4), (2, 1, 1)), "T_world_cam"),
    ("T_world_cam", np.tile(2 * np.eye(4), (3, 1, 1)), "T_world_cam"),
    ("keyframe", np.array([0, -1, 2], np.int32), "keyframe"),
    ("keyframe", np.array([0, 1], np.int32), "keyframe"),
    ("level", np.int64(-1), "level"),
    ("level", np.int64(40), "level"),
    ("key", np.zeros(5, np.uint8), "key"),
])
def test_a_malformed_index_is_refused_naming_file_and_member(tmp_path, member, value, message):
    n_blocks = 12 * 16
    good = dict(codes=np.zeros((3, n_blocks), np.float32), T_world_cam=np.tile(np.eye(4), (3, 1, 1)),
                keyframe=np.arange(3, dtype=np.int32), level=np.int64(2), key=np.zeros(32, np.uint8))
    path = tmp_path / PLACES_FILE
    with open(path, "wb") as fh:
        save_npz_deterministic(fh, **{**good, member: value})
    with pytest.raises(BundleFormatError) as err:
        PlaceIndex.load(path, None)
    assert str(path) in str(err.value) and message in str(err.value)
    good_path = tmp_path / "good.npz"
    with open(good_path, "wb") as fh:
        save_npz_deterministic(fh, **good)
    assert len(PlaceIndex.load(good_path, None)) == 3


def test_a_missing_member_is_named(tmp_path):
    path = tmp_path / PLACES_FILE
    with open(path, "wb") as fh:
        save_npz_deterministic(fh, codes=np.zeros((1, 192), np.float32))
    with pytest.raises(BundleFormatError, match="T_world_cam"):
        PlaceIndex.load(path, None)


def test_extending_a_bundle_starts_from_its_stored_index(built, project, monkeypatch):
    """``build --extend`` (a second session, no start pose) relocalizes its first frame with the
    bundle's index: the map it tracks against is the saved one, so the key matches."""
    from atlas_pipeline.localization.sequence import SequenceTracker

    adopted: list[bool] = []
    original = SequenceTracker._adopt_stored_places

    def recording(self):
        index = original(self)
        adopted.append(index is not None)
        return index

    monkeypatch.setattr(SequenceTracker, "_adopt_stored_places", recording)
    out = project / "extended"
    assert main(["build", "--input", "synth-small", "--output", str(out), "--extend", str(built), *FAST,
                 "--set", "mapping.pose_source=estimated"]) == 0
    assert adopted[:1] == [True]
    assert PLACES_FILE in load_world_bundle(out).metadata["files"]  # the extended world's own index


def test_an_index_grown_by_mapping_loses_its_key(built):
    """A stored index adopted by a mapping session grows with its keyframes: it no longer is what
    its key describes, so handing the same object to another session renders a fresh one."""
    from atlas_pipeline.localization.places import adopt_stored

    cfg, bundle, manifest, model, poses = _session(built)
    stored = bundle.stored_places(manifest.camera)
    n_levels = pyramid_levels(cfg.localization)
    assert adopt_stored(stored, model, poses, manifest.camera, n_levels) is stored
    stored.add_keyframe(model, poses[0], len(poses))
    assert stored.key is None
    assert adopt_stored(stored, model, poses, manifest.camera, n_levels) is None


def test_the_key_covers_the_splat_limits(built, monkeypatch):
    """Retuning how the map is splatted makes an older index another index (rendered again)."""
    import atlas_pipeline.localization.tracker as tracker_module

    cfg, bundle, manifest, model, poses = _session(built)
    stored = bundle.stored_places(manifest.camera)
    assert map_key(model, poses, manifest.camera, stored.level) == stored.key
    tuned = dataclasses.replace(tracker_module.C, splat_max_radius_px=tracker_module.C.splat_max_radius_px + 1)
    monkeypatch.setattr(tracker_module, "C", tuned)
    assert map_key(model, poses, manifest.camera, stored.level) != stored.key


def test_relocalize_uses_the_stored_index(built, monkeypatch):
    """``atlas-gs relocalize``'s frames placed with the bundle's index, as with one rendered then."""
    from atlas_pipeline.localization.relocalize import relocalize_frames

    cfg, bundle, manifest, model, poses = _session(built)
    rendered: list[int] = []
    original = PlaceIndex.add_keyframe
    monkeypatch.setattr(PlaceIndex, "add_keyframe", lambda self, *a: rendered.append(1) or original(self, *a))
    frames = [0, 6, 11]
    stored = list(relocalize_frames(manifest, model, poses, cfg, frames, places=bundle.stored_places(manifest.camera)))
    assert rendered == []
    fresh = list(relocalize_frames(manifest, model, poses, cfg, frames))
    assert len(rendered) == len(poses)
    assert [i for i, _ in stored] == frames and any(r.ok for _, r in stored)
    for (_, a), (_, b) in zip(stored, fresh):
        assert a.ok == b.ok
        np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
