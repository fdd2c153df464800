"""A non-editable install works. The wheel carries both packages and the built-in configs
(``atlas_pipeline/configs``); installed, atlas-gs reads those through importlib.resources and keeps
user state in ``$ATLAS_GS_HOME`` (default: the working directory), never in the source tree or
site-packages. A source checkout keeps everything in the checkout, as before."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

import atlas_pipeline
from atlas_pipeline import config
from atlas_pipeline.sensors import registry

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("atlas_pipeline", "assets")
STATE_VARS = ("ATLAS_PROJECT_ROOT", "ATLAS_GS_HOME", "ATLAS_LOCAL_REGISTRY", "ATLAS_ARTIFACTS_DIR",
              "ATLAS_DATA_DIR", "DAGSTER_HOME")
# The synthetic partition at the test size (tests/conftest.py SMALL_SYNTH), set in the user registry
# of the install's home, so the run also proves that file is read from there.
SMALL_SYNTHETIC = {"kind": "synthetic", "seed": 0, "n_frames": 12, "width": 160, "height": 120,
                   "fx": 131.25, "fy": 131.25, "cx": 79.5, "cy": 59.5}
QUICK = ["--profile", "demo", "--set", "mapping.fit.epochs=0", "--set", "video.orbit_frames=4"]


def _source_packages() -> list[str]:
    pkgs = []
    for top in PACKAGES:
        for init in sorted((ROOT / top).rglob("__init__.py")):
            if "__pycache__" not in init.parts:
                pkgs.append(".".join(init.parent.relative_to(ROOT).parts))
    return pkgs


def _shipped_configs() -> list[str]:
    return sorted(p.name for p in (ROOT / "configs").glob("*.yaml") if p.name != "datasets.local.yaml")


def test_pyproject_lists_every_package_and_maps_the_configs():
    tomllib = pytest.importorskip("tomllib")
    st = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert sorted(st["packages"]) == sorted([*_source_packages(), "atlas_pipeline.configs"]), \
        "a package was added or removed: update [tool.setuptools] packages in pyproject.toml"
    assert st["package-dir"] == {"atlas_pipeline.configs": "configs"}
    assert st["package-data"]["atlas_pipeline.configs"] == ["*.yaml"]
    assert "datasets.local.yaml" in st["exclude-package-data"]["atlas_pipeline.configs"]


@pytest.fixture
def clean_state_env(monkeypatch):
    for var in STATE_VARS:
        monkeypatch.delenv(var, raising=False)


def test_a_source_checkout_keeps_everything_in_the_checkout(clean_state_env):
    if config.source_root() != ROOT:
        pytest.skip(f"atlas_pipeline is imported from {atlas_pipeline.__file__}, not this checkout")
    from assets.io_managers import artifacts_root

    assert config.project_root() == ROOT
    assert config.configs_dir() == ROOT / "configs"
    assert registry.registry_files()[0] == ROOT / "configs" / "datasets.yaml"
    assert registry.local_registry_path() == ROOT / "configs" / "datasets.local.yaml"
    assert artifacts_root() == ROOT / "artifacts"
    assert registry.data_dir() == ROOT / "data"


def test_atlas_gs_home_moves_the_user_state_not_the_built_in_configs(clean_state_env, monkeypatch, tmp_path):
    from assets.io_managers import artifacts_root

    configs = config.configs_dir()
    monkeypatch.setenv("ATLAS_GS_HOME", str(tmp_path))
    assert config.project_root() == tmp_path.resolve()
    assert config.configs_dir() == configs
    assert registry.local_registry_path() == tmp_path.resolve() / "configs" / "datasets.local.yaml"
    assert artifacts_root() == tmp_path.resolve() / "artifacts"
    assert registry.data_dir() == tmp_path.resolve() / "data"


def test_installed_the_user_state_defaults_to_the_working_directory(clean_state_env, monkeypatch, tmp_path):
    monkeypatch.setattr(config, "source_root", lambda: None)
    monkeypatch.chdir(tmp_path)
    assert config.project_root() == tmp_path
    assert registry.local_registry_path() == tmp_path / "configs" / "datasets.local.yaml"


# ---- the real thing: build the wheel, install it in a fresh venv, run the main job ---------------

_NOT_COPIED_AT_TOP = {".git", ".venv", "venv", "build", "dist", "artifacts", "data", ".dagster_home",
                      ".pytest_cache", ".hypothesis"}


def _copy_source(dst: Path) -> Path:
    """The working tree without its state and build output (the build writes build/ and egg-info)."""
    def ignore(d: str, names: list[str]) -> set[str]:
        skip = {n for n in names if n == "__pycache__" or n.endswith(".egg-info") or n.startswith(".tmp_dagster_home")}
        if Path(d) == ROOT:
            skip |= _NOT_COPIED_AT_TOP & set(names)
        return skip

    shutil.copytree(ROOT, dst, ignore=ignore)
    # A user's own registry next to the built-in one must stay out of the wheel.
    (dst / "configs" / "datasets.local.yaml").write_text("datasets: {}\n")
    return dst


def _build_wheel(src: Path, out: Path) -> Path:
    cmd = [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-w", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if res.returncode != 0:  # no index to fetch the build backend from: build with this venv's setuptools
        res = subprocess.run([*cmd, "--no-build-isolation"], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    (wheel,) = out.glob("atlas_gs-*.whl")
    return wheel


def _check_wheel_contents(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == set(PACKAGES), tops
    for top in PACKAGES:
        for py in (ROOT / top).rglob("*.py"):
            if "__pycache__" not in py.parts:
                assert py.relative_to(ROOT).as_posix() in names, f"{py.relative_to(ROOT)} is not in the wheel"
    shipped = sorted(n.rsplit("/", 1)[1] for n in names if n.startswith("atlas_pipeline/configs/"))
    assert shipped == _shipped_configs()  # the built-in profiles and registry, not datasets.local.yaml
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "atlas-gs = assets.cli:command" in zipfile.ZipFile(wheel).read(entry_points).decode()


def _tree(root: Path) -> dict[str, int]:
    """Files under ``root`` and their mtimes, leaving out bytecode and numba's kernel caches
    (``__pycache__``: numba writes its cache next to the module, wherever that is installed)."""
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts}


def _source_state() -> dict[str, int | None]:
    """What a run that wrongly used the checkout would touch (checked by mtime, cheaply)."""
    paths = [ROOT / "configs", ROOT / "configs" / "datasets.local.yaml", ROOT / "artifacts", ROOT / "data",
             ROOT / "data" / "synthetic", ROOT / ".dagster_home", ROOT / ".dagster_home" / "storage",
             ROOT / ".dagster_home" / "history"]
    if (ROOT / "artifacts").is_dir():
        for asset in (ROOT / "artifacts").iterdir():
            paths += [asset, asset / "synthetic"]
    return {str(p): (p.stat().st_mtime_ns if p.exists() else None) for p in paths}


@pytest.mark.slow
def test_wheel_install_runs_the_main_job_outside_the_source_tree(tmp_path):
    wheel = _build_wheel(_copy_source(tmp_path / "src"), tmp_path / "wheel")
    _check_wheel_contents(wheel)

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=300)
    py = venv / "bin" / "python"
    res = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index",
                          str(wheel)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    site = Path(subprocess.check_output([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                        text=True).strip())
    # This venv's dependencies (not its atlas-gs: a plain path line runs no editable finder), no network.
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "_atlas_gs_test_deps.pth").write_text("".join(f"{d}\n" for d in sorted(deps)))

    home = tmp_path / "home"
    (home / "configs").mkdir(parents=True)
    (home / "configs" / "datasets.local.yaml").write_text(json.dumps({"datasets": {"synthetic": SMALL_SYNTHETIC}}))
    env = {k: v for k, v in os.environ.items()
           if k not in STATE_VARS and k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env["PATH"] = str(venv / "bin") + os.pathsep + env.get("PATH", "")

    probe = ("import json, atlas_pipeline, assets\n"
             "from atlas_pipeline.config import configs_dir, project_root, source_root\n"
             "from atlas_pipeline.sensors.registry import local_registry_path\n"
             "print(json.dumps({'atlas_pipeline': atlas_pipeline.__file__, 'assets': assets.__file__,\n"
             "  'source_root': str(source_root()), 'configs': str(configs_dir()), 'home': str(project_root()),\n"
             "  'local_registry': str(local_registry_path())}))")
    where = json.loads(subprocess.check_output([str(py), "-c", probe], cwd=home, env=env, text=True, timeout=300))
    for key in ("atlas_pipeline", "assets", "configs"):
        assert Path(where[key]).is_relative_to(site), (key, where)
    assert where["source_root"] == "None"
    assert Path(where["home"]) == home.resolve()
    assert Path(where["local_registry"]) == home.resolve() / "configs" / "datasets.local.yaml"

    install_before, source_before = _tree(venv), _source_state()
    res = subprocess.run([str(venv / "bin" / "atlas-gs"), "run", "synthetic", *QUICK], cwd=home, env=env,
                         capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-5000:]
    out = json.loads(res.stdout)
    assert out["success"]

    bundle = home / "artifacts" / "world_bundle" / "synthetic"
    assert Path(out["world_bundle"]) == bundle.resolve()
    assert (bundle / "metadata.json").is_file() and (bundle / "transitions.parquet").is_file()
    videos = [Path(v) for v in out["videos"]]
    assert len(videos) == 3 and all(v.is_relative_to(home.resolve() / "artifacts" / "demo_videos") for v in videos)
    assert all(v.stat().st_size > 0 for v in videos)
    assert (home / ".dagster_home" / "history").is_dir()  # the Dagster instance is the home's too
    assert (home / "data" / "synthetic" / "rgb.txt").is_file()  # and the generated frames
    assert _tree(venv) == install_before, "the run wrote into the install"
    assert _source_state() == source_before, "the run wrote into the source tree"
