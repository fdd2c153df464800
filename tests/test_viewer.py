"""The browser viewer (``atlas-gs view``): the scene it builds from a bundle, its loopback-only
binding, and, in headless Chromium (pixels, not HTML): the splats, the mesh and occupancy layers
and their switches, the frame slider's marker and status, a drag staying in the room, Reset view,
and a console without errors of ours."""

from __future__ import annotations

import argparse
import base64
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

pytest.importorskip("viser", reason="viser is not installed (pip install -e .)")

from atlas_pipeline.errors import BundleFormatError, ConfigError  # noqa: E402
from atlas_pipeline.gaussian_world.field import GaussianField  # noqa: E402
from atlas_pipeline.localization.localizer import LocalizationReport  # noqa: E402
from atlas_pipeline.scene_memory.bundle import write_world_bundle  # noqa: E402
from atlas_pipeline.viz import viewer, viewer_controls, viewer_layers  # noqa: E402
from atlas_pipeline.viz.viewer_controls import SELECTED_RGB  # noqa: E402

# A colour no viewer chrome uses (viser's UI is white, grey and blue) and no other layer has.
SPLAT_RGB = (230, 20, 230)
SPLAT_TOLERANCE = 70  # per channel: splat edges blend with the white background
MIN_SPLAT_SHARE = 0.05  # of the scene; the sheet fills most of the first view
# Lost (red) and relocalized (orange) markers seen from ~0.7 m: ~300 px each (0.08 % of the scene).
MIN_MARKER_SHARE = 0.0004
MARKER_TOLERANCE = 40
MIN_SELECTED_PX = 30  # the slider's yellow camera (dot and frustum) seen from ~1 m: a few hundred px
# The layer folders' colours: a teal mesh quad, the occupancy grid's free cells. The canvas tone-maps
# meshes (react-three-fiber's default ACES curve; the splats and images are not), so the quad is
# found as teal-ish (red low, green and blue high), not by its exact colour.
MESH_RGB = (20, 200, 200)
FREE_RGB = viewer_layers.FREE_RGBA[:3]
LAYER_TOLERANCE = 20  # images are drawn without tone mapping, in their exact colours; grey text is 35 away
MIN_LAYER_SHARE = 0.01
KEYFRAMES = [0, 4, 8]
LOST, RELOCALIZED = 5, 6
SCREEN_W, SCREEN_H = 1000, 600
SCENE_W = 660  # the scene left of viser's panel (the panel's thumbnails have colours of their own)
# SwiftShader on a loaded 2-core machine: first frames take a while.
BROWSER_DEADLINE_S = float(os.environ.get("ATLAS_BROWSER_DEADLINE_S", 120.0))
# Software WebGL: headless Chromium has no GPU here; ANGLE on SwiftShader gives it WebGL 2.
CHROMIUM_FLAGS = ["--headless=new", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--disable-dev-shm-usage", "--no-first-run", "--no-default-browser-check",
                  "--disable-extensions", "--mute-audio", f"--window-size={SCREEN_W},{SCREEN_H}"]


def _sheet(T_world_cam: np.ndarray, distance_m: float = 1.5, half_m: float = 0.6,
           step_m: float = 0.03) -> GaussianField:
    """A flat square of magenta Gaussians facing the camera ``T_world_cam``, ``distance_m`` ahead."""
    R, p = T_world_cam[:3, :3], T_world_cam[:3, 3]
    a = np.arange(-half_m, half_m + 1e-9, step_m)
    u, v = np.meshgrid(a, a)
    pos = p + R[:, 2] * distance_m + u.reshape(-1, 1) * R[:, 0] + v.reshape(-1, 1) * R[:, 1]  # [N, 3]
    n = len(pos)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return GaussianField(pos, np.full((n, 3), step_m * 0.8), q, np.tile(SPLAT_RGB, (n, 1)), np.full(n, 0.95),
                         np.arange(n, dtype=np.uint64))


