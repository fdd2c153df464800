"""A bundle knows which recording each keyframe is a frame of, and every consumer reads it there.

On real TUM frames: teddy split into two recordings, the second mapped into the first's world
(``build --extend``); the export pairs every image with its own frame's pose, a recording missing
or replaced by other frames has its keyframes left out (never paired with other frames), the
viewer and the evaluation read each keyframe from its own recording. The metadata reading itself
(older bundles, malformed fields) is tested without frames.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.scene_memory.recordings import (UNKNOWN_RECORDING, bundle_keyframe_sources, join_recordings,
                                                    recording_tag)
from tests.conftest import isolate_project, tum_folder

TEDDY = "tum_fr3_teddy_100"
SPLIT = 40  # recording A: teddy frames 0..39, recording B: 40..79
FAST = ["--camera", "freiburg3", "--set", "mapping.fit.epochs=0", "--set", "mapping.colour_refinement.iterations=0"]
# B's keyframes are tracked into A's world (mapped at A's ground truth): within a few cm of B's
# ground truth; A's keyframes are at their ground truth exactly. Another frame's pose is >= 10 cm off.
POSE_TOLERANCE_M = 0.03


def _split(src: Path, dst: Path, lo: int, hi: int) -> Path:
    """Frames ``lo..hi-1`` of the TUM folder ``src`` as a TUM folder ``dst`` (images copied, lists
    and ground truth trimmed to them)."""
    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()
    times = []
    for name in ("rgb.txt", "depth.txt"):
        lines = (src / name).read_text().splitlines()
        head = [ln for ln in lines if ln.startswith("#")]
        body = [ln for ln in lines if ln and not ln.startswith("#")][lo:hi]
        for ln in body:
            rel = ln.split()[1]
            shutil.copyfile(src / rel, dst / rel)
            times.append(float(ln.split()[0]))
        (dst / name).write_text("\n".join(head + body) + "\n")
    lines = (src / "groundtruth.txt").read_text().splitlines()
    t0, t1 = min(times) - 0.05, max(times) + 0.05
    keep = [ln for ln in lines if ln.startswith("#") or (ln and t0 <= float(ln.split()[0]) <= t1)]
    (dst / "groundtruth.txt").write_text("\n".join(keep) + "\n")
    return dst


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def worlds(tmp_path_factory):
    """``{root, A, B, wA, wB, teddy}``: A and B (B in a folder also named ``A``: a recording is told
    apart by content, not by name), the world of A and that world extended with B."""
    from assets.cli import main
    from atlas_pipeline.sensors.registry import read_dataset_manifest
    from atlas_pipeline.sensors.registry import dataset_from_spec

    src = tum_folder(TEDDY)
    root = tmp_path_factory.mktemp("keyframe_sources")
    with pytest.MonkeyPatch.context() as mp:
        isolate_project(root, mp)
        a = _split(src, root / "A", 0, SPLIT)
        b = _split(src, root / "second" / "A", SPLIT, 2 * SPLIT)
        assert main(["build", "--input", str(a), "--output", str(root / "wA"), *FAST]) == 0
        assert main(["build", "--input", str(b), "--extend", str(root / "wA"), "--output", str(root / "wB"),
                     *FAST]) == 0
        teddy = read_dataset_manifest(dataset_from_spec(str(src), "freiburg3"))
        yield {"root": root, "A": a, "B": b, "wA": root / "wA", "wB": root / "wB", "teddy": teddy, "mp": mp}


def _export(world: Path, out: Path, *argv: str) -> dict:
    from assets.cli import main

    assert main(["export", str(world), "--format", "colmap", "--output", str(out), *argv]) == 0
    return json.loads((out / "export.json").read_text())


def _images_and_poses(out: Path) -> list[tuple[str, np.ndarray]]:
    """``(name, T_world_cam [4, 4])`` of every image of the COLMAP model in ``out``."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    return [(img.name, np.linalg.inv(np.vstack([img.cam_from_world().matrix(), [0, 0, 0, 1]])))
            for img in sorted(rec.images.values(), key=lambda im: im.name)]


