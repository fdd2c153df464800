"""A world knows what it holds: the anchor only for its own recording (by content, never by name),
identity facts (map id, count) from its checksummed Gaussians, an imported world localized in, a
recording's camera against the world's, and a start pose far from the world refused."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from assets.cli import main
from atlas_pipeline.config import load_profile
from atlas_pipeline.errors import BundleFormatError, ConfigError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.geometry import tq_from_pose
from atlas_pipeline.localization.localizer import OUTCOME_COMPLETE, OUTCOME_STOPPED_WORLD_MISMATCH, LocalizationReport
from atlas_pipeline.localization.sequence import STATUS_ANCHOR, STATUS_LOST
from atlas_pipeline.scene_memory.bundle import load_world_bundle, map_id_of, read_lineage, write_world_bundle
from atlas_pipeline.scene_memory.localize import camera_difference, check_camera, check_start_pose, tracking_voxel_m
from atlas_pipeline.scene_memory.metadata import start_pose, world_recording
from atlas_pipeline.sensors.camera import TUM_CAMERAS
from atlas_pipeline.sensors.tum import load_tum_sequence

from tests.conftest import tum_folder

TEDDY = "tum_fr3_teddy_100"
# Two stretches of the teddy recording: the world is mapped from A; B is another stretch of the
# same room (the camera has moved on), which a copy under A's folder name must not pass for.
FRAMES_A = (4, 16)  # teddy's ground truth starts at its frame 4
FRAMES_B = (22, 34)
MAX_PLACED_ERROR_M = 0.05  # a frame placed where it is (the world shares the ground truth's frame)


def _json_out(capsys) -> dict:
    return json.loads(capsys.readouterr().out)


# ---- the anchor: the world's own recording, by content -----------------------------------------

ANCHOR = {"frame_index": 3, "T_world_cam": np.eye(4).tolist()}
BUILT = {"dataset": {"name": "a", "content_hash": "hA"}, "anchor": ANCHOR, "lineage": {"parent": None}}
IMPORTED = {"dataset": None, "gaussians": {"voxel_size_m": 0.02, "pose_source": "imported"}}
EXTENDED_OLD = {**BUILT, "lineage": {"parent": {"path": "/w/parent"}}}  # its anchor names no recording
EXTENDED = {**BUILT, "anchor": {**ANCHOR, "content_hash": "hA"}, "lineage": {"parent": {"path": "/w/parent"}},
            "recordings": [{"name": "p", "root": "/p", "content_hash": "hP"},
                           {"name": "a", "root": "/a", "content_hash": "hA"}]}


@pytest.mark.parametrize("meta, name, content_hash, anchored, says", [
    (BUILT, "a", "hA", True, None),  # the world's own recording
    (BUILT, "a-copy", "hA", True, None),  # the same frames under another name: content decides
    (BUILT, "a", "hB", False, "has the name of the recording this world was built from, but not its frames"),
    (BUILT, "b", "hB", False, None),  # another recording: relocalized, said at INFO
    (BUILT, "a", "", False, "content hash unknown"),  # nothing to prove it with
    ({**BUILT, "anchor": None}, "a", "hA", False, None),
    ({"dataset": {"name": "a", "content_hash": None}, "anchor": ANCHOR}, "a", "hA", False, "not its frames"),
    (IMPORTED, "a", "hA", False, "this world has no recording (imported from a PLY?)"),
    (EXTENDED_OLD, "a", "hA", False, None),  # whose frame the anchor is cannot be proved
    (EXTENDED, "a", "hA", True, None),
    (EXTENDED, "p", "hP", False, None),  # one of its recordings, but not the one the anchor is in
])
def test_the_anchor_is_only_for_the_recording_it_is_in_by_content(caplog, meta, name, content_hash, anchored, says):
    with caplog.at_level(logging.INFO, logger="atlas_pipeline"):
        T, frame = start_pose(meta, name, content_hash=content_hash)
    if anchored:
        assert frame == 3 and np.array_equal(T, np.eye(4))
    else:
        assert (T, frame) == (None, 0)
        assert len(caplog.records) == 1 and name in caplog.text  # one line says why
    if says:
        assert says in caplog.text and caplog.records[0].levelno == logging.WARNING


@pytest.mark.parametrize("meta", [BUILT, IMPORTED, EXTENDED])
def test_a_given_start_pose_or_relocalize_wins_in_every_world(meta):
    T0 = np.diag([1.0, -1.0, -1.0, 1.0])
    T, frame = start_pose(meta, "a", T0, content_hash="hA")
    assert frame == 0 and T is T0
    assert start_pose(meta, "a", relocalize=True, content_hash="hA") == (None, 0)


@pytest.mark.parametrize("meta, content_hash, own", [
    (BUILT, "hA", True), (BUILT, "hB", False), (BUILT, "", False), (IMPORTED, "hA", False),
    (EXTENDED, "hP", True), ({"dataset": {"name": "a"}, "recordings": None}, "hA", False),
    ({"dataset": {"name": "a"}, "recordings": [None, "x", {"content_hash": "hA"}]}, "hA", True),
])
def test_world_recording_matches_by_content_and_tolerates_missing_or_null_keys(meta, content_hash, own):
    assert (world_recording(meta, content_hash) is not None) == own


@pytest.mark.parametrize("anchor, field", [({"frame_index": 0, "T_world_cam": np.eye(3).tolist()}, "anchor.T_world_cam"),
                                           ({"frame_index": 0, "T_world_cam": "x"}, "anchor.T_world_cam"),
                                           ({"frame_index": -1, "T_world_cam": np.eye(4).tolist()}, "anchor.frame_index"),
                                           ({"frame_index": "0", "T_world_cam": np.eye(4).tolist()}, "anchor.frame_index")])
def test_a_malformed_anchor_names_the_field(anchor, field):
    with pytest.raises(BundleFormatError, match=f"metadata.json: field {field}"):
        start_pose({**BUILT, "anchor": anchor}, "a", content_hash="hA")


# ---- identity facts from the checksummed Gaussians ---------------------------------------------

def _field(n: int = 50, seed: int = 0) -> GaussianField:
    """A small random field within the unit cube."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return GaussianField(rng.uniform(0, 1, (n, 3)), np.full((n, 3), 0.02), q / np.linalg.norm(q, axis=1, keepdims=True),
                         rng.integers(0, 256, (n, 3)), np.full(n, 0.9), np.arange(n, dtype=np.uint64) + 1)


