"""The viewer's camera and controls: where it orbits, how far it may go, the frame slider with its
camera marker, thumbnail and status, reset-view and splat-size.

Orbit (:func:`orbit_view`): viser's camera orbits its look-at point, and a drag turns it by a fixed
angle per pixel (camera-controls: a full turn per canvas height, 60 degrees for 100 px on a 600 px
canvas; viser offers no setting for the rate). So the view is made safe by where the orbit is: about
the middle of the Gaussians (the room's centre), at the cameras' own median distance from it
(where the recording stood: inside a room, around an object), and the camera is kept inside the
room's box (:class:`OrbitView`: the Gaussians' robust box in the frame of the floor's principal
axes, with the keyframes' positions) by pulling each position the browser reports back into it,
and the orbit distance between :data:`ORBIT_MIN_M` and :data:`ORBIT_MAX_FACTOR` times the radius.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["OrbitView", "orbit_view", "FrameTrack", "frame_track", "install_camera_limits", "add_frame_slider",
           "add_view_controls", "SELECTED_RGB", "SPLAT_SCALES"]

SELECTED_RGB = (250, 210, 0)  # yellow: the slider's frame
ORBIT_MIN_RADIUS_M = 0.3
ORBIT_RAISE = 0.35  # of the radius: the start view looks slightly down on the middle
ORBIT_MIN_M = 0.05
ORBIT_MAX_FACTOR = 2.0
ROOM_MARGIN_FRACTION = 0.02  # of the box's diagonal: the camera stays this far inside the box
CLAMP_TOLERANCE_M = 0.01  # a report this close to the box is left alone (no correction loop)
ARM_AFTER_S = 3.0  # the box is enforced once the browser showed the start view, or after this
SPLAT_SCALES = (0.25, 3.0, 0.25)  # splat-size slider: min, max, step (times each Gaussian's sigma)
THUMBNAIL_CACHE = 64


@dataclass
class OrbitView:
    """The start view (``position``, ``pivot``, ``up``, each ``[3]``), the orbit ``radius_m`` and
    the room's box: ``R_box`` ``[3, 3]`` (columns: its axes in the world, the last one up) and
    ``lo``/``hi`` ``[3]`` in its axes."""

    position: np.ndarray
    pivot: np.ndarray
    up: np.ndarray
    radius_m: float
    R_box: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def clamp(self, p: np.ndarray) -> np.ndarray:
        """``p`` ``[3]`` moved into the box (unchanged when inside)."""
        q = self.R_box.T @ np.asarray(p, np.float64)
        return self.R_box @ np.clip(q, self.lo, self.hi)


def _perpendicular(up: np.ndarray) -> np.ndarray:
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    return a / np.linalg.norm(a)


def orbit_view(points: np.ndarray, camera_xyz: np.ndarray, centre: np.ndarray, diag_m: float, up: np.ndarray,
               percentiles: tuple[float, float]) -> OrbitView:
    """The orbit of a world whose Gaussian centres are ``points`` ``[N, 3]`` (robust ``centre`` and
    diagonal ``diag_m``), recorded from cameras at ``camera_xyz`` ``[K, 3]`` (first one first),
    ``up`` ``[3]`` (module docstring)."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    pivot = np.asarray(centre, np.float64)
    cams = np.asarray(camera_xyz, np.float64).reshape(-1, 3)
    cams = cams[np.isfinite(cams).all(axis=1)]
    horiz = (cams - pivot) - np.outer((cams - pivot) @ up, up)
    lengths = np.linalg.norm(horiz, axis=1)
    radius = float(np.clip(np.median(lengths) if len(cams) else 0.5 * diag_m, ORBIT_MIN_RADIUS_M,
                           max(0.5 * diag_m, ORBIT_MIN_RADIUS_M)))
    direction = horiz[0] / lengths[0] if len(cams) and lengths[0] > 1e-6 else _perpendicular(up)
    # The box's horizontal axes: the principal axes of the points on the floor plane (walls of a
    # room are seldom along the world's x and y).
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    e1 = _perpendicular(up)
    if len(pts) >= 3:
        flat = (pts - pivot) - np.outer((pts - pivot) @ up, up)
        w, v = np.linalg.eigh(flat.T @ flat)
        if w[-1] > 0:
            e1 = v[:, -1] - (v[:, -1] @ up) * up
            e1 /= np.linalg.norm(e1)
    R = np.stack([e1, np.cross(up, e1), up], axis=1)
    local = (pts if len(pts) else pivot[None]) @ R
    lo, hi = np.percentile(local, percentiles, axis=0)
    if len(cams):
        lo, hi = np.minimum(lo, (cams @ R).min(axis=0)), np.maximum(hi, (cams @ R).max(axis=0))
    margin = ROOM_MARGIN_FRACTION * diag_m
    lo, hi = lo + margin, hi - margin
    mid = (lo + hi) / 2
    lo, hi = np.minimum(lo, mid), np.maximum(hi, mid)  # a box thinner than two margins: its middle plane
    view = OrbitView(pivot + radius * direction + ORBIT_RAISE * radius * up, pivot, up, radius, R, lo, hi)
    view.position = view.clamp(view.position)
    return view