@pytest.fixture
def viewer_world(isolated, small_synthetic, small_manifest) -> Path:
    """A bundle over the small synthetic sequence (registered as ``synth-small``): a magenta sheet in
    front of the first keyframe, three keyframes at ground-truth poses, and a localization report
    with one lost frame (pose unknown) and one relocalized frame."""
    m = small_manifest
    gt = m.T_world_cam_gt
    field = _sheet(gt[KEYFRAMES[0]])
    n = m.n_frames
    est = gt.copy()
    est[:, :3, 3] += 0.01  # a small estimation error
    est[LOST] = np.nan  # lost, never placed
    status = ["anchor"] + ["tracked"] * (n - 1)
    status[LOST], status[RELOCALIZED] = "lost", "relocalized"
    nan = np.full(n, np.nan)
    report = LocalizationReport("synth-small", field.content_hash()[:16], m.timestamps_s, est, status, nan, nan, nan,
                                np.full((n, 4, 4), np.nan), nan, nan, {})
    meta = {
        "name": "synth-small", "partition": "synth-small",
        "dataset": {"name": "synth-small", "root": str(m.root), "n_frames": n, "content_hash": m.content_hash,
                    "camera": m.camera.to_dict()},
        "gaussians": {"voxel_size_m": 0.02, "isotropic": True, "n_keyframes": len(KEYFRAMES),
                      "pose_source": "ground_truth"},
        "keyframes": {"indices": KEYFRAMES, "T_world_cam": [gt[i].tolist() for i in KEYFRAMES]},
    }
    return write_world_bundle(isolated / "world", field, meta, localization=report)


def _kf0_frame(small_manifest) -> tuple[np.ndarray, np.ndarray]:
    """``(R [3, 3], p [3])`` of the first keyframe: columns right, down, forward."""
    T0 = small_manifest.T_world_cam_gt[KEYFRAMES[0]]
    return T0[:3, :3], T0[:3, 3]


@pytest.fixture
def layer_folders(tmp_path, small_manifest) -> list[Path]:
    """Two export folders as ``atlas-gs export`` writes them: ``mesh/`` a teal quad 0.3 m in front
    of the magenta sheet, to its upper left; ``occupancy/`` a 4 x 4 m grid of free cells (one row
    occupied) on a plane 0.3 m below the sheet's centre, facing up."""
    from atlas_pipeline.interop.mesh import TriangleMesh, write_mesh_ply
    from atlas_pipeline.interop.occupancy import GridSpec, OccupancyGrid, write_ros_map

    R, p = _kf0_frame(small_manifest)
    x, y, z = R[:, 0], R[:, 1], R[:, 2]
    mesh_dir, occ_dir = tmp_path / "mesh", tmp_path / "occupancy"
    mesh_dir.mkdir()
    occ_dir.mkdir()
    corners = np.array([p + 1.2 * z + u * x + v * y for u, v in ((-0.55, -0.45), (-0.15, -0.45), (-0.15, -0.05),
                                                                 (-0.55, -0.05))], np.float32)
    normals = np.tile(-z, (4, 1)).astype(np.float32)
    write_mesh_ply(TriangleMesh(corners, np.tile(MESH_RGB, (4, 1)).astype(np.uint8),
                                np.array([[0, 1, 2], [0, 2, 3]], np.int32), normals), mesh_dir / "mesh.ply")
    T_world_map = np.eye(4)
    T_world_map[:3, :3] = np.stack([x, z, -y], axis=1)  # x right, y forward, z up
    T_world_map[:3, 3] = p + 1.5 * z + 0.3 * y
    state = np.zeros((80, 80), np.int8)  # FREE
    state[60] = 100  # OCCUPIED: a wall 1 m behind the sheet
    grid = OccupancyGrid(state, GridSpec(np.array([-2.0, -2.0]), 0.05, (80, 80)), T_world_map, -y, 0.0, (0.05, 2.0))
    write_ros_map(grid, occ_dir)
    (occ_dir / "occupancy.json").write_text(json.dumps({"resolution_m": 0.05, "origin_xy_m": [-2.0, -2.0],
                                                        "T_world_map": T_world_map.tolist()}))
    return [mesh_dir, occ_dir]