def _check_pairs(out: Path, teddy) -> list[int]:
    """Every exported image is a teddy frame (by its bytes) and its pose is that frame's ground
    truth; returns the teddy frame of each image."""
    by_digest = {_digest(teddy.rgb_path(i)): i for i in range(teddy.n_frames)}
    frames = []
    for name, T in _images_and_poses(out):
        t = by_digest[_digest(out / "images" / name)]
        assert teddy.has_gt[t], name
        err = np.linalg.norm(T[:3, 3] - teddy.T_world_cam_gt[t][:3, 3])
        assert err < POSE_TOLERANCE_M, f"{name} is teddy frame {t} but its pose is {err:.3f} m from that frame's"
        frames.append(t)
    return frames


@pytest.mark.slow
def test_extended_bundle_names_each_keyframes_recording_by_content(worlds):
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.sensors.registry import dataset_from_spec, read_dataset_manifest

    meta = json.loads((worlds["wB"] / "metadata.json").read_text())
    hashes = [read_dataset_manifest(dataset_from_spec(str(worlds[k]), "freiburg3")).content_hash for k in "AB"]
    recs = meta["recordings"]
    assert [r["content_hash"] for r in recs] == hashes and [r["name"] for r in recs] == ["a", "a"]
    assert [r["root"] for r in recs] == [str(worlds["A"]), str(worlds["B"])]
    parent = json.loads((worlds["wA"] / "metadata.json").read_text())["keyframes"]
    n_a = len(parent["indices"])
    kf = meta["keyframes"]
    assert kf["indices"][:n_a] == parent["indices"] and kf["recording"] == [0] * n_a + [1] * (len(kf["indices"]) - n_a)
    # the anchor is a frame of the bundle's own recording (B), never A's first keyframe
    assert meta["anchor"]["content_hash"] == hashes[1] and meta["anchor"]["frame_index"] == kf["indices"][n_a]
    # the saved world carries the same record through the next --extend
    w = GaussianWorld.load(worlds["wB"])
    assert w.keyframe_recording.tolist() == kf["recording"] and w.recordings == recs


@pytest.mark.slow
def test_export_of_an_extended_world_pairs_every_image_with_its_own_frame(worlds):
    out = worlds["root"] / "export_ab"
    summary = _export(worlds["wB"], out)
    meta = json.loads((worlds["wB"] / "metadata.json").read_text())
    kf = meta["keyframes"]
    frames = _check_pairs(out, worlds["teddy"])
    # every keyframe is there once, as the teddy frame it is: A's index i is teddy i, B's is teddy 40 + i
    want = sorted(i + SPLIT * j for i, j in zip(kf["indices"], kf["recording"]))
    assert sorted(frames) == want and summary["n_images"] == len(want)
    names = [n for n, _ in _images_and_poses(out)]
    tag = recording_tag(meta["recordings"][0], 0)
    assert len(set(names)) == len(names)
    assert {n for n in names if n.startswith(tag + "_")} == {f"{tag}_frame_{i:06d}.png" for i, j in
                                                             zip(kf["indices"], kf["recording"]) if j == 0}
    assert [r["n_frames"] for r in summary["recordings"]] == [kf["recording"].count(1), kf["recording"].count(0)]


@pytest.mark.slow
def test_a_copy_of_the_worlds_own_recording_gives_no_duplicate_names(worlds):
    from assets.cli import main

    copy = worlds["root"] / "copy" / "A"
    shutil.copytree(worlds["A"], copy)
    w2 = worlds["root"] / "wA2"
    # merged at ground truth, the copy's keyframes are the same frames as the world's own
    assert main(["build", "--input", str(copy), "--extend", str(worlds["wA"]), "--output", str(w2), *FAST,
                 "--set", "mapping.pose_source=ground_truth"]) == 0
    meta = json.loads((w2 / "metadata.json").read_text())
    assert len(meta["recordings"]) == 1 and set(meta["keyframes"]["recording"]) == {0}  # one recording, by content
    assert len(meta["keyframes"]["indices"]) > len(set(meta["keyframes"]["indices"]))
    out = worlds["root"] / "export_copy"
    _export(w2, out)
    names = [n for n, _ in _images_and_poses(out)]
    assert len(names) == len(set(names)) == len(set(meta["keyframes"]["indices"]))
    assert all(n.startswith("frame_") for n in names)
    _check_pairs(out, worlds["teddy"])