def install_camera_limits(server: Any, view: OrbitView) -> None:
    """For every browser that connects: the orbit distance limits, and each camera position it
    reports outside the room's box pulled back in (the look-at kept)."""

    def on_connect(client: Any) -> None:
        cam = client.camera
        cam.min_orbit_distance = ORBIT_MIN_M
        cam.max_orbit_distance = max(ORBIT_MAX_FACTOR * view.radius_m, 2 * ORBIT_MIN_M)
        armed = [False]
        connected = time.monotonic()

        def keep_inside(camera: Any) -> None:
            p = np.asarray(camera.position, np.float64)
            if not np.isfinite(p).all():
                return
            if not armed[0]:
                # A browser reports its default camera before it applies the start view; moving
                # that one would override the start view.
                armed[0] = (np.linalg.norm(p - view.position) < 0.05 * view.radius_m
                            or time.monotonic() - connected > ARM_AFTER_S)
                if not armed[0]:
                    return
            q = view.clamp(p)
            if np.linalg.norm(q - p) > CLAMP_TOLERANCE_M:
                look_at = tuple(float(v) for v in camera.look_at)
                camera.position = tuple(float(v) for v in q)  # viser moves the look-at along: put it back
                camera.look_at = look_at

        cam.on_update(keep_inside)

    server.on_client_connect(on_connect)


def reset_camera(camera: Any, view: OrbitView) -> None:
    """``camera`` (a viser ``CameraHandle``) back to the start view."""
    camera.up_direction = tuple(float(v) for v in view.up)
    camera.position = tuple(float(v) for v in view.position)  # moves the look-at along: set it after
    camera.look_at = tuple(float(v) for v in view.pivot)


@dataclass
class FrameTrack:
    """What the slider walks: ``T_world_cam`` ``[N, 4, 4]`` (NaN: not known), ``status`` (N
    strings), ``frame_indices`` ``[N]`` (into the frame's recording, -1: none), ``timestamps_s``
    ``[N]`` or None, and ``manifest``: the frames' recording, or a list of N (each frame's own: the
    keyframes of an extended world come from several recordings), None for no images."""

    T_world_cam: np.ndarray
    status: list[str]
    frame_indices: np.ndarray
    timestamps_s: np.ndarray | None
    manifest: Any
    label: str

    def __len__(self) -> int:
        return len(self.status)

    def manifest_of(self, k: int) -> Any:
        """The recording frame ``k`` is one of (None: its images are not available)."""
        return self.manifest[k] if isinstance(self.manifest, list) else self.manifest


def frame_track(T_est: np.ndarray, T_gt: np.ndarray | None, status: list[str], timestamps_s: np.ndarray | None,
                report_manifest: Any, keyframe_T: np.ndarray, keyframe_indices: np.ndarray,
                keyframe_manifest: Any) -> FrameTrack:
    """The localization report's frames (each at its estimate, else its ground truth) when there is
    one, else the keyframes (``keyframe_manifest``: their recording, or a list of each one's)."""
    if len(status):
        T = np.array(T_est, np.float64)
        if T_gt is not None and len(T_gt) == len(T):
            unknown = ~np.isfinite(T).all(axis=(1, 2))
            T[unknown] = T_gt[unknown]
        return FrameTrack(T, list(status), np.arange(len(T)), timestamps_s, report_manifest, "frame")
    return FrameTrack(np.asarray(keyframe_T, np.float64), ["keyframe"] * len(keyframe_T),
                      np.asarray(keyframe_indices, np.int64), None, keyframe_manifest, "keyframe")


def _wxyz(R: np.ndarray) -> tuple[float, ...]:
    from atlas_pipeline.geometry import rotmat_to_quat_xyzw

    q = rotmat_to_quat_xyzw(R)
    return (float(q[3]), float(q[0]), float(q[1]), float(q[2]))