@pytest.fixture
def small_bundle(tmp_path) -> Path:
    return write_world_bundle(tmp_path / "w", _field(), {"name": "w", "dataset": None})


def _edit(bundle: Path, **fields) -> None:
    path = bundle / "metadata.json"
    meta = json.loads(path.read_text())
    meta.update(fields)
    path.write_text(json.dumps(meta))


def test_a_bundle_states_the_identity_of_its_gaussians(small_bundle):
    b = load_world_bundle(small_bundle)
    assert b.map_id == map_id_of(_field()) == b.metadata["map_id"] and b.n_gaussians == 50
    assert load_world_bundle(small_bundle, source="ply").map_id == b.map_id  # the PLY holds the same world
    lin = read_lineage(small_bundle, verify=True)
    assert (lin["map_id"], lin["n_gaussians"]) == (b.map_id, 50)


@pytest.mark.parametrize("edit, field", [({"n_gaussians": 5}, "n_gaussians"), ({"map_id": "0123456789abcdef"}, "map_id"),
                                         ({"map_id": ""}, "map_id"), ({"n_gaussians": 51}, "n_gaussians")])
def test_edited_identity_facts_in_metadata_are_refused_naming_the_field(isolated, small_bundle, capsys, edit, field):
    _edit(small_bundle, **edit)
    for source in ("bin", "ply"):
        with pytest.raises(BundleFormatError, match=rf"metadata.json: field {field} is .* \(checksum verified\)"):
            load_world_bundle(small_bundle, source=source)
    with pytest.raises(BundleFormatError, match=f"field {field}"):
        read_lineage(small_bundle, verify=True)
    assert main(["lineage", str(small_bundle)]) == 2
    err = capsys.readouterr().err
    assert "metadata.json" in err and f"field {field}" in err and "Traceback" not in err


@pytest.mark.parametrize("gaussians", [None, {"voxel_size_m": None}, {}])
def test_null_sections_fall_back_to_the_profiles_voxel(small_bundle, gaussians):
    _edit(small_bundle, gaussians=gaussians)
    b = load_world_bundle(small_bundle)
    cfg = load_profile("default")
    assert tracking_voxel_m(b, cfg) == cfg.mapping.voxel_size_m
    assert b.tracking_model().fixed  # the imported-world path (surfels from the Gaussian centres) reads it too