@pytest.mark.slow
def test_a_missing_or_replaced_recording_has_its_keyframes_left_out(worlds, caplog):
    a, away = worlds["A"], worlds["root"] / "A.away"
    kf = json.loads((worlds["wB"] / "metadata.json").read_text())["keyframes"]
    n_b = kf["recording"].count(1)
    a.rename(away)
    try:
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            summary = _export(worlds["wB"], worlds["root"] / "export_missing")
        lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(lines) == 1 and f"keyframes of recording 'a'" in lines[0] and str(a) in lines[0], lines
        assert summary["n_images"] == n_b
        _check_pairs(worlds["root"] / "export_missing", worlds["teddy"])
        # other frames where A was (B's, under A's name and folder): told apart by content, left out
        shutil.copytree(worlds["B"], a)
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            summary = _export(worlds["wB"], worlds["root"] / "export_replaced")
        assert "holds other frames" in caplog.text and summary["n_images"] == n_b
        _check_pairs(worlds["root"] / "export_replaced", worlds["teddy"])
        shutil.rmtree(a)
    finally:
        away.rename(a)


@pytest.mark.slow
def test_estimated_export_reads_the_localized_recording_not_the_one_of_its_name(worlds, caplog):
    """B (its folder named as A's) localized in A's world: its placed frames are read from B, the
    recording the report names by content; with B gone, never from A (the world's own recording,
    of B's name), but an error asking for B."""
    from assets.cli import main

    world = worlds["root"] / "wA_loc"
    shutil.copytree(worlds["wA"], world)
    assert main(["localize", "--world", str(world), "--input", str(worlds["B"]), "--camera", "freiburg3"]) in (0, 3)
    out = worlds["root"] / "export_loc"
    summary = _export(world, out)
    assert summary["pose_source"] == "estimated" and summary["n_images"] > 0
    assert min(_check_pairs(out, worlds["teddy"])) >= SPLIT  # B's frames, each at its own pose
    b, away = worlds["B"], worlds["root"] / "B.away"
    b.rename(away)
    try:
        caplog.clear()
        assert main(["export", str(world), "--format", "colmap", "--output", str(worlds["root"] / "x")]) == 2
        assert "the frames of dataset 'a' are not available" in caplog.text and "holds other frames" in caplog.text
        summary = _export(world, worlds["root"] / "export_loc_input", "--input", str(away), "--camera", "freiburg3")
        assert summary["n_images"] > 0 and min(_check_pairs(worlds["root"] / "export_loc_input", worlds["teddy"])) >= SPLIT
    finally:
        away.rename(b)


@pytest.mark.slow
def test_extending_an_older_bundle_takes_its_keyframes_recording_from_its_dataset(worlds):
    """A bundle written before keyframes named their recording (no ``recordings``, no
    ``keyframe_recording`` in world.npz): extended, its keyframes are frames of its dataset."""
    from assets.cli import main
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.io_utils import sha256_file

    old = worlds["root"] / "wA_old"
    shutil.copytree(worlds["wA"], old)
    w = GaussianWorld.load(old)
    w.recordings, w.keyframe_recording = [], None
    w.save(old)
    meta = json.loads((old / "metadata.json").read_text())
    own = meta.pop("recordings")[0]
    del meta["keyframes"]["recording"]
    for name in ("world.npz", "world.json"):  # as that older writer listed them
        meta["files"][name].update(bytes=(old / name).stat().st_size, sha256=sha256_file(old / name))
    (old / "metadata.json").write_text(json.dumps(meta))
    assert GaussianWorld.load(old).keyframe_recording is None
    out = worlds["root"] / "wAB_old"
    assert main(["build", "--input", str(worlds["B"]), "--extend", str(old), "--output", str(out), *FAST,
                 "--set", "mapping.pose_source=ground_truth"]) == 0
    ext = json.loads((out / "metadata.json").read_text())
    n_a = len(meta["keyframes"]["indices"])
    assert ext["recordings"][0] == own and ext["recordings"][1]["root"] == str(worlds["B"])
    assert ext["keyframes"]["recording"] == [0] * n_a + [1] * (len(ext["keyframes"]["indices"]) - n_a)
    export_dir = worlds["root"] / "export_old"
    _export(out, export_dir)
    _check_pairs(export_dir, worlds["teddy"])


