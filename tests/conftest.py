"""Shared fixtures: a small synthetic dataset, isolated project folders, the real TUM frames."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# A quarter-size synthetic sequence: same scene and path as the default, quick to run everywhere.
SMALL_SYNTH = {"seed": 0, "n_frames": 12, "width": 160, "height": 120,
               "fx": 131.25, "fy": 131.25, "cx": 79.5, "cy": 59.5}


def tum_folder(name: str) -> Path:
    """A folder of ../shared/data, or skip the test saying why."""
    p = SHARED_DATA / name
    if not (p / "rgb.txt").is_file():
        pytest.skip(f"real TUM RGB-D frames not available at {p} (only the project's CI machines have them)")
    return p


@pytest.fixture(autouse=True)
def _signal_handlers_restored():
    """SIGINT's and SIGTERM's handlers as they were before the test: a Dagster run in the main
    thread changes them for good (see ``assets.runs.signal_dispositions_kept``; ``atlas-gs`` puts
    them back, a test running a job itself does not), and a SIGTERM left ignored is inherited by
    every process a later test starts."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, handler in saved.items():
        if handler is not None:
            signal.signal(s, handler)


def isolate_project(root: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Point data, artifacts, the local registry and ``DAGSTER_HOME`` into ``root``, with a small
    synthetic dataset registered as ``synth-small``."""
    import yaml

    reg = root / "datasets.local.yaml"
    reg.write_text(yaml.safe_dump({"datasets": {"synth-small": {"kind": "synthetic", **SMALL_SYNTH}}}))
    monkeypatch.setenv("ATLAS_DATA_DIR", str(root / "data"))
    monkeypatch.setenv("ATLAS_ARTIFACTS_DIR", str(root / "artifacts"))
    monkeypatch.setenv("ATLAS_LOCAL_REGISTRY", str(reg))
    monkeypatch.setenv("DAGSTER_HOME", str(root / "dagster_home"))
    (root / "dagster_home").mkdir()
    return root


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """Data, artifacts and the local registry in a temporary folder (:func:`isolate_project`)."""
    return isolate_project(tmp_path, monkeypatch)


@pytest.fixture(scope="session")
def small_synthetic(tmp_path_factory) -> Path:
    """A generated small synthetic dataset folder (TUM layout), shared by the session."""
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, generate_synthetic_dataset

    return generate_synthetic_dataset(tmp_path_factory.mktemp("synth") / "synth-small", SyntheticSpec(**SMALL_SYNTH))


@pytest.fixture(scope="session")
def small_manifest(small_synthetic):
    from atlas_pipeline.sensors.synthetic import SyntheticSpec
    from atlas_pipeline.sensors.tum import load_tum_sequence

    return load_tum_sequence(small_synthetic, SyntheticSpec(**SMALL_SYNTH).camera(), "synth-small")


@pytest.fixture(scope="session")
def small_world(small_manifest):
    """The small synthetic world's voxel Gaussians before any fit (the keyframe-fit tests' start;
    tests/test_tracking.py has its own ``small_world``)."""
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse

    cfg = load_profile("default").with_overrides({"mapping.fit.epochs": 0,
                                                  "mapping.colour_refinement.iterations": 0})
    fused = fuse(small_manifest, cfg)
    return build_gaussian_world(fused, select_keyframes_stage(small_manifest, fused, cfg), cfg).field


class InlinePool:
    """A ``concurrent.futures`` executor's interface (``ThreadPoolExecutor`` or
    ``ProcessPoolExecutor``) that runs each job at once, where it is submitted: the reference for
    work spread over a pool, or a way to keep fakes in one process."""

    def __init__(self, *args, **kwargs):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args):
        from concurrent.futures import Future

        done = Future()
        done.set_result(fn(*args))
        return done