def test_layers_from_export_folders(viewer_world, layer_folders, small_manifest):
    data = viewer.load_viewer_data(viewer_world, read_dataset=False, layers=layer_folders)
    assert data.mesh is not None and len(data.mesh.triangles) == 2
    np.testing.assert_array_equal(data.mesh.colors, np.tile(MESH_RGB, (4, 1)))
    occ = data.occupancy
    assert occ is not None and occ.rgba.shape == (80, 80, 4) and occ.cell_counts["occupied"] == 80
    assert (occ.width_m, occ.height_m) == pytest.approx((4.0, 4.0))
    R, p = _kf0_frame(small_manifest)
    np.testing.assert_allclose(occ.T_world_quad[:3, 3], p + 1.5 * R[:, 2] + 0.3 * R[:, 1]
                               + viewer_layers.FLOOR_LIFT_M * -R[:, 1], atol=1e-6)  # grid centred on the origin
    # The occupied row (map row 60, y = +1 m) is image row 80 - 1 - 60 (images start at the far edge).
    assert (occ.rgba[19, :, :3] == viewer_layers.OCCUPIED_RGBA[:3]).all()
    glb = viewer_layers.mesh_glb(data.mesh)
    assert glb[:4] == b"glTF" and len(glb) % 4 == 0
    data = viewer.load_viewer_data(viewer_world, read_dataset=False, layers=[viewer_world])
    assert data.mesh is None and any("neither mesh.ply nor map.pgm" in n for n in data.notes)