# ---- a recording's camera against the world's --------------------------------------------------

F1, F2, F3, DEFAULT = (TUM_CAMERAS[k] for k in ("freiburg1", "freiburg2", "freiburg3", "default"))


@pytest.mark.parametrize("world, recording, differs", [
    (F3, F3, None),
    (F1, F1, None),
    (F3, F1, "fx 517.306 vs 535.4"),
    (F1, F2, "cx 325.141 vs 318.643"),
    (F3, DEFAULT, "fx 525 vs 535.4"),
    (F3, F3.scaled(0.5), "image size 320x240 vs 640x480"),
    (F3, type(F3)(640, 480, 535.4 * 1.003, 539.2, 320.1 + 1.5, 247.6, 5000.0, ()), None),  # a recalibration
    (F3, type(F3)(640, 480, 535.4, 539.2, 320.1, 247.6, 1000.0, ()), "depth scale 1000 vs 5000"),
    (F3, type(F3)(640, 480, 535.4, 539.2, 320.1, 247.6, 5000.0, (0.2, 0.0, 0.0, 0.0, 0.0)), "lens distortion"),
])
def test_camera_difference(world, recording, differs):
    got = camera_difference(world, recording)
    assert got is None if differs is None else differs in got


def test_another_camera_is_a_warning_naming_both(caplog):
    meta = {"dataset": {"name": "a", "camera": F1.to_dict()}}
    with caplog.at_level(logging.WARNING):
        note = check_camera(meta, "teddy", F3)
    assert note is not None and note in caplog.text
    assert "'teddy' is read with camera freiburg3 (fx 535.4" in note and "recorded with freiburg1 (fx 517.306" in note
    assert check_camera(meta, "teddy", F1) is None and check_camera(IMPORTED, "teddy", F3) is None


@pytest.mark.parametrize("camera", [{"fx": 1}, "freiburg1", {**F3.to_dict(), "cx": 900.0}])
def test_a_worlds_unusable_camera_is_a_warning_and_no_comparison(caplog, camera):
    """A stored camera that is none (fields missing, not an object, principal point outside the
    image): the comparison only ever warns, so it is skipped with a warning naming the field."""
    with caplog.at_level(logging.WARNING):
        assert check_camera({"dataset": {"name": "a", "camera": camera}}, "teddy", F3) is None
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lines) == 1 and lines[0].startswith("metadata.json: field dataset.camera is not a usable camera"), lines


# ---- a start pose far from the world -----------------------------------------------------------

def _pose(x: float, y: float = 0.5, z: float = 0.5) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


@pytest.mark.parametrize("x, refused", [(0.5, False), (-3.0, False), (1.0 + 3.9, False), (1.0 + 4.1, True),
                                        (1e9, True), (-1e9, True)])
def test_a_start_pose_farther_than_the_depth_range_from_the_world_is_refused(x, refused):
    field = _field()  # Gaussians within the unit cube
    margin_m = 4.0
    if not refused:
        check_start_pose(_pose(x), field, margin_m)
        return
    with pytest.raises(ConfigError, match=r"--start-pose: the camera centre .* m from the world .*\(fusion.max_depth_m\)"):
        check_start_pose(_pose(x), field, margin_m)


# ---- the camera in localization.json -----------------------------------------------------------

@pytest.mark.parametrize("camera", [F3.to_dict(), None])
def test_the_reports_camera_is_saved_and_old_reports_still_load(tmp_path, camera):
    n = 3
    nan = np.full(n, np.nan)
    rep = LocalizationReport("a", "m", np.arange(n, dtype=float), np.tile(np.eye(4), (n, 1, 1)), ["tracked"] * n,
                             nan, nan, nan, np.full((n, 4, 4), np.nan), nan, nan, {"outcome": OUTCOME_COMPLETE},
                             camera=camera)
    rep.save(tmp_path)
    data = json.loads((tmp_path / "localization.json").read_text())
    assert ("camera" in data) == (camera is not None)  # a report without one reads as before
    assert LocalizationReport.load(tmp_path).camera == camera


# ---- on real frames ----------------------------------------------------------------------------