@pytest.mark.slow
def test_viewer_and_evaluation_read_each_keyframe_from_its_recording(worlds):
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.scene_memory.recordings import keyframe_indices_of
    from atlas_pipeline.sensors.registry import dataset_from_spec, read_dataset_manifest
    from atlas_pipeline.viz.viewer import _thumbnail, load_viewer_data

    data = load_viewer_data(worlds["wB"])
    kf = json.loads((worlds["wB"] / "metadata.json").read_text())["keyframes"]
    a, b = (read_dataset_manifest(dataset_from_spec(str(worlds[k]), "freiburg3")) for k in "AB")
    assert [m.content_hash for m in data.keyframe_manifests] == [(a, b)[j].content_hash for j in kf["recording"]]
    for k, (i, j) in enumerate(zip(kf["indices"], kf["recording"])):
        if data.keyframe_images[k] is not None:
            assert np.array_equal(data.keyframe_images[k], _thumbnail((a, b)[j].read_rgb(i))), k
    assert sum(img is not None for img in data.keyframe_images) == len(kf["indices"])
    # held-out frames of B are the frames that are no keyframe of B (A's keyframe indices are A's frames)
    world = GaussianWorld.load(worlds["wB"])
    assert keyframe_indices_of(world, b).tolist() == [i for i, j in zip(kf["indices"], kf["recording"]) if j == 1]


# ---- the metadata, without frames ------------------------------------------------------------


def _meta(**extra) -> dict:
    T = np.eye(4).tolist()
    return {"dataset": {"name": "a", "root": "/x/a", "content_hash": "f" * 64, "n_frames": 10, "camera": None},
            "keyframes": {"indices": [2, 5], "T_world_cam": [T, T]}, **extra}


def test_an_older_bundle_reads_every_keyframe_as_a_frame_of_its_dataset():
    ks = bundle_keyframe_sources(_meta())
    assert ks.recordings == [_meta()["dataset"]] and ks.recording.tolist() == [0, 0] and ks.indices.tolist() == [2, 5]
    imported = bundle_keyframe_sources({"dataset": None, "keyframes": {}})
    assert len(imported) == 0 and imported.recordings == []


@pytest.mark.parametrize("extra, field", [
    ({"recordings": [{"name": "a"}], "keyframes": {"indices": [2, 5], "T_world_cam": [np.eye(4).tolist()] * 2,
                                                   "recording": [0, 1]}}, "keyframes.recording"),
    ({"recordings": [{"name": "a"}], "keyframes": {"indices": [2, 5], "T_world_cam": [np.eye(4).tolist()] * 2,
                                                   "recording": [0]}}, "keyframes.recording"),
    ({"recordings": [{"name": "a"}], "keyframes": {"indices": [2, 5], "T_world_cam": [np.eye(4).tolist()] * 2}},
     "keyframes.recording"),
    ({"recordings": [{"name": "a", "content_hash": 7}], "keyframes": {
        "indices": [2], "T_world_cam": [np.eye(4).tolist()], "recording": [0]}}, "recordings[0].content_hash"),
    ({"recordings": {"name": "a"}}, "recordings"),
    ({"keyframes": {"indices": [2, -1], "T_world_cam": [np.eye(4).tolist()] * 2}}, "keyframes.indices"),
])
def test_a_malformed_keyframe_source_names_its_field(extra, field, tmp_path):
    where = tmp_path / "metadata.json"
    with pytest.raises(BundleFormatError, match=r"field " + field.replace("[", r"\[").replace("]", r"\]")) as e:
        bundle_keyframe_sources(_meta(**extra), where)
    assert str(where) in str(e.value)


