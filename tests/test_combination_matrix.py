"""Worlds made four ways (built, from estimated poses, extended, imported) times every consumer
(localize, relocalize, transitions, the four exports, the viewer, a demo video, the lineage), on
small real frames: each cell's outputs are checked for what they claim
(``benchmarks/bench_combinations.py`` holds the cells and prints the same matrix)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tests.conftest import tum_folder

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_combinations as combos  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    source = tum_folder(combos.DEFAULT_SEQUENCE)
    return combos.build_worlds(tmp_path_factory.mktemp("combos"), source, 24, "freiburg3")


@pytest.mark.parametrize("consumer", list(combos.CONSUMERS))
@pytest.mark.parametrize("kind", combos.WORLD_KINDS)
def test_cell(setup, kind, consumer):
    ok, text, _ = combos.run_cell(setup, kind, consumer)
    assert ok, f"{kind} x {consumer}: {text}"


def test_a_wrong_pose_is_caught(setup):
    """The cells' pose check itself: an image paired with another frame's pose fails it."""
    import numpy as np

    a = setup.a
    idx = np.flatnonzero(np.isfinite(a.T_world_cam_gt).all(axis=(1, 2)))[:4]
    digests = [a.pixel_digests[i] for i in idx]
    T = a.T_world_cam_gt[idx].copy()
    T[3, :3, 3] += (0.0, 0.2, 0.0)  # the fourth image given a pose 20 cm from its frame's
    assert combos.check_poses_of_frames(setup, digests[:3], T[:3])["max_pose_err_cm"] < 0.01
    with pytest.raises(combos.CellFailure, match=f"frame {idx[3]} of rec_a"):
        combos.check_poses_of_frames(setup, digests, T)