def add_frame_slider(server: Any, track: FrameTrack, fov_y: float, aspect: float, frustum_m: float, marker_m: float,
                     thumbnail: Callable[[np.ndarray], np.ndarray], status_rgb: dict[str, tuple[int, int, int]]) -> Any:
    """A slider over ``track``: a yellow camera (frustum and dot) at the frame's pose, its image
    (read from the recording when it moves, one small thumbnail at a time) and its status.
    Returns the slider's handle (None for an empty track)."""
    if not len(track):
        return None
    scene, gui = server.scene, server.gui
    frustum = scene.add_camera_frustum("/selected/frustum", fov=fov_y, aspect=aspect, scale=1.6 * frustum_m,
                                       color=SELECTED_RGB, thickness=3.0, thickness_units="screen",
                                       cast_shadow=False, receive_shadow=False, visible=False)
    dot = scene.add_point_cloud("/selected/dot", points=np.zeros((1, 3), np.float32), colors=SELECTED_RGB,
                                point_size=1.3 * marker_m, point_shape="circle", point_shading="flat", visible=False)
    folder = gui.add_folder("Frames")
    with folder:
        slider = gui.add_slider(track.label.capitalize(), min=0, max=max(len(track) - 1, 1), step=1, initial_value=0,
                                disabled=len(track) < 2)
        text = gui.add_markdown("")
        image = gui.add_image(np.full((12, 16, 3), 235, np.uint8), visible=False)

    @functools.lru_cache(maxsize=THUMBNAIL_CACHE)
    def frame_image(k: int) -> np.ndarray | None:
        """Thumbnail of track entry ``k``: frame ``frame_indices[k]`` of its own recording."""
        from atlas_pipeline.errors import AtlasError

        m, i = track.manifest_of(k), int(track.frame_indices[k])
        if m is None or not 0 <= i < m.n_frames:
            return None
        try:
            return thumbnail(m.read_rgb(i))
        except (AtlasError, OSError, ValueError) as exc:
            logger.warning("frame %d of '%s': image not shown (%s)", i, m.dataset, exc)
            return None

    def show(k: int) -> None:
        k = int(np.clip(k, 0, len(track) - 1))
        T = track.T_world_cam[k]
        known = bool(np.isfinite(T).all())
        if known:
            frustum.wxyz, frustum.position = _wxyz(T[:3, :3]), tuple(float(v) for v in T[:3, 3])
            dot.position = tuple(float(v) for v in T[:3, 3])
        frustum.visible = dot.visible = known
        st = track.status[k]
        rgb = status_rgb.get(st)
        swatch = f"<span style='color:rgb{rgb}'>&#9632;</span> " if rgb else ""
        when = f", t = {track.timestamps_s[k]:.2f} s" if track.timestamps_s is not None else ""
        where = "" if known else " (no pose: not drawn)"
        i = int(track.frame_indices[k])
        m = track.manifest_of(k)
        of = f" of '{m.dataset}'" if isinstance(track.manifest, list) and m is not None else ""
        text.content = (f"{track.label} **{k}** of {len(track)} (dataset frame {i}{of}{when}): "
                        f"{swatch}**{st}**{where}")
        img = frame_image(k) if i >= 0 else None
        if img is not None:
            image.image = img
        image.visible = img is not None

    slider.on_update(lambda _e: show(slider.value))
    show(0)
    return slider


def add_view_controls(server: Any, view: OrbitView, splats: Any, base_covariances: np.ndarray | None) -> dict[str, Any]:
    """Reset-view button (every browser's camera back to the start view, or the clicking one's)
    and, with Gaussians, a splat-size slider (each Gaussian's sigma times the value)."""
    gui = server.gui
    out: dict[str, Any] = {}
    folder = gui.add_folder("View")
    with folder:
        reset = gui.add_button("Reset view")

        def on_reset(event: Any) -> None:
            clients = [event.client] if event.client is not None else list(server.get_clients().values())
            for c in clients:
                reset_camera(c.camera, view)

        reset.on_click(on_reset)
        out["reset"] = reset
        if splats is not None and base_covariances is not None and len(base_covariances):
            lo, hi, step = SPLAT_SCALES
            size = gui.add_slider("Splat size", min=lo, max=hi, step=step, initial_value=1.0)

            def on_size(_event: Any) -> None:
                s = float(size.value)
                splats.covariances = (base_covariances * (s * s)).astype(np.float32)

            size.on_update(on_size)
            out["splat_size"] = size
    return out


def thinned_indices(n: int, max_n: int) -> np.ndarray:
    """At most ``max_n`` of ``range(n)``, evenly spread, the first and last included."""
    if n <= max_n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_n).round().astype(int))


def frustum_size(diag_m: float, n_drawn: int, fraction: float, size_range: tuple[float, float]) -> float:
    """Frustum size (m): a fraction of the world's size, smaller as more are drawn (a fan of a
    dozen at the full size hides what they look at)."""
    return float(np.clip(fraction * diag_m / math.sqrt(max(n_drawn, 4) / 4.0), *size_range))
