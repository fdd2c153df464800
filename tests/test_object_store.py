"""Artifacts on object storage: an S3-compatible server (moto) started on 127.0.0.1 by the test,
reached through fsspec/s3fs. Versions are content-addressed prefixes published by one pointer PUT;
readers verify every file against the pointer; only our own old versions are collected."""

import json
import urllib.request

import pyarrow as pa
import pytest

pytest.importorskip("s3fs")
pytest.importorskip("moto.server")

from assets.io_managers import ArtifactIOManager  # noqa: E402
from assets.storage import POINTER_NAME, RECORD_NAME, object_store  # noqa: E402
from atlas_pipeline.errors import ArtifactError, OutputPolicyError  # noqa: E402

BUCKET = "atlas-test"
ROOT = f"s3://{BUCKET}/artifacts"


@pytest.fixture
def s3(tmp_path, monkeypatch):
    """A moto S3 server on a free port of 127.0.0.1, a bucket, and this machine's scratch folder."""
    import s3fs
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    for k, v in {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1",
                 "AWS_ENDPOINT_URL": f"http://{host}:{port}", "ATLAS_SCRATCH_DIR": str(tmp_path / "scratch")}.items():
        monkeypatch.setenv(k, v)
    object_store.cache_clear()
    s3fs.S3FileSystem.clear_instance_cache()
    fs = s3fs.S3FileSystem()
    fs.mkdir(BUCKET)
    try:
        yield fs
    finally:
        # moto keeps its buckets per process, not per server: empty them for the next test
        urllib.request.urlopen(urllib.request.Request(f"http://{host}:{port}/moto-api/reset", method="POST"))
        object_store.cache_clear()
        s3fs.S3FileSystem.clear_instance_cache()
        server.stop()


def _objects(fs) -> dict[str, str]:
    fs.invalidate_cache()
    return {k: str(v.get("LastModified")) for k, v in fs.find(f"{BUCKET}/artifacts", detail=True).items()}


def _table(n: int) -> pa.Table:
    return pa.table({"step": list(range(n)), "x": [0.5 * i for i in range(n)]})


def test_versions_are_published_by_one_pointer_and_verified_on_read(s3, tmp_path, monkeypatch):
    io = ArtifactIOManager(root=ROOT)
    assert io.remote and not io.intact("transitions", "synth-small")
    io.prepare("transitions", "synth-small")
    first = io.stage("transitions", "synth-small", _table(3), run_id="r1")
    io.commit(first)
    base = f"{BUCKET}/artifacts/transitions/synth-small"
    v1 = "v-" + first.record["content_hash"][:24]
    assert set(_objects(s3)) == {f"{base}/{POINTER_NAME}", f"{base}/{v1}/{RECORD_NAME}", f"{base}/{v1}/table.parquet"}
    pointer = json.loads(s3.cat_file(f"{base}/{POINTER_NAME}"))
    assert pointer["current"] == v1 and pointer["record"]["content_hash"] == first.record["content_hash"]
    assert io.intact("transitions", "synth-small")
    assert io.load_artifact("transitions", "synth-small").equals(_table(3))

    # The same bytes again: nothing is written.
    before = _objects(s3)
    io.commit(io.stage("transitions", "synth-small", _table(3), run_id="r2"))
    assert _objects(s3) == before

    # Two more versions: the current and the previous stay, the oldest of ours is collected.
    second = io.stage("transitions", "synth-small", _table(4), run_id="r3")
    io.commit(second)
    third = io.stage("transitions", "synth-small", _table(5), run_id="r4")
    io.commit(third)
    versions = {k.split("/")[4] for k in _objects(s3) if "/v-" in k}
    assert versions == {"v-" + second.record["content_hash"][:24], "v-" + third.record["content_hash"][:24]}
    assert io.load_artifact("transitions", "synth-small").equals(_table(5))

    # Another machine (empty cache) reading a changed object: an error naming it, never the bytes.
    v3 = "v-" + third.record["content_hash"][:24]
    s3.pipe_file(f"{base}/{v3}/table.parquet", b"not the parquet file the pointer lists")
    monkeypatch.setenv("ATLAS_SCRATCH_DIR", str(tmp_path / "other-machine"))
    object_store.cache_clear()
    io2 = ArtifactIOManager(root=ROOT)
    assert not io2.intact("transitions", "synth-small")  # the size differs
    with pytest.raises(ArtifactError, match=f"{v3}/table.parquet"):
        io2.load_artifact("transitions", "synth-small")


def test_a_prefix_holding_foreign_objects_is_refused_and_never_collected(s3):
    io = ArtifactIOManager(root=ROOT)
    base = f"{BUCKET}/artifacts/transitions/synth-small"
    s3.pipe_file(f"{base}/notes.txt", b"the user's")
    with pytest.raises(OutputPolicyError, match="notes.txt"):
        io.prepare("transitions", "synth-small")
    s3.rm_file(f"{base}/notes.txt")
    # A version-like prefix that is not ours (no record of ours) survives garbage collection.
    s3.pipe_file(f"{base}/v-{'0' * 24}/data.bin", b"someone else's")
    for n in (3, 4, 5):
        io.commit(io.stage("transitions", "synth-small", _table(n)))
    assert f"{base}/v-{'0' * 24}/data.bin" in _objects(s3)


def test_a_foreign_pointer_is_an_error_naming_it(s3):
    s3.pipe_file(f"{BUCKET}/artifacts/keyframes/synth-small/{POINTER_NAME}", b'{"hello": 1}')
    io = ArtifactIOManager(root=ROOT)
    with pytest.raises(ArtifactError, match=f"keyframes/synth-small/{POINTER_NAME}: not an atlas-gs artifact pointer"):
        io.load_artifact("keyframes", "synth-small")
    assert not io.intact("keyframes", "synth-small")


@pytest.mark.slow
def test_full_graph_on_object_storage_then_reused(isolated, s3, monkeypatch, capsys):
    from assets.cli import main

    monkeypatch.setenv("ATLAS_ARTIFACTS_DIR", ROOT)
    assert main(["run", "synth-small", "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["success"] and len(first["recomputed"]) == 9, first
    objects = _objects(s3)
    pointers = sorted(k.split("/")[2] for k in objects if k.endswith(POINTER_NAME))
    assert pointers == sorted(["raw_dataset", "fused_frames", "keyframes", "gaussian_world", "localization_report",
                               "transitions", "demo_videos", "render_evaluation", "world_bundle"])
    assert any(k.endswith("/gaussians.ply") for k in objects) and any(k.endswith("_orbit.mp4") for k in objects)
    assert not (isolated / "artifacts").exists()  # nothing went to the local artifacts folder

    assert main(["run", "synth-small", "--json"]) == 0
    second = json.loads(capsys.readouterr().out)
    assert second["success"] and second["recomputed"] == [] and len(second["reused"]) == 9, second
    assert _objects(s3) == objects  # not one object written or touched
