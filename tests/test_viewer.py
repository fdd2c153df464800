"""The browser viewer (``atlas-gs view``): the scene it builds from a bundle, its loopback-only
binding, and, in headless Chromium, that the Gaussian splats really draw (pixels, not HTML)."""

from __future__ import annotations

import argparse
import base64
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

import numpy as np
import pytest

pytest.importorskip("viser", reason="viser is not installed (pip install -e .)")

from atlas_pipeline.errors import BundleFormatError, ConfigError  # noqa: E402
from atlas_pipeline.gaussian_world.field import GaussianField  # noqa: E402
from atlas_pipeline.localization.localizer import LocalizationReport  # noqa: E402
from atlas_pipeline.scene_memory.bundle import write_world_bundle  # noqa: E402
from atlas_pipeline.viz import viewer  # noqa: E402

# A colour no viewer chrome uses (viser's UI is white, grey and blue) and no other layer has.
SPLAT_RGB = (230, 20, 230)
SPLAT_TOLERANCE = 70  # per channel: splat edges blend with the white background
MIN_SPLAT_SHARE = 0.05  # of the screenshot; the sheet fills ~11 % of the view when drawn
# Lost (red) and relocalized (orange) markers: ~0.6 % each when drawn; the legend's swatches in the
# panel are ~0.01 %, so this cannot pass on the panel alone.
MIN_MARKER_SHARE = 0.002
MARKER_TOLERANCE = 40
KEYFRAMES = [0, 4, 8]
LOST, RELOCALIZED = 5, 6
SCREEN_W, SCREEN_H = 800, 600
BROWSER_DEADLINE_S = 120.0  # swiftshader on a loaded 2-core machine: first frames take a while
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
    with pytest.raises(ConfigError, match="neither a bundle folder nor a partition"):
        args.func(p.parse_args(["view", "no-such-partition"]))


# ---- headless Chromium ---------------------------------------------------------------------------


def _chromium() -> str | None:
    for name in (os.environ.get("ATLAS_CHROMIUM"), "chromium", "chromium-browser", "google-chrome", "chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


class _DevTools:
    """The few Chrome DevTools Protocol calls the test needs, over the page's websocket."""

    def __init__(self, ws_url: str):
        from websockets.sync.client import connect  # viser's own dependency

        self.ws = connect(ws_url, max_size=None, open_timeout=30)
        self.next_id = 0

    def call(self, method: str, timeout_s: float = 60.0, **params):
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:  # events arrive in between; skip them
            msg = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.1)))
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg["result"]

    def close(self) -> None:
        self.ws.close()


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


def _colour_share(png: bytes, rgb: tuple[int, int, int], tol: int) -> float:
    import imageio.v3 as iio

    im = iio.imread(png)[..., :3].astype(np.int16)  # [H, W, 3]
    return float((np.abs(im - np.array(rgb)) <= tol).all(axis=-1).mean())


@pytest.mark.slow  # 4-12 s: Chromium's start and software WebGL on a shared 2-core machine
def test_browser_draws_the_splats(viewer_world, tmp_path):
    """Serve the bundle on 127.0.0.1, open it in headless Chromium (software WebGL) and wait until
    the splats show: a noticeable share of the screenshot in the Gaussians' colour."""
    binary = _chromium()
    if binary is None:
        pytest.skip("no chromium binary on PATH (Debian: apt-get install chromium; .ci/install-browser.sh)")
    profile = Path(tempfile.mkdtemp(prefix="chromium-", dir=tmp_path))
    t0 = time.monotonic()
    with viewer.serve(viewer_world, port=0) as h:
        proc, devtools_port = _launch_chromium(binary, profile)
        try:
            listing = f"http://127.0.0.1:{devtools_port}/json/list"
            targets = json.loads(urllib.request.urlopen(listing, timeout=30).read())
            page = next(t for t in targets if t["type"] == "page")
            cdp = _DevTools(page["webSocketDebuggerUrl"])
            cdp.call("Emulation.setDeviceMetricsOverride", width=SCREEN_W, height=SCREEN_H, deviceScaleFactor=1,
                     mobile=False)
            cdp.call("Page.navigate", url=h.url)
            shares, png = {}, b""
            deadline = time.monotonic() + BROWSER_DEADLINE_S
            while time.monotonic() < deadline:
                time.sleep(1.0)
                png = base64.b64decode(cdp.call("Page.captureScreenshot", format="png")["data"])
                shares = {"splats": _colour_share(png, SPLAT_RGB, SPLAT_TOLERANCE),
                          "lost": _colour_share(png, viewer.LOST_RGB, MARKER_TOLERANCE),
                          "relocalized": _colour_share(png, viewer.RELOCALIZED_RGB, MARKER_TOLERANCE)}
                markers = min(shares["lost"], shares["relocalized"])
                if shares["splats"] >= MIN_SPLAT_SHARE and markers >= MIN_MARKER_SHARE:
                    break
            cdp.close()
        finally:
            _stop(proc)
    shot = tmp_path / "viewer.png"
    shot.write_bytes(png)  # kept in the test's tmp folder, to look at
    print(f"pixel shares {({k: round(v, 4) for k, v in shares.items()})} after {time.monotonic() - t0:.1f} s; {shot}")
    assert shares["splats"] >= MIN_SPLAT_SHARE, (f"only {shares['splats']:.1%} of the screenshot has the splats' "
                                                 f"colour (want {MIN_SPLAT_SHARE:.0%}); see {shot}")
    for layer in ("lost", "relocalized"):
        assert shares[layer] >= MIN_MARKER_SHARE, f"{layer} markers: {shares[layer]:.2%} of the screenshot; see {shot}"


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