def test_layers_are_bounded_and_clean():
    rng = np.random.default_rng(0)
    n = 120  # a 120 x 120 vertex grid: 28,322 triangles
    u, v = np.meshgrid(np.linspace(0, 3, n), np.linspace(0, 3, n))
    verts = np.stack([u.ravel(), v.ravel(), 0.05 * rng.standard_normal(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    cols = rng.integers(0, 255, (n * n, 3)).astype(np.uint8)
    verts[5] = np.nan  # a NaN vertex and a repeated-vertex triangle are dropped before anything else
    tris = np.concatenate([tris, [[7, 7, 8]]])
    v2, c2, t2 = viewer_layers.clean_mesh(verts, cols, tris)
    assert np.isfinite(v2).all() and len(t2) == len(tris) - 1 - int((tris == 5).any(axis=1).sum())
    v3, c3, t3 = viewer_layers.decimate(v2, c2, t2, max_triangles=5000)
    assert 0 < len(t3) <= 5000 and t3.max() < len(v3) and np.isfinite(v3).all() and len(c3) == len(v3)
    assert viewer_layers._mesh_layer(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), "x", 10) is None
    # An occupancy grid larger than the texture bound is merged, keeping every obstacle.
    state = np.zeros((3000, 2100), np.int8)
    state[1234, 987] = 100
    layer = viewer_layers.occupancy_layer(state, 0.05, np.zeros(2), np.eye(4), "x")
    assert max(layer.rgba.shape[:2]) <= viewer_layers.MAX_OCCUPANCY_PX
    assert (layer.rgba[..., :3] == viewer_layers.OCCUPIED_RGBA[:3]).all(axis=-1).sum() == 1
    assert viewer_layers.occupancy_layer(np.zeros((0, 0), np.int8), 0.05, np.zeros(2), np.eye(4), "x") is None
    assert viewer_layers.occupancy_layer(state, 0.05, np.zeros(2), np.full((4, 4), np.nan), "x") is None


def test_frusta_thinned_and_orbit_inside_the_room():
    assert len(viewer_controls.thinned_indices(40, viewer.MAX_FRUSTA)) == viewer.MAX_FRUSTA
    assert viewer_controls.thinned_indices(5, 12).tolist() == [0, 1, 2, 3, 4]
    assert viewer_controls.frustum_size(5.0, 12, 0.03, (0.015, 0.5)) < viewer_controls.frustum_size(5.0, 3, 0.03,
                                                                                                     (0.015, 0.5))
    # A 6 x 4 x 2.5 m room's walls and cameras near its middle, turned 30 degrees about z.
    rng = np.random.default_rng(1)
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    walls = np.concatenate([np.stack([rng.uniform(-3, 3, 500), np.full(500, sy), rng.uniform(0, 2.5, 500)], 1)
                            for sy in (-2, 2)] + [np.stack([np.full(500, sx), rng.uniform(-2, 2, 500),
                                                            rng.uniform(0, 2.5, 500)], 1) for sx in (-3, 3)])
    pts = walls @ Rz.T
    cams = np.array([[0.5, 0.3, 1.4], [-0.4, 0.2, 1.4], [0.1, -0.6, 1.5]]) @ Rz.T
    up = np.array([0.0, 0.0, 1.0])
    view = viewer_controls.orbit_view(pts, cams, np.median(pts, axis=0), 7.6, up, viewer.EXTENT_PERCENTILES)
    inside = lambda q, tol=0.0: (np.abs((Rz.T @ q)[:2]) < [3.0 + tol, 2.0 + tol]).all() and 0 < q[2] < 2.5  # noqa: E731
    assert inside(view.position) and 0.3 <= view.radius_m < 2.0
    for deg in range(0, 360, 15):  # the orbit at its radius never leaves the room
        a = np.radians(deg)
        q = view.pivot + view.radius_m * np.array([np.cos(a), np.sin(a), 0.3])
        assert inside(q), deg
    # Anything outside comes back in (to the box's corner: the walls' principal axes are estimated).
    assert inside(view.clamp(np.array([10.0, -8.0, 9.0])), tol=0.1)


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_scene_holds_every_layer(viewer_world):
    with viewer.serve(viewer_world, port=0) as h:
        s = h.summary
        assert h.url.startswith("http://127.0.0.1:")
        port = h.server.get_port()
        html = urllib.request.urlopen(h.url, timeout=10).read().decode()
        assert "<html" in html.lower()
    assert s["n_gaussians"] == 41 * 41
    assert s["n_keyframes"] == 3 and s["n_keyframe_images"] == 3  # thumbnails from the frames on disk
    assert s["n_frames"] == 12 and s["n_estimated_poses"] == 11
    assert s["n_ground_truth_poses"] == 12 and s["ground_truth_frame"].startswith("world frame")
    assert s["n_lost_marked"] == 1 and s["n_relocalized_marked"] == 1  # the lost one at its ground truth
    # Layers computed from the keyframes' frames: the room's mesh fuses; the sheet alone has no floor.
    assert s["n_mesh_triangles"] > 1000 and s["mesh_source"] == "computed from 3 of 3 keyframes"
    assert s["occupancy_px"] is None and any(n.startswith("no occupancy layer") for n in s["notes"])
    assert s["n_frusta"] == 3
    deadline = time.monotonic() + 10
    while _port_open(port) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _port_open(port), "the server still listens after stop()"


def test_frames_not_on_disk_give_bare_frusta(viewer_world, small_synthetic, tmp_path):
    meta = json.loads((viewer_world / "metadata.json").read_text())
    data = viewer.load_viewer_data(viewer_world, read_dataset=False)
    assert all(img is None for img in data.keyframe_images) and data.T_world_cam_gt is None
    assert any("not read" in n for n in data.notes)
    assert meta["dataset"]["root"] == str(small_synthetic)


def test_only_loopback_unless_allowed(viewer_world):
    for host in ("127.0.0.1", "127.0.0.2", "::1", "localhost"):
        assert viewer.is_loopback_host(host)
    for host in ("0.0.0.0", "192.168.1.5", "::", "example.org", ""):
        assert not viewer.is_loopback_host(host)
        with pytest.raises(ConfigError, match="loopback"):
            viewer.serve(viewer_world, host=host, port=0)


def test_corrupt_inputs_are_refused(viewer_world, tmp_path):
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "localization.json").write_text('{"dataset": "x", "frames": [{"status": 3}]}')
    with pytest.raises(BundleFormatError, match="localization.json"):
        viewer.load_viewer_data(viewer_world, report=tmp_path / "rep", read_dataset=False)
    data = bytearray((viewer_world / "gaussians.bin").read_bytes())
    data[-1] ^= 0xFF
    (viewer_world / "gaussians.bin").write_bytes(bytes(data))
    with pytest.raises(BundleFormatError, match="checksum"):
        viewer.serve(viewer_world, port=0)


def test_ground_truth_of_another_frame_is_aligned_onto_the_estimate(small_manifest):
    from atlas_pipeline.geometry import pose_from_tq

    T_est = small_manifest.T_world_cam_gt  # [N, 4, 4]
    S = pose_from_tq(np.array([1.0, -2.0, 0.5]), np.array([0.0, 0.0, np.sin(0.4), np.cos(0.4)]))
    status = ["anchor"] + ["tracked"] * (len(T_est) - 1)
    T_gt, how = viewer._ground_truth_in_world(T_est, S @ T_est, status, same_frame=False)
    np.testing.assert_allclose(T_gt, T_est, atol=1e-6)
    assert how.startswith("aligned")
    T_gt, how = viewer._ground_truth_in_world(T_est, S @ T_est, status, same_frame=True)
    np.testing.assert_allclose(T_gt, S @ T_est) and how.startswith("world frame")


def test_splat_covariances_follow_scale_and_rotation():
    s = np.array([[0.1, 0.02, 0.01]])
    quarter_turn_z = np.array([[0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]])  # x, y, z, w
    cov = viewer.splat_covariances(s, quarter_turn_z)[0]
    np.testing.assert_allclose(np.diag(cov), [0.02 ** 2, 0.1 ** 2, 0.01 ** 2], rtol=1e-5)  # local x now along world y
    np.testing.assert_allclose(cov, cov.T, atol=1e-9)
    rng = np.random.default_rng(0)
    q = rng.normal(size=(50, 4))
    covs = viewer.splat_covariances(rng.uniform(0.001, 0.2, (50, 3)), q)
    assert (np.linalg.eigvalsh(covs.astype(np.float64)) > 0).all()


def test_view_command_arguments(viewer_world, monkeypatch):
    from assets.cli.parser import build_parser

    p = build_parser()
    args = p.parse_args(["view", str(viewer_world), "--port", "0"])
    assert args.host == "127.0.0.1" and args.port == 0 and args.report is None
    seen = {}
    monkeypatch.setattr(viewer, "run_viewer", lambda world, **kw: seen.update(world=world, **kw) or 0)
    assert args.func(args) == 0
    assert seen["world"] == viewer_world and seen["host"] == "127.0.0.1" and seen["report"] is None
    assert seen["layers"] == [] and seen["compute_layers"] is True
    args = p.parse_args(["view", str(viewer_world), "--layers", "a", "b", "--no-layers"])
    assert args.func(args) == 0 and seen["layers"] == [Path("a"), Path("b")] and seen["compute_layers"] is False
    with pytest.raises(ConfigError, match="neither a bundle folder nor a partition"):
        args.func(p.parse_args(["view", "no-such-partition"]))


# ---- headless Chromium ---------------------------------------------------------------------------


def _chromium() -> str | None:
    for name in (os.environ.get("ATLAS_CHROMIUM"), "chromium", "chromium-browser", "google-chrome", "chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


# The one console error the page logs that is not ours: viser's splat renderer draws each Gaussian
# on a quad whose "position" attribute has 2 components (x, y), and three.js's bounding sphere of
# that geometry (for frustum culling) reads a third one past the array's end. Culling with a NaN
# sphere keeps the splats drawn. Our own layers never send such geometry (viewer_layers.clean_mesh,
# empty layers not drawn); any other error fails the test.
KNOWN_CLIENT_ERRORS = ("THREE.BufferGeometry.computeBoundingSphere(): Computed radius is NaN",)


class _DevTools:
    """The few Chrome DevTools Protocol calls the test needs, over the page's websocket; the
    console's errors and uncaught exceptions are collected in ``errors`` as they arrive."""

    def __init__(self, ws_url: str):
        from websockets.sync.client import connect  # viser's own dependency

        self.ws = connect(ws_url, max_size=None, open_timeout=30)
        self.next_id = 0
        self.errors: list[str] = []
        self.shots_dir = Path(tempfile.gettempdir())

    def _event(self, msg: dict) -> None:
        method, p = msg.get("method"), msg.get("params", {})
        if method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            self.errors.append(" ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
        elif method == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            self.errors.append(p["entry"].get("text", ""))
        elif method == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            self.errors.append(d.get("exception", {}).get("description") or d.get("text", "exception"))

    def call(self, method: str, timeout_s: float = 60.0, **params):
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:  # events arrive in between
            msg = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.1)))
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg["result"]
            self._event(msg)

    def close(self) -> None:
        self.ws.close()

    # -- what the tests do with a page --

    def screenshot(self) -> np.ndarray:
        import imageio.v3 as iio

        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return iio.imread(png)[..., :3]  # [H, W, 3] uint8

    def evaluate(self, js: str):
        return self.call("Runtime.evaluate", expression=js, returnByValue=True).get("result", {}).get("value")

    def drag(self, dx: int, x: int = SCENE_W // 2, y: int = SCREEN_H // 2, steps: int = 10) -> None:
        """A left-button drag of ``dx`` pixels across the scene, as a user's mouse makes it."""
        self.call("Input.dispatchMouseEvent", type="mousePressed", x=x, y=y, button="left", buttons=1, clickCount=1)
        for k in range(1, steps + 1):
            self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x + dx * k // steps, y=y, button="left",
                      buttons=1)
            time.sleep(0.03)
        self.call("Input.dispatchMouseEvent", type="mouseReleased", x=x + dx, y=y, button="left", clickCount=1)

    def unexpected_errors(self) -> list[str]:
        return [e for e in self.errors if not any(k in e for k in KNOWN_CLIENT_ERRORS)]


