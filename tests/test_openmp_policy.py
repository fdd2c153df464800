"""The library makes OpenMP's threads wait passively (atlas_pipeline.OPENMP_WAIT_POLICY) unless the
user chose a policy: spinning barriers collapse parallel kernels when another job shares the cores
(benchmarks/bench_openmp_wait.py)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

_PROBE = "import os, atlas_pipeline; print(os.environ.get('OMP_WAIT_POLICY'))"


def _policy_after_import(env_policy: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if env_policy is not None:
        env["OMP_WAIT_POLICY"] = env_policy
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


def test_import_sets_passive_wait_policy():
    import atlas_pipeline

    assert _policy_after_import(None) == atlas_pipeline.OPENMP_WAIT_POLICY == "PASSIVE"


@pytest.mark.parametrize("user_policy", ["ACTIVE", "passive"])
def test_user_policy_wins(user_policy):
    assert _policy_after_import(user_policy) == user_policy