def _trim(src: Path, dst: Path, frames: tuple[int, int]) -> Path:
    """A TUM folder holding frames ``frames[0] .. frames[1] - 1`` of ``src`` (images copied)."""
    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()
    for name in ("rgb.txt", "depth.txt"):
        lines = (src / name).read_text().splitlines()
        rows = [ln for ln in lines if ln.strip() and not ln.startswith("#")][frames[0]:frames[1]]
        (dst / name).write_text("\n".join([ln for ln in lines if ln.startswith("#")] + rows) + "\n")
        for row in rows:
            shutil.copy2(src / row.split()[1], dst / row.split()[1])
    shutil.copy2(src / "groundtruth.txt", dst / "groundtruth.txt")
    return dst


@pytest.fixture(scope="module")
def teddy_world(tmp_path_factory):
    """World ``wA`` built from teddy's frames A (folder ``A``, named ``a``), and B's frames in a
    folder also named ``A``: ``(root, world, A, other_A)``."""
    from atlas_pipeline.scene_memory.build import build_world_bundle
    from atlas_pipeline.sensors.registry import dataset_from_spec

    src = tum_folder(TEDDY)
    root = tmp_path_factory.mktemp("identity")
    a = _trim(src, root / "A", FRAMES_A)
    other = _trim(src, root / "other" / "A", FRAMES_B)
    world = root / "wA"
    build_world_bundle(dataset_from_spec(str(a), "freiburg3"), load_profile("default"), world)
    return root, world, a, other


def _localize(capsys, world: Path, recording: Path, *options: str) -> tuple[int, dict, str]:
    code = main(["localize", "--world", str(world), "--input", str(recording), "--camera", "freiburg3", *options])
    captured = capsys.readouterr()
    return code, json.loads(captured.out) if captured.out.strip() else {}, captured.err


@pytest.mark.slow
@pytest.mark.parametrize("case", ["own", "copy under another name", "other frames under the same name"])
def test_a_recording_gets_the_worlds_anchor_only_when_its_frames_are_the_worlds(isolated, teddy_world, capsys, case):
    root, world_a, a, other = teddy_world
    world = isolated / "w"
    shutil.copytree(world_a, world)
    recording = {"own": a, "copy under another name": root / "a-copy",
                 "other frames under the same name": other}[case]
    if case == "copy under another name" and not recording.exists():
        shutil.copytree(a, recording)
    anchor = json.loads((world / "metadata.json").read_text())["anchor"]
    code, summary, err = _localize(capsys, world, recording)
    assert code == 0 and summary["outcome"] == OUTCOME_COMPLETE
    rep = LocalizationReport.load(world)
    anchored = case != "other frames under the same name"
    assert (rep.status[anchor["frame_index"]] == STATUS_ANCHOR) == anchored
    assert summary["start"] == ("given" if anchored else "relocalized")
    i = anchor["frame_index"]
    gt = load_tum_sequence(recording, TUM_CAMERAS["freiburg3"], "a").T_world_cam_gt  # the bundle keeps none
    if not anchored:
        assert "'a' has the name of the recording this world was built from, but not its frames" in err
        # Where A's anchor would have put this frame is not where it was: the test can tell them apart.
        assert np.linalg.norm(gt[i][:3, 3] - np.asarray(anchor["T_world_cam"])[:3, 3]) > \
            2 * MAX_PLACED_ERROR_M
    assert np.linalg.norm(rep.T_world_cam[i][:3, 3] - gt[i][:3, 3]) < MAX_PLACED_ERROR_M
    # Every frame where it is (the world was mapped from ground truth, so errors are absolute).
    assert summary["n_tracked"] + summary["n_relocalized"] >= len(rep.status) - 1
    assert summary["rmse_t_unaligned_m"] < MAX_PLACED_ERROR_M