def _launch_chromium(binary: str, profile: Path) -> tuple[subprocess.Popen, int]:
    flags = list(CHROMIUM_FLAGS)
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        flags.append("--no-sandbox")  # Chromium refuses to run its sandbox as root (CI containers)
    proc = subprocess.Popen([binary, *flags, "--remote-debugging-port=0", f"--user-data-dir={profile}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    port_file = profile / "DevToolsActivePort"  # Chromium writes the port it picked here
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{binary} exited with {proc.returncode} at start")
        if port_file.is_file() and port_file.read_text().strip():
            return proc, int(port_file.read_text().split()[0])
        time.sleep(0.1)
    raise RuntimeError(f"{binary} did not open its DevTools port in 60 s")


def _stop(proc: subprocess.Popen) -> None:
    """End the browser we started and its helper processes (its own session)."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


@contextlib.contextmanager
def _page(url: str, tmp_path: Path) -> Iterator[_DevTools]:
    """``url`` open in headless Chromium (console collected); skips without a chromium binary."""
    binary = _chromium()
    if binary is None:
        pytest.skip("no chromium binary on PATH (Debian: apt-get install chromium; .ci/install-browser.sh)")
    proc, devtools_port = _launch_chromium(binary, Path(tempfile.mkdtemp(prefix="chromium-", dir=tmp_path)))
    try:
        listing = f"http://127.0.0.1:{devtools_port}/json/list"
        targets = json.loads(urllib.request.urlopen(listing, timeout=30).read())
        cdp = _DevTools(next(t for t in targets if t["type"] == "page")["webSocketDebuggerUrl"])
        cdp.shots_dir = tmp_path
        cdp.call("Runtime.enable")
        cdp.call("Log.enable")
        cdp.call("Emulation.setDeviceMetricsOverride", width=SCREEN_W, height=SCREEN_H, deviceScaleFactor=1,
                 mobile=False)
        cdp.call("Page.navigate", url=url)
        try:
            yield cdp
        finally:
            cdp.close()
    finally:
        _stop(proc)


def _share(im: np.ndarray, rgb: tuple[int, int, int], tol: int) -> float:
    """Share of the scene's pixels (left of the panel) within ``tol`` of ``rgb`` in every channel."""
    return float(_mask(im, rgb, tol).mean())


def _mask(im: np.ndarray, rgb: tuple[int, int, int], tol: int) -> np.ndarray:
    return (np.abs(im[:, :SCENE_W].astype(np.int16) - np.array(rgb)) <= tol).all(axis=-1)


def _teal_share(im: np.ndarray) -> float:
    r, g, b = (im[:, :SCENE_W, i].astype(np.int16) for i in range(3))
    return float(((r < 140) & (g > 150) & (b > 150)).mean())


def _wait_for(cdp: _DevTools, ok, what: str, deadline_s: float = BROWSER_DEADLINE_S) -> np.ndarray:
    """Screenshots until ``ok(image)`` holds (the image), else the test fails naming ``what``."""
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            im = cdp.screenshot()
        except RuntimeError as exc:  # the page is still being swapped in by the navigation
            if "Not attached" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.5)
            continue
        if ok(im):
            return im
        if time.monotonic() > deadline:
            shot = cdp.shots_dir / f"failed_{what.replace(' ', '_')[:40]}.png"
            shot.write_bytes(_png(im))
            pytest.fail(f"{what}: not seen within {deadline_s:.0f} s (last screenshot: {shot})")
        time.sleep(0.5)


def _client(h):
    deadline = time.monotonic() + 30
    while not h.server.get_clients():
        assert time.monotonic() < deadline, "the browser never connected"
        time.sleep(0.1)
    return next(iter(h.server.get_clients().values()))


def _look(client, position, look_at, settle_s: float = 1.0) -> None:
    client.camera.position = tuple(float(v) for v in position)  # viser moves the look-at along
    client.camera.look_at = tuple(float(v) for v in look_at)
    time.sleep(settle_s)


@pytest.mark.slow  # 4-12 s: Chromium's start and software WebGL on a shared 2-core machine
def test_browser_draws_the_splats(viewer_world, small_manifest, tmp_path):
    """Serve the bundle on 127.0.0.1, open it in headless Chromium (software WebGL): the splats fill
    a noticeable share of the first view and shrink with the splat-size slider, the lost and
    relocalized markers show when the camera looks at them, and the console logs no error of ours."""
    with viewer.serve(viewer_world, port=0, compute_layers=False) as h, _page(h.url, tmp_path) as cdp:
        im = _wait_for(cdp, lambda im: _share(im, SPLAT_RGB, SPLAT_TOLERANCE) >= MIN_SPLAT_SHARE,
                       f"splats on {MIN_SPLAT_SHARE:.0%} of the view")
        client = _client(h)
        # Splat size: a quarter of each sigma opens gaps between the sheet's Gaussians (3 cm apart).
        full = _share(im, SPLAT_RGB, SPLAT_TOLERANCE)
        h.summary["widgets"]["splat_size"].value = 0.25
        _wait_for(cdp, lambda im: _share(im, SPLAT_RGB, SPLAT_TOLERANCE) < 0.6 * full, "smaller splats", 30)
        h.summary["widgets"]["splat_size"].value = 1.0
        _wait_for(cdp, lambda im: _share(im, SPLAT_RGB, SPLAT_TOLERANCE) > 0.9 * full, "splats back to size", 30)
        view = h.summary["view"]
        markers = small_manifest.T_world_cam_gt[[LOST, RELOCALIZED], :3, 3].mean(axis=0)
        h.summary["widgets"]["Keyframes"].value = False  # frusta between the markers and this view
        _look(client, markers + 0.5 * (view.pivot - markers), markers)  # from the sheet's side, inside the box
        im = _wait_for(cdp, lambda im: min(_share(im, viewer.LOST_RGB, MARKER_TOLERANCE),
                                           _share(im, viewer.RELOCALIZED_RGB, MARKER_TOLERANCE)) >= MIN_MARKER_SHARE,
                       "the lost and relocalized markers")
        errors = cdp.unexpected_errors()
    (tmp_path / "viewer.png").write_bytes(_png(im))
    assert not errors, f"console errors: {errors}"


def _png(im: np.ndarray) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", im, extension=".png")


@pytest.mark.slow
def test_browser_mesh_and_occupancy_layers_toggle(viewer_world, layer_folders, tmp_path):
    """The mesh and occupancy layers (read from export folders) draw, and switching each off in
    the panel takes its pixels away; the console stays free of errors of ours."""
    with viewer.serve(viewer_world, port=0, layers=layer_folders, compute_layers=False) as h, \
            _page(h.url, tmp_path) as cdp:
        s = h.summary
        assert s["n_mesh_triangles"] == 2 and s["occupancy_cells"]["free"] > 0
        on = _wait_for(cdp, lambda im: _teal_share(im) >= MIN_LAYER_SHARE
                       and _share(im, FREE_RGB, LAYER_TOLERANCE) >= MIN_LAYER_SHARE, "mesh and occupancy layers")
        boxes = s["widgets"]
        boxes["Mesh"].value = False
        no_mesh = _wait_for(cdp, lambda im: _teal_share(im) < MIN_LAYER_SHARE / 10,
                            "the mesh switched off", 30)
        boxes["Occupancy"].value = False
        neither = _wait_for(cdp, lambda im: _share(im, FREE_RGB, LAYER_TOLERANCE) < MIN_LAYER_SHARE / 10,
                            "the occupancy grid switched off", 30)
        boxes["Mesh"].value = True
        _wait_for(cdp, lambda im: _teal_share(im) >= MIN_LAYER_SHARE, "the mesh back on", 30)
        errors = cdp.unexpected_errors()
    for name, im in (("on", on), ("no_mesh", no_mesh), ("neither", neither)):
        (tmp_path / f"layers_{name}.png").write_bytes(_png(im))
    assert _share(no_mesh, FREE_RGB, LAYER_TOLERANCE) >= MIN_LAYER_SHARE, "occupancy went off with the mesh"
    assert not errors, f"console errors: {errors}"


@pytest.mark.slow
def test_browser_slider_drag_and_reset(viewer_world, small_manifest, tmp_path):
    """The frame slider moves the yellow camera and says the frame's status; a 100 px drag keeps
    the camera inside the room's box and near its orbit; Reset view (clicked in the page) returns
    to the first view, pixels and pose."""
    with viewer.serve(viewer_world, port=0, compute_layers=False) as h, _page(h.url, tmp_path) as cdp:
        view = h.summary["view"]
        first = _wait_for(cdp, lambda im: _share(im, SPLAT_RGB, SPLAT_TOLERANCE) >= MIN_SPLAT_SHARE, "the first view")
        client = _client(h)
        slider = h.summary["widgets"]["frame"]
        # Look at the trajectory from the sheet's side to see the marker move along it.
        track = small_manifest.T_world_cam_gt[:, :3, 3]  # [N, 3]: the estimate is 1 cm off
        mid = track.mean(axis=0)
        _look(client, mid + 0.6 * (view.pivot - mid), mid)

        def centroid(im: np.ndarray) -> np.ndarray | None:
            m = _mask(im, SELECTED_RGB, MARKER_TOLERANCE)
            return np.argwhere(m).mean(axis=0) if m.sum() >= MIN_SELECTED_PX else None

        at0 = centroid(_wait_for(cdp, lambda im: centroid(im) is not None, "the selected frame's marker"))
        slider.value = len(track) - 1
        moved = _wait_for(cdp, lambda im: centroid(im) is not None and np.linalg.norm(centroid(im) - at0) > 15,
                          "the marker moving to the last frame", 30)
        slider.value = LOST
        _wait_for(cdp, lambda im: "lost" in (cdp.evaluate("document.body.innerText") or ""), "frame status 'lost'", 30)
        assert f"frame {LOST} of 12" in cdp.evaluate("document.body.innerText").replace("**", "")

        # Back to the first view, then a user's 100 px drag.
        slider.value = 0
        viewer_controls.reset_camera(client.camera, view)
        _wait_for(cdp, lambda im: np.linalg.norm(client.camera.position - view.position) < 1e-3, "reset", 30)
        time.sleep(1.0)
        # The first view once every layer has arrived: the very first screenshot may precede some on a
        # loaded machine, so Reset view is compared with this one.
        settled = cdp.screenshot()
        cdp.drag(100)
        time.sleep(1.5)
        dragged = np.asarray(client.camera.position, float)
        assert np.linalg.norm(dragged - view.position) > 0.05, "the drag did not turn the camera"
        np.testing.assert_allclose(view.clamp(dragged), dragged, atol=0.02)  # inside the room's box
        assert np.linalg.norm(dragged - view.pivot) <= viewer_controls.ORBIT_MAX_FACTOR * view.radius_m + 0.02
        clicked = cdp.evaluate("(() => { const b = [...document.querySelectorAll('button')]"
                               ".find(b => b.innerText.trim() === 'Reset view'); if (b) b.click(); return !!b; })()")
        assert clicked, "no Reset view button in the page"
        _wait_for(cdp, lambda im: np.linalg.norm(client.camera.position - view.position) < 0.01,
                  "the first pose after Reset view", 30)
        back = _wait_for(cdp, lambda im: np.abs(im[:, :SCENE_W].astype(int) - settled[:, :SCENE_W]).mean() < 6,
                         "the first view's pixels after Reset view", 30)
        np.testing.assert_allclose(client.camera.position, view.position, atol=0.01)
        np.testing.assert_allclose(client.camera.look_at, view.pivot, atol=0.01)
        errors = cdp.unexpected_errors()
    for name, im in (("first", first), ("moved", moved), ("back", back)):
        (tmp_path / f"slider_{name}.png").write_bytes(_png(im))
    assert not errors, f"console errors: {errors}"


def test_websocket_refuses_pages_of_other_sites(viewer_world):
    """Any page open in the user's browser can open a websocket to 127.0.0.1; only the viewer's own
    (loopback) pages, and clients that send no Origin, may read the map."""
    import viser
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    with viewer.serve(viewer_world, port=0) as h:
        uri = f"ws://127.0.0.1:{h.server.get_port()}/"
        proto = [f"viser-v{viser.__version__}"]
        for origin in ("https://example.org", "http://127.0.0.1.evil.example:80", "null"):
            with pytest.raises(InvalidStatus) as refused:
                connect(uri, origin=origin, subprotocols=proto, open_timeout=10).close()
            assert refused.value.response.status_code == 403, origin
        for origin in (h.url.rstrip("/"), f"http://localhost:{h.server.get_port()}", None):
            with connect(uri, origin=origin, subprotocols=proto, open_timeout=10) as ws:
                assert ws.subprotocol == proto[0]  # handshake done: the viewer's own page gets in