def test_joining_recordings_tells_them_apart_by_content():
    a = {"name": "a", "root": "/x/a", "content_hash": "1" * 64, "n_frames": 40, "camera": None}
    same_elsewhere = {**a, "root": "/y/a"}
    other_same_name = {**a, "content_hash": "2" * 64}
    recs, idx = join_recordings([], np.zeros(0, np.int64), 0, a, 3)
    recs, idx = join_recordings(recs, idx, 3, same_elsewhere, 2)
    assert recs == [a] and idx.tolist() == [0] * 5
    recs, idx = join_recordings(recs, idx, 5, other_same_name, 1)
    assert recs == [a, other_same_name] and idx.tolist() == [0] * 5 + [1]
    # keyframes whose recording was never recorded stay unknown: never taken for the new one's
    recs, idx = join_recordings([], None, 4, a, 2)
    assert recs == [UNKNOWN_RECORDING, a] and idx.tolist() == [0] * 4 + [1] * 2


# ---- older extended bundles: the parent's keyframes only where proven ---------------------------

def _small_field(n: int = 20, seed: int = 0):
    from atlas_pipeline.gaussian_world.field import GaussianField

    rng = np.random.default_rng(seed)
    return GaussianField(rng.uniform(0, 1, (n, 3)), np.full((n, 3), 0.02), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
                         rng.integers(0, 256, (n, 3)), np.full(n, 0.9), np.arange(n, dtype=np.uint64) + 1)


def _pose_at(x: float) -> list:
    T = np.eye(4)
    T[0, 3] = x
    return T.tolist()


def _rec(name: str, h: str) -> dict:
    return {"name": name, "root": f"/x/{name}", "content_hash": h * 64, "n_frames": 10, "camera": None}


def _older_bundle(path: Path, dataset: dict, indices: list[int], xs: list[float], parent: Path | None,
                  seed: int) -> Path:
    """A bundle as written before keyframes named their recording: no ``recordings``, no
    ``keyframes.recording``; ``lineage.parent`` names ``parent`` as ``build --extend`` did."""
    from atlas_pipeline.scene_memory.bundle import parent_reference, write_world_bundle

    meta = {"name": path.name, "dataset": dataset,
            "keyframes": {"indices": indices, "T_world_cam": [_pose_at(x) for x in xs]},
            "lineage": {"parent": parent_reference(parent) if parent is not None else None}}
    return write_world_bundle(path, _small_field(seed=seed), meta)


@pytest.fixture
def older_chain(tmp_path) -> dict:
    """Three older bundles: ``p`` built from recording a (keyframes 0, 4), ``c`` extended from it
    with b (its keyframes 0, 4 then 1, 6), ``g`` extended from ``c`` with c (then 2)."""
    a, b, c = _rec("a", "1"), _rec("b", "2"), _rec("c", "3")
    p = _older_bundle(tmp_path / "p", a, [0, 4], [0.0, 0.4], None, 0)
    ch = _older_bundle(tmp_path / "c", b, [0, 4, 1, 6], [0.0, 0.4, 1.1, 1.6], p, 1)
    g = _older_bundle(tmp_path / "g", c, [0, 4, 1, 6, 2], [0.0, 0.4, 1.1, 1.6, 2.2], ch, 2)
    return {"p": p, "c": ch, "g": g, "a": a, "b": b, "rc": c}


def _sources(bundle: Path):
    from atlas_pipeline.scene_memory.bundle import read_metadata

    return bundle_keyframe_sources(read_metadata(bundle), bundle / "metadata.json")


def test_an_older_extended_bundle_gives_its_parents_keyframes_to_the_parents_recording(older_chain):
    ks = _sources(older_chain["c"])
    assert ks.recordings == [older_chain["a"], older_chain["b"]] and ks.recording.tolist() == [0, 0, 1, 1]
    assert ks.unknown_reason == ""
    # followed up a lineage of older bundles: each extension's keyframes of its own recording
    ks = _sources(older_chain["g"])
    assert ks.recordings == [older_chain["a"], older_chain["b"], older_chain["rc"]]
    assert ks.recording.tolist() == [0, 0, 1, 1, 2] and ks.indices.tolist() == [0, 4, 1, 6, 2]


def _corrupt(bundle: Path, name: str = "gaussians.ply") -> None:
    with open(bundle / name, "r+b") as f:
        f.seek(-1, 2)
        last = f.read(1)
        f.seek(-1, 2)
        f.write(bytes([last[0] ^ 0xFF]))


