"""Drives the real ``dagster dev`` web server: materialize a partition through GraphQL, read back the
materializations and their staleness, then materialize again and see every asset reused."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

pytest.importorskip("dagster_webserver", reason="dagster-webserver is not installed")

ROOT = Path(__file__).resolve().parents[1]
PART = "synth-small"
ASSETS = {"raw_dataset", "fused_frames", "keyframes", "gaussian_world", "localization_report",
          "transitions", "demo_videos", "render_evaluation", "world_bundle"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _gql(url: str, query: str, variables: dict | None = None) -> dict:
    req = urllib.request.Request(url + "/graphql", data=json.dumps({"query": query, "variables": variables or {}}).encode(),
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=30) as r:
        body = json.loads(r.read())
    assert "errors" not in body, body["errors"]
    return body["data"]


LAUNCH = """
mutation($p: ExecutionParams!) { launchRun(executionParams: $p) {
  __typename
  ... on LaunchRunSuccess { run { runId } }
  ... on PythonError { message }
  ... on InvalidSubsetError { message }
  ... on RunConfigValidationInvalid { errors { message } }
}}"""
RUN_STATUS = "query($id: ID!) { runOrError(runId: $id) { __typename ... on Run { status } } }"
NODES = """
query($partition: String!) { assetNodes { assetKey { path } staleStatus(partition: $partition)
  assetMaterializations(partitions: [$partition], limit: 1) { runId partition
    metadataEntries { label ... on BoolMetadataEntry { boolValue } ... on TextMetadataEntry { text } } } } }"""


def _wait_run(url: str, run_id: str, deadline: float) -> str:
    while time.time() < deadline:
        status = _gql(url, RUN_STATUS, {"id": run_id})["runOrError"].get("status")
        if status in ("SUCCESS", "FAILURE", "CANCELED"):
            return status
        time.sleep(1.0)
    raise AssertionError(f"run {run_id} did not finish in time")


def _nodes(url: str) -> dict:
    """Asset nodes by key (``settings/...`` keys have two parts)."""
    return {"/".join(n["assetKey"]["path"]): n for n in _gql(url, NODES, {"partition": PART})["assetNodes"]}


def _launch(url: str) -> str:
    params = {"selector": {"repositoryLocationName": "atlas_gs", "repositoryName": "__repository__",
                           "jobName": "atlas_gs_all"},
              "runConfigData": {},
              "executionMetadata": {"tags": [{"key": "dagster/partition", "value": PART}]}}
    res = _gql(url, LAUNCH, {"p": params})["launchRun"]
    assert res["__typename"] == "LaunchRunSuccess", res
    return res["run"]["runId"]


@pytest.mark.slow
def test_dagster_dev_materializes_a_partition_and_reports_staleness(isolated):
    # A fresh DAGSTER_HOME: the partitions are the registry's, read as the code location loads.
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    env = dict(os.environ)  # ATLAS_* and DAGSTER_HOME from the isolated fixture
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    log = open(isolated / "dagster_dev.log", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "dagster", "dev", "-w", "workspace.yaml", "-h", "127.0.0.1",
                             "-p", str(port)], cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        deadline = time.time() + 150
        loaded = False
        while time.time() < deadline and not loaded:
            assert proc.poll() is None, (isolated / "dagster_dev.log").read_text()[-3000:]
            try:
                data = _gql(url, "{ repositoriesOrError { ... on RepositoryConnection { nodes { name location { name } } } } }")
                loaded = any(n["location"]["name"] == "atlas_gs" for n in data["repositoriesOrError"].get("nodes", []))
            except (urllib.error.URLError, ConnectionError, OSError):
                pass
            time.sleep(1.0)
        assert loaded, "dagster dev did not load the atlas_gs code location\n" + (isolated / "dagster_dev.log").read_text()[-3000:]

        run_id = _launch(url)
        assert _wait_run(url, run_id, time.time() + 240) == "SUCCESS", (isolated / "dagster_dev.log").read_text()[-3000:]
        nodes = _nodes(url)
        assert ASSETS <= set(nodes)
        for a in ASSETS:
            mats = nodes[a]["assetMaterializations"]
            assert mats and mats[0]["runId"] == run_id and mats[0]["partition"] == PART, (a, mats)
            assert nodes[a]["staleStatus"] == "FRESH", (a, nodes[a]["staleStatus"])
            reused = {e["label"]: e.get("boolValue") for e in mats[0]["metadataEntries"]}["reused"]
            assert reused is False
        assert (isolated / "artifacts" / "world_bundle" / PART / "metadata.json").is_file()

        # The same materialization again: every asset reused, still fresh.
        run2 = _launch(url)
        assert _wait_run(url, run2, time.time() + 120) == "SUCCESS"
        nodes = _nodes(url)
        for a in ASSETS:
            m = nodes[a]["assetMaterializations"][0]
            assert m["runId"] == run2 and {e["label"]: e.get("boolValue") for e in m["metadataEntries"]}["reused"] is True
            assert nodes[a]["staleStatus"] == "FRESH"
    finally:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=20)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait(timeout=10)
        log.close()