@pytest.mark.slow
@pytest.mark.parametrize("how", ["--relocalize", "--start-pose", "neither"])
def test_an_imported_world_is_localized_in(isolated, teddy_world, capsys, how):
    _, world_a, a, _ = teddy_world
    imported = isolated / "imp"
    assert main(["import-ply", str(world_a / "gaussians.ply"), "--output", str(imported)]) == 0
    capsys.readouterr()
    options = {"--relocalize": ["--relocalize"], "neither": []}.get(how)
    if options is None:
        gt = load_tum_sequence(a, TUM_CAMERAS["freiburg3"], "a").T_world_cam_gt[0]
        assert np.isfinite(gt).all()  # FRAMES_A starts where the ground truth does
        t, q = tq_from_pose(gt)
        options = ["--start-pose", " ".join(f"{v:.6f}" for v in (*t, *q))]
    code, summary, err = _localize(capsys, imported, a, *options)
    assert code == 0 and summary["outcome"] == OUTCOME_COMPLETE, err
    assert summary["start"] == ("given" if how == "--start-pose" else "relocalized")
    assert ("this world has no recording (imported from a PLY?)" in err) == (how == "neither")
    assert summary["n_tracked"] + summary["n_relocalized"] >= FRAMES_A[1] - FRAMES_A[0] - 1
    assert summary["rmse_t_unaligned_m"] < MAX_PLACED_ERROR_M
    assert json.loads((imported / "localization.json").read_text())["camera"]["fx"] == TUM_CAMERAS["freiburg3"].fx


@pytest.mark.slow
@pytest.mark.parametrize("camera, warned", [("freiburg3", False), ("freiburg1", True)])
def test_the_camera_a_world_is_localized_with_is_recorded_and_another_is_named(isolated, teddy_world, capsys,
                                                                               camera, warned):
    _, world_a, a, _ = teddy_world
    world = isolated / "w"
    shutil.copytree(world_a, world)
    code = main(["localize", "--world", str(world), "--input", str(a), "--camera", camera])
    captured = capsys.readouterr()
    assert code in (0, 3)  # another camera may well fail to place the frames; what counts is what is said
    saved = json.loads((world / "localization.json").read_text())
    assert saved["camera"] == TUM_CAMERAS[camera].to_dict()
    said = "'a' is read with camera freiburg1 (fx 517.306"
    assert (said in captured.err) == warned and ("recorded with freiburg3" in captured.err) == warned
    assert ("world_camera_differs" in saved["summary"]) == warned


@pytest.mark.slow
def test_a_start_pose_far_from_the_world_is_refused_and_one_that_places_nothing_exits_3(isolated, teddy_world, capsys):
    _, world_a, a, _ = teddy_world
    world = isolated / "w"
    shutil.copytree(world_a, world)
    before = sorted(p.name for p in world.iterdir())
    code, _, err = _localize(capsys, world, a, "--start-pose", "1e9 0 0 0 0 0 1")
    assert code == 2 and "--start-pose: the camera centre (1e+09, 0, 0) is" in err and "Traceback" not in err
    assert sorted(p.name for p in world.iterdir()) == before  # nothing written
    # Within reach of the world but 2 m from where the recording starts, with relocalization off:
    # tracking from there places no frame, and the run says the world does not hold the frames.
    anchor = np.asarray(json.loads((world / "metadata.json").read_text())["anchor"]["T_world_cam"])
    t, q = tq_from_pose(anchor)
    start = " ".join(f"{v:.6f}" for v in (t[0] + 2.0, t[1], t[2], *q))
    code, summary, err = _localize(capsys, world, a, "--start-pose", start, "--set", "localization.relocalize=false")
    assert code == 3, err
    assert summary["outcome"] == OUTCOME_STOPPED_WORLD_MISMATCH and "none of the" in summary["stopped_reason"]
    rep = LocalizationReport.load(world)
    assert rep.summary["outcome"] == OUTCOME_STOPPED_WORLD_MISMATCH
    assert set(rep.status) <= {STATUS_ANCHOR, STATUS_LOST}