def _move(bundle: Path) -> None:
    bundle.rename(bundle.with_name(bundle.name + ".away"))


def _rebuild_other(bundle: Path) -> None:  # another world written where the parent was
    shutil.rmtree(bundle)
    _older_bundle(bundle, _rec("a", "1"), [0, 4], [0.0, 0.4], None, 7)


def _shift_keyframes(bundle: Path) -> None:  # the parent's keyframes edited since (metadata only)
    meta = json.loads((bundle / "metadata.json").read_text())
    meta["keyframes"]["T_world_cam"][1] = _pose_at(0.5)
    (bundle / "metadata.json").write_text(json.dumps(meta))


@pytest.mark.parametrize("damage, says", [
    (_move, "(lineage.parent.path) is not on disk"),
    (_corrupt, "does not verify"),
    (_rebuild_other, "holds another world than the one extended"),
    (_shift_keyframes, "are not the first keyframes of this one"),
])
def test_an_older_extended_bundle_whose_parent_cannot_prove_them_has_unknown_keyframes(older_chain, damage, says):
    from atlas_pipeline.scene_memory.recordings import is_unknown

    damage(older_chain["p"])
    ks = _sources(older_chain["c"])
    # no keyframe given to any recording: how many came from the parent is what cannot be proven
    assert len(ks.recordings) == 1 and is_unknown(ks.recordings[0]) and ks.recording.tolist() == [0] * 4
    assert says in ks.unknown_reason and str(older_chain["c"] / "metadata.json") in ks.unknown_reason
    # and so in every bundle extended from it
    ks = _sources(older_chain["g"])
    assert is_unknown(ks.recordings[0]) and says in ks.unknown_reason


def test_an_older_extended_bundle_whose_lineage_loops_has_unknown_keyframes(older_chain):
    meta = json.loads((older_chain["p"] / "metadata.json").read_text())
    meta["lineage"]["parent"] = {"path": str(older_chain["c"].resolve())}  # p names c, c names p
    (older_chain["p"] / "metadata.json").write_text(json.dumps(meta))
    ks = _sources(older_chain["c"])
    # the parent still proves which keyframes are c's own; its own keyframes' recording is unknown
    assert ks.recordings[1:] == [older_chain["b"]] and ks.recording.tolist() == [0, 0, 1, 1]
    assert ks.recordings[0] == UNKNOWN_RECORDING and "a loop" in ks.unknown_reason


def _as_older(world: Path, dst: Path) -> Path:
    """A copy of the bundle ``world`` as written before keyframes named their recording (no
    ``recordings``, no ``keyframes.recording``, no ``keyframe_recording`` in world.npz)."""
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.io_utils import sha256_file

    shutil.copytree(world, dst)
    w = GaussianWorld.load(dst)
    w.recordings, w.keyframe_recording = [], None
    w.save(dst)
    meta = json.loads((dst / "metadata.json").read_text())
    meta.pop("recordings")
    del meta["keyframes"]["recording"]
    for name in ("world.npz", "world.json"):  # as that older writer listed them
        meta["files"][name].update(bytes=(dst / name).stat().st_size, sha256=sha256_file(dst / name))
    (dst / "metadata.json").write_text(json.dumps(meta))
    return dst


def _third_recording(worlds) -> Path:
    c = worlds["root"] / "C"
    return c if c.exists() else _split(tum_folder(TEDDY), c, 2 * SPLIT, 2 * SPLIT + 20)