@pytest.mark.slow
@pytest.mark.parametrize("command", ["localize", "log-transitions", "lineage"])
def test_a_real_world_with_an_edited_count_is_refused_by_every_command(isolated, teddy_world, capsys, command):
    _, world_a, a, _ = teddy_world
    world = isolated / "w"
    shutil.copytree(world_a, world)
    _edit(world, n_gaussians=5)
    args = [command, str(world)] if command == "lineage" else \
        [command, "--world", str(world), "--input", str(a), "--camera", "freiburg3"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "metadata.json: field n_gaussians is 5, but gaussians.bin (checksum verified) holds" in err
    assert not (world / "localization.json").exists() and not (world / "transitions.parquet").exists()


@pytest.fixture(scope="module")
def extended_world(teddy_world):
    """``wA`` extended with B's frames (whose folder is also named ``A``): ``(world, A, B)``."""
    from atlas_pipeline.scene_memory.build import build_world_bundle
    from atlas_pipeline.sensors.registry import dataset_from_spec

    root, world_a, a, other = teddy_world
    world = root / "wAB"
    if not world.exists():
        build_world_bundle(dataset_from_spec(str(other), "freiburg3"), load_profile("default"), world, extend=world_a)
    return world, a, other


@pytest.mark.slow
@pytest.mark.parametrize("which", ["parent's recording", "extension's recording"])
def test_in_an_extended_world_every_frame_is_placed_where_it_is(isolated, extended_world, capsys, which):
    """Both recordings carry the name 'a'; the anchor (the extension's first keyframe) may start
    only the extension's own frames, and no frame of either is put at the other's pose."""
    world_ab, a, b = extended_world
    world = isolated / "w"
    shutil.copytree(world_ab, world)
    recording = a if which == "parent's recording" else b
    code, summary, err = _localize(capsys, world, recording)
    assert code == 0 and summary["outcome"] == OUTCOME_COMPLETE, err
    rep = LocalizationReport.load(world)
    if which == "parent's recording":
        assert STATUS_ANCHOR not in rep.status
    gt = load_tum_sequence(recording, TUM_CAMERAS["freiburg3"], "a").T_world_cam_gt
    placed = np.isfinite(rep.T_world_cam).all(axis=(1, 2))
    assert placed.sum() >= len(rep.status) - 1
    errors_m = np.linalg.norm(rep.T_world_cam[placed][:, :3, 3] - gt[placed][:, :3, 3], axis=1)
    assert errors_m.max() < MAX_PLACED_ERROR_M


# ---- identity without loading the world: gaussians.bin read, not loaded -----------------------

def _sh_field(n: int, degree: int, seed: int = 1) -> GaussianField:
    from atlas_pipeline.gaussian_world.field import sh_rest_count

    f = _field(n, seed)
    rng = np.random.default_rng(seed)
    return GaussianField(f.positions, rng.uniform(0.01, 0.1, (n, 3)), f.rotations_xyzw, f.colors, f.opacities, f.ids,
                         rng.normal(size=(n, sh_rest_count(degree), 3)) if degree else None)


@pytest.mark.parametrize("field", [
    GaussianField(np.random.default_rng(0).uniform(0, 1, (37, 3)), np.full((37, 3), 0.02),
                  np.tile([0.0, 0.0, 0.0, 1.0], (37, 1)), np.zeros((37, 3)), np.full(37, 0.5),
                  np.arange(37, dtype=np.uint64) + 9),  # isotropic: ATLASGS1, scales and rotations expanded
    _field(41),  # ATLASGS2
    _sh_field(29, 2),  # ATLASGS2 version 3, with SH coefficients
    GaussianField.empty(),
], ids=["atlasgs1", "atlasgs2", "atlasgs2-sh", "empty"])
def test_the_map_id_read_from_gaussians_bin_is_the_loaded_worlds(tmp_path, monkeypatch, field):
    from atlas_pipeline.scene_memory import bundle as bundle_module
    from atlas_pipeline.scene_memory.binary import read_gaussian_binary, write_gaussian_binary

    path = write_gaussian_binary(field, tmp_path / "gaussians.bin")
    want = (len(field), map_id_of(read_gaussian_binary(path)))
    assert bundle_module.binary_identity(path) == want
    monkeypatch.setattr(bundle_module, "_STREAM_CHUNK_BYTES", 40)  # many chunks, rows split across none
    assert bundle_module.binary_identity(path) == want


def test_a_truncated_gaussians_bin_is_named_by_its_count(tmp_path):
    from atlas_pipeline.scene_memory.binary import write_gaussian_binary
    from atlas_pipeline.scene_memory.bundle import binary_identity

    path = write_gaussian_binary(_field(), tmp_path / "gaussians.bin")
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(BundleFormatError, match=r"gaussians.bin: count 50 needs \d+ bytes, file has"):
        binary_identity(path)


def _no_loading(monkeypatch) -> None:
    """Loading the Gaussians fails: what runs must take the identity from the file's header and bytes."""
    from atlas_pipeline.scene_memory import binary, bundle

    def refuse(*_a, **_k):
        raise AssertionError("the world was loaded")

    for module in (binary, bundle):
        monkeypatch.setattr(module, "read_gaussian_binary", refuse)
    monkeypatch.setattr(bundle, "load_world_bundle", refuse)


def test_lineage_verifies_without_loading_the_world(isolated, small_bundle, capsys, monkeypatch):
    _no_loading(monkeypatch)
    assert main(["lineage", str(small_bundle), "--json"]) == 0
    lin = json.loads(capsys.readouterr().out)
    assert lin["verified"] is True and lin["problems"] == []
    assert (lin["map_id"], lin["n_gaussians"]) == (map_id_of(_field()), 50)


@pytest.mark.parametrize("damaged", ["gaussians.ply", "gaussians.bin", "metadata.json"])
def test_a_damaged_bundles_lineage_is_shown_with_a_warning_naming_the_file(isolated, small_bundle, capsys, damaged):
    meta = json.loads((small_bundle / "metadata.json").read_text())
    if damaged == "metadata.json":
        _edit(small_bundle, map_id="0123456789abcdef")
        says = "metadata.json: field map_id is '0123456789abcdef', but the Gaussians of gaussians.bin"
    else:
        data = bytearray((small_bundle / damaged).read_bytes())
        data[-1] ^= 0xFF
        (small_bundle / damaged).write_bytes(bytes(data))
        says = f"{damaged}: checksum does not match metadata.json"
    assert main(["lineage", str(small_bundle)]) == 2
    captured = capsys.readouterr()
    assert f"bundle      {small_bundle.resolve()}" in captured.out and "verified    NO: 1 problem" in captured.out
    warnings = [ln for ln in captured.err.splitlines() if ln.startswith("warning:")]
    assert len(warnings) == 1 and says in warnings[0] and "Traceback" not in captured.err, captured.err
    assert main(["lineage", str(small_bundle), "--json"]) == 2
    lin = json.loads(capsys.readouterr().out)
    assert lin["verified"] is False and len(lin["problems"]) == 1 and says in lin["problems"][0]
    # the identity shown: the verified Gaussians', else (gaussians.bin damaged) as metadata.json states it
    assert lin["map_id"] == (meta["map_id"] if damaged != "metadata.json" else map_id_of(_field()))
    with pytest.raises(BundleFormatError, match=says.split(":")[0]):
        read_lineage(small_bundle, verify=True)  # strict: the library's default


def test_the_anchor_beyond_the_frames_loaded_is_no_start(caplog):
    with caplog.at_level(logging.INFO, logger="atlas_pipeline"):
        assert start_pose(BUILT, "a", content_hash="hA", n_frames=3) == (None, 0)  # anchor: frame 3
    assert "beyond the 3 frames loaded (dataset.max_frames)" in caplog.text
    assert start_pose(BUILT, "a", content_hash="hA", n_frames=4)[1] == 3


# ---- one recording read to another frame count (dataset.max_frames) -----------------------------

XYZ = "tum_fr1_xyz_10"  # 9 RGB-D frames (one RGB frame has no depth within 20 ms)
XYZ_FAST = ["--camera", "freiburg1", "--set", "mapping.fit.epochs=0", "--set", "mapping.colour_refinement.iterations=0"]
FEWER_FRAMES = 5


@pytest.fixture(scope="module")
def xyz_worlds(tmp_path_factory):
    """xyz (folder ``xyz``, named ``xyz``), worlds built from all its frames and from its first 6,
    and teddy's first 10 frames in a folder also named ``xyz``: ``{xyz, w_all, w_6, other}``."""
    src = tum_folder(XYZ)
    root = tmp_path_factory.mktemp("max_frames")
    with pytest.MonkeyPatch.context() as mp:
        from tests.conftest import isolate_project

        isolate_project(root, mp)
        xyz = root / "xyz"
        shutil.copytree(src, xyz)
        other = _trim(tum_folder(TEDDY), root / "other" / "xyz", (0, 10))
        assert main(["build", "--input", str(xyz), "--output", str(root / "w_all"), *XYZ_FAST]) == 0
        assert main(["build", "--input", str(xyz), "--output", str(root / "w_6"), *XYZ_FAST,
                     "--set", "dataset.max_frames=6"]) == 0
    return {"xyz": xyz, "w_all": root / "w_all", "w_6": root / "w_6", "other": other}


def _xyz_localized(isolated, xyz_worlds, capsys, world: str, *options: str) -> tuple[Path, dict, str]:
    copy = isolated / world
    shutil.copytree(xyz_worlds[world], copy)
    capsys.readouterr()
    code = main(["localize", "--world", str(copy), "--input", str(xyz_worlds["xyz"]), *XYZ_FAST, *options])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return copy, json.loads(captured.out), captured.err


@pytest.mark.slow
@pytest.mark.parametrize("world, options", [("w_all", ["--set", f"dataset.max_frames={FEWER_FRAMES}"]),
                                            ("w_6", [])])
def test_the_worlds_recording_read_to_another_frame_count_starts_at_the_anchor(isolated, xyz_worlds, capsys,
                                                                               world, options):
    """Fewer frames than the world was built from, or more: the same recording by content (its
    first frames), so the anchor, no warning, and not stopped as another recording."""
    copy, summary, err = _xyz_localized(isolated, xyz_worlds, capsys, world, *options)
    anchor = json.loads((copy / "metadata.json").read_text())["anchor"]
    assert "has the name of the recording" not in err and summary["start"] == "given"
    rep = LocalizationReport.load(copy)
    assert rep.status[anchor["frame_index"]] == STATUS_ANCHOR and summary["outcome"] == OUTCOME_COMPLETE
    assert np.allclose(rep.T_world_cam[anchor["frame_index"]], np.asarray(anchor["T_world_cam"]), rtol=0, atol=1e-9)
    assert rep.n_frames == (FEWER_FRAMES if options else 9)


@pytest.mark.slow
def test_an_export_with_input_reads_the_first_frames_a_localization_placed(isolated, xyz_worlds, capsys):
    import pycolmap

    copy, summary, _ = _xyz_localized(isolated, xyz_worlds, capsys, "w_all",
                                      "--set", f"dataset.max_frames={FEWER_FRAMES}")
    out = isolated / "export"
    code = main(["export", str(copy), "--format", "colmap", "--input", str(xyz_worlds["xyz"]), "--camera", "freiburg1",
                 "--output", str(out)])
    assert code == 0, capsys.readouterr().err
    rep = LocalizationReport.load(copy)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    poses = {img.name: np.linalg.inv(np.vstack([img.cam_from_world().matrix(), [0, 0, 0, 1]]))
             for img in rec.images.values()}
    assert sorted(poses) == [f"frame_{i:06d}.png" for i in range(FEWER_FRAMES)]
    for i in range(FEWER_FRAMES):  # each image at the pose its own frame was placed at
        assert np.allclose(poses[f"frame_{i:06d}.png"], rep.T_world_cam[i], atol=1e-5)


@pytest.mark.slow
def test_log_transitions_ground_truth_is_the_localized_frames_by_content(isolated, xyz_worlds, capsys, monkeypatch):
    import pyarrow.parquet as pq

    copy, _, _ = _xyz_localized(isolated, xyz_worlds, capsys, "w_all", "--set", f"dataset.max_frames={FEWER_FRAMES}")
    gt_args = ["--set", "transitions.pose_source=ground_truth"]
    # another recording under the name: refused naming --input, nothing written
    code = main(["log-transitions", "--world", str(copy), "--input", str(xyz_worlds["other"]), *XYZ_FAST, *gt_args])
    err = capsys.readouterr().err
    assert code == 2 and f"--input 'xyz' ({xyz_worlds['other']}) holds other frames than" in err, err
    assert "dataset.max_frames=5 would" in err and "Traceback" not in err
    assert not (copy / "transitions.parquet").exists()
    # the same recording read whole, or to fewer frames: the report's first frames, by content
    gt = load_tum_sequence(xyz_worlds["xyz"], TUM_CAMERAS["freiburg1"], "xyz").T_world_cam_gt[:FEWER_FRAMES]
    _no_loading(monkeypatch)  # the count comes from gaussians.bin's header
    for options in ([], ["--set", "dataset.max_frames=3"]):
        code = main(["log-transitions", "--world", str(copy), "--input", str(xyz_worlds["xyz"]), *XYZ_FAST, *gt_args,
                     *options])
        assert code == 0, capsys.readouterr().err
        table = pq.read_table(copy / "transitions.parquet").to_pydict()
        assert len(table["step"]) == FEWER_FRAMES - 1
        assert np.allclose(table["before_x_m"], gt[:-1, 0, 3]) and np.allclose(table["after_x_m"], gt[1:, 0, 3])
        assert set(table["n_gaussians"]) == {json.loads((copy / "metadata.json").read_text())["n_gaussians"]}