@pytest.mark.slow
def test_an_older_extended_bundle_pairs_each_image_with_its_own_frame(worlds):
    """wB (A's world extended with B) as an older writer left it: its parent, wA, proves which
    keyframes are A's; the export and the next --extend read and record each from its own."""
    from assets.cli import main

    old = _as_older(worlds["wB"], worlds["root"] / "wB_older")
    kf = json.loads((worlds["wB"] / "metadata.json").read_text())["keyframes"]
    out = worlds["root"] / "export_older"
    summary = _export(old, out)
    assert sorted(_check_pairs(out, worlds["teddy"])) == sorted(i + SPLIT * j for i, j in zip(kf["indices"],
                                                                                              kf["recording"]))
    assert summary["n_images"] == len(kf["indices"])
    ext = worlds["root"] / "wBC_older"
    assert main(["build", "--input", str(_third_recording(worlds)), "--extend", str(old), "--output", str(ext), *FAST,
                 "--set", "mapping.pose_source=ground_truth"]) == 0
    new = json.loads((ext / "metadata.json").read_text())
    recs = json.loads((worlds["wB"] / "metadata.json").read_text())["recordings"]
    assert [r["content_hash"] for r in new["recordings"][:2]] == [r["content_hash"] for r in recs]
    assert new["keyframes"]["recording"][:len(kf["recording"])] == kf["recording"]


@pytest.mark.slow
def test_an_older_extended_bundle_without_its_parent_reads_none_of_its_keyframes(worlds, caplog, capsys):
    """Its parent gone, which of its keyframes are A's is unproven: none is paired with any frames,
    neither found nor given with --input, and a world extended from it records them as unknown."""
    from assets.cli import main

    old = _as_older(worlds["wB"], worlds["root"] / "wB_orphan")
    wa, away = worlds["wA"], worlds["root"] / "wA.away"
    wa.rename(away)
    try:
        for extra in ([], ["--input", str(worlds["B"]), "--camera", "freiburg3"]):
            capsys.readouterr()
            assert main(["export", str(old), "--format", "colmap", "--output", str(worlds["root"] / "x"),
                         *extra]) == 2
            err = capsys.readouterr().err
            assert f"its parent bundle {wa} (lineage.parent.path) is not on disk" in err, err
            assert "no keyframe can be exported at its pose" in err and not (worlds["root"] / "x").exists()
        ext = worlds["root"] / "wBC_orphan"
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            assert main(["build", "--input", str(_third_recording(worlds)), "--extend", str(old), "--output", str(ext),
                         *FAST, "--set", "mapping.pose_source=ground_truth"]) == 0
        assert "recorded in the new bundle as frames of an unknown recording" in caplog.text
        new = json.loads((ext / "metadata.json").read_text())
        n_old = len(json.loads((old / "metadata.json").read_text())["keyframes"]["indices"])
        assert new["recordings"][0] == UNKNOWN_RECORDING and new["keyframes"]["recording"][:n_old] == [0] * n_old
        # its export holds C's keyframes only, each with its own frame; the unknown ones left out, said once
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            summary = _export(ext, worlds["root"] / "export_orphan")
        assert summary["n_images"] == len(new["keyframes"]["indices"]) - n_old
        assert min(_check_pairs(worlds["root"] / "export_orphan", worlds["teddy"])) >= 2 * SPLIT
        lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(lines) == 1 and f"{n_old} keyframes of recording 'unnamed'" in lines[0], lines
    finally:
        away.rename(wa)


def test_a_recorded_camera_that_is_no_camera_is_no_candidate(isolated, caplog):
    """Read with the layout's default camera instead, the frames would carry wrong intrinsics:
    the folder is refused with a warning naming the recording and its camera field."""
    from atlas_pipeline.scene_memory.recordings import open_recording, recording_record
    from atlas_pipeline.sensors.camera import TUM_CAMERAS
    from atlas_pipeline.sensors.registry import dataset_from_spec, read_dataset_manifest

    xyz = tum_folder("tum_fr1_xyz_10")
    good = recording_record(read_dataset_manifest(dataset_from_spec(str(xyz), "freiburg1")))
    bad = {**good, "name": "unregistered-xyz", "camera": {**TUM_CAMERAS["freiburg1"].to_dict(), "cx": 900.0}}
    with caplog.at_level(logging.WARNING):
        manifest, why = open_recording(bad)
    assert manifest is None and "its recorded camera (field camera) is not a usable camera" in why
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lines) == 1 and "recording 'unregistered-xyz'" in lines[0] and "field camera" in lines[0], lines
    manifest, _ = open_recording({**good, "name": "unregistered-xyz"})  # the control: its own camera reads
    assert manifest is not None and manifest.camera == TUM_CAMERAS["freiburg1"]
