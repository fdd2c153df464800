"""The synthetic room (or suite) and its objects: placement, and the per-surface texture table.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import logging
import numpy as np

from atlas_pipeline.sensors.synthetic_path import _PATH_A_M, _PATH_B_M

if TYPE_CHECKING:
    from atlas_pipeline.sensors.synthetic_spec import SyntheticSpec

__all__ = ["ROOM_MIN", "ROOM_MAX", "SceneObject", "SyntheticScene", "build_scene", "textured_scene", "scene_of"]

logger = logging.getLogger(__name__)


ROOM_MIN = np.array([-3.0, -2.5, 0.0])
ROOM_MAX = np.array([3.0, 2.5, 3.0])
# Objects stand inside this footprint and > 0.55 m (horizontally) from the path ellipse.
_OBJ_REGION_XY = (1.4, 1.0)
_MIN_CLEARANCE_M = 0.55
# Surface ids: room surfaces first, then one per object.
_SID_FLOOR, _SID_CEILING = 0, 1
_SID_WALL_XMIN, _SID_WALL_XMAX, _SID_WALL_YMIN, _SID_WALL_YMAX = 2, 3, 4, 5
_N_ROOM_SURFACES = 6
_NOISE_N = 64  # value-noise lattice is periodic with 64 cells per axis
# Rows of the packed per-surface texture table (SyntheticScene.texture_table()).
_T_C0, _T_C1, _T_SCALE, _T_OFF, _T_CHK, _T_STRIPE = 0, 3, 6, 7, 10, 12
_T_ROWS = 16


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One object standing on the floor.

    Attributes:
        kind: ``"box"``, ``"sphere"`` or ``"cylinder"`` (vertical axis).
        centre: ``[3]`` box centre, sphere centre, or cylinder axis point at mid height.
        half_size: ``[3]`` box half extents; for a sphere ``(r, r, r)``; for a cylinder
            ``(r, r, h/2)``.
        surface_id: index into the scene's texture table.
    """

    kind: str
    centre: np.ndarray
    half_size: np.ndarray
    surface_id: int


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """Room, objects and per-surface textures of one seed.

    Attributes:
        seed: the seed it was built from.
        room_min, room_max: ``[3]`` corners of the room box.
        objects: the objects, each with its own surface id.
        noise: ``[65 * 65 * 65]`` float32 value-noise lattice in [0, 1], flattened; periodic with
            64 cells per axis (index 64 repeats index 0, so corner lookups need no wrap).
        tex_c0, tex_c1: ``[S, 3]`` the two colours each surface's noise blends between.
        tex_scale: ``[S]`` noise lattice cells per metre of the coarsest octave.
        tex_offset: ``[S, 3]`` lattice offset, so surfaces do not share noise.
        checker_size: ``[S]`` checker cell size in metres (0 = none).
        checker_contrast: ``[S]`` darkening of odd checker cells.
        stripe_dir: ``[S, 3]`` stripe wave vector in cycles per metre.
        stripe_contrast: ``[S]`` stripe darkening amplitude.
    """

    seed: int
    room_min: np.ndarray
    room_max: np.ndarray
    objects: tuple[SceneObject, ...]
    noise: np.ndarray = field(repr=False)
    tex_c0: np.ndarray
    tex_c1: np.ndarray
    tex_scale: np.ndarray
    tex_offset: np.ndarray
    checker_size: np.ndarray
    checker_contrast: np.ndarray
    stripe_dir: np.ndarray
    stripe_contrast: np.ndarray

    def texture_table(self) -> np.ndarray:
        """All texture parameters packed as ``[16, S]`` float32 (rows: c0 rgb, c1 rgb, scale,
        offset xyz, 1 / checker size (0 = none), checker contrast, stripe xyz, stripe contrast)."""
        tab = np.zeros((_T_ROWS, self.tex_c0.shape[0]), dtype=np.float32)
        tab[_T_C0:_T_C0 + 3] = self.tex_c0.T
        tab[_T_C1:_T_C1 + 3] = self.tex_c1.T
        tab[_T_SCALE] = self.tex_scale
        tab[_T_OFF:_T_OFF + 3] = self.tex_offset.T
        cs = self.checker_size
        tab[_T_CHK] = np.where(cs > 0, 1.0 / np.where(cs > 0, cs, 1.0), 0.0)
        tab[_T_CHK + 1] = self.checker_contrast
        tab[_T_STRIPE:_T_STRIPE + 3] = self.stripe_dir.T
        tab[_T_STRIPE + 3] = self.stripe_contrast
        return tab

    def clearance_m(self, points_xyz: np.ndarray) -> np.ndarray:
        """Distance ``[N]`` from points ``[N, 3]`` to the nearest wall or object surface.

        Points inside an object get 0, points outside the room a negative distance.
        """
        p = np.atleast_2d(np.asarray(points_xyz, dtype=np.float64))
        d = np.minimum(p - self.room_min, self.room_max - p).min(axis=1)
        for obj in self.objects:
            d = np.minimum(d, _object_distance(obj, p))
        return d


def _object_distance(obj: SceneObject, p: np.ndarray) -> np.ndarray:
    """Euclidean distance ``[N]`` from points ``[N, 3]`` to the object (0 inside)."""
    c, h = obj.centre, obj.half_size
    if obj.kind == "box":
        q = np.maximum(np.abs(p - c) - h, 0.0)
        return np.linalg.norm(q, axis=1)
    if obj.kind == "sphere":
        return np.maximum(np.linalg.norm(p - c, axis=1) - h[0], 0.0)
    # Cylinder: radial and axial excess combine like a 2D box distance.
    radial = np.maximum(np.linalg.norm(p[:, :2] - c[:2], axis=1) - h[0], 0.0)
    axial = np.maximum(np.abs(p[:, 2] - c[2]) - h[2], 0.0)
    return np.hypot(radial, axial)


def _footprint_radius(kind: str, half: np.ndarray) -> float:
    """Horizontal radius of a bounding circle (used for spacing and clearance checks)."""
    return float(np.hypot(half[0], half[1])) if kind == "box" else float(half[0])


def _ellipse_clearance(xy: np.ndarray, r: float) -> float:
    """Smallest horizontal distance from a disc (centre ``xy`` ``[2]``, radius ``r``) to the
    camera path ellipse."""
    th = np.linspace(0.0, 2.0 * np.pi, 2048, endpoint=False)
    ex = _PATH_A_M * np.cos(th)
    ey = _PATH_B_M * np.sin(th)
    return float(np.min(np.hypot(ex - xy[0], ey - xy[1]))) - r


def _place_objects(rng: np.random.Generator, kinds: list[str]) -> list[SceneObject] | None:
    """Rejection-sample non-overlapping objects of ``kinds`` standing on the floor.

    A draw that cannot fit every object starts over (up to 50 times), so a scene always has all
    of its objects; returns None if even that fails.
    """
    rx, ry = _OBJ_REGION_XY
    for _restart in range(50):
        objects: list[SceneObject] = []
        placed: list[tuple[np.ndarray, float]] = []
        for kind in kinds:
            for _attempt in range(300):
                if kind == "box":
                    half = np.array(
                        [rng.uniform(0.15, 0.35), rng.uniform(0.15, 0.3), rng.uniform(0.15, 0.5)]
                    )
                elif kind == "sphere":
                    r = rng.uniform(0.18, 0.35)
                    half = np.array([r, r, r])
                else:
                    r = rng.uniform(0.12, 0.25)
                    half = np.array([r, r, rng.uniform(0.25, 0.6)])
                xy = np.array([rng.uniform(-rx, rx), rng.uniform(-ry, ry)])
                # The whole footprint must lie inside the object region.
                if abs(xy[0]) + half[0] > rx or abs(xy[1]) + half[1] > ry:
                    continue
                fr = _footprint_radius(kind, half)
                if any(np.linalg.norm(xy - pxy) < fr + pr + 0.1 for pxy, pr in placed):
                    continue
                if _ellipse_clearance(xy, fr) < _MIN_CLEARANCE_M:
                    continue
                break
            else:  # too crowded for this draw
                break
            placed.append((xy, fr))
            centre = np.array([xy[0], xy[1], half[2]])  # resting on the floor
            objects.append(SceneObject(kind, centre, half, _N_ROOM_SURFACES + len(objects)))
        if len(objects) == len(kinds):
            return objects
        logger.debug("synthetic scene: %d of %d objects fit, retrying", len(objects), len(kinds))
    return None


def build_scene(seed: int) -> SyntheticScene:
    """Room and 4-6 objects placed from ``seed`` (``numpy.random.default_rng(seed)``).

    Objects (at least two boxes, a sphere and a cylinder) are rejection-sampled so they do not
    overlap and stay more than 0.55 m (horizontally) from the camera path ellipse for any phase,
    which keeps every camera pose clear of them.
    """
    rng = np.random.default_rng(seed)
    n_obj = int(rng.integers(4, 7))
    kinds = ["box", "box", "sphere", "cylinder"] + [
        str(k) for k in rng.choice(["box", "sphere", "cylinder"], size=n_obj - 4)
    ]
    kinds = [kinds[i] for i in rng.permutation(n_obj)]

    objects = _place_objects(rng, kinds)
    if objects is None:
        # Never observed (300 seeds checked); fail loudly rather than build a different scene.
        raise RuntimeError(f"synthetic scene {seed}: could not place {kinds}")
    return textured_scene(seed, rng, objects, ROOM_MIN, ROOM_MAX)


def textured_scene(seed: int, rng: np.random.Generator, objects: list[SceneObject], room_min: np.ndarray,
                   room_max: np.ndarray, flat_ids: tuple[int, ...] = ()) -> SyntheticScene:
    """The scene of ``objects`` in the box ``room_min``..``room_max`` ``[3]`` with textures drawn
    from ``rng``; objects whose surface id is in ``flat_ids`` (partition walls) get wallpaper
    instead of an object's saturated colour."""
    n_surf = _N_ROOM_SURFACES + len(objects)
    noise = rng.random((_NOISE_N,) * 3, dtype=np.float32)
    noise = np.pad(noise, ((0, 1),) * 3, mode="wrap").ravel()  # [65^3], see SyntheticScene.noise

    # Room palette: warm floor, light walls with distinct tints, pale ceiling.
    c0 = np.zeros((n_surf, 3))
    c1 = np.zeros((n_surf, 3))
    c0[_SID_FLOOR], c1[_SID_FLOOR] = (0.55, 0.36, 0.2), (0.85, 0.65, 0.42)
    c0[_SID_CEILING], c1[_SID_CEILING] = (0.6, 0.6, 0.62), (0.95, 0.95, 0.9)
    wall_tints = [(0.75, 0.55, 0.5), (0.5, 0.65, 0.75), (0.6, 0.72, 0.5), (0.78, 0.72, 0.5)]
    for k, tint in enumerate(wall_tints):
        t = np.array(tint)
        c0[_SID_WALL_XMIN + k], c1[_SID_WALL_XMIN + k] = 0.45 * t, np.minimum(1.0, 1.25 * t)
    for obj in objects:
        base = rng.uniform(0.15, 0.95, size=3)
        base[rng.integers(3)] = rng.uniform(0.75, 1.0)  # one strong channel: saturated colour
        if obj.surface_id in flat_ids:
            base = 0.55 + 0.4 * base  # a painted wall: pale
        c0[obj.surface_id] = 0.35 * base if obj.surface_id not in flat_ids else 0.6 * base
        c1[obj.surface_id] = base

    tex_scale = np.full(n_surf, 2.0)
    tex_scale[_N_ROOM_SURFACES:] = rng.uniform(3.0, 5.0, size=len(objects))
    tex_offset = rng.uniform(0.0, _NOISE_N, size=(n_surf, 3))
    checker_size = np.zeros(n_surf)
    checker_contrast = np.zeros(n_surf)
    checker_size[_SID_FLOOR], checker_contrast[_SID_FLOOR] = 0.5, 0.25  # floor tiles
    checker_size[_SID_CEILING], checker_contrast[_SID_CEILING] = 0.6, 0.12
    stripe_dir = np.zeros((n_surf, 3))
    stripe_contrast = np.zeros(n_surf)
    # Wallpaper: vertical stripes on x walls, slanted ones on y walls.
    stripe_dir[_SID_WALL_XMIN] = stripe_dir[_SID_WALL_XMAX] = (0.0, 4.0, 0.0)
    stripe_dir[_SID_WALL_YMIN] = stripe_dir[_SID_WALL_YMAX] = (3.0, 0.0, 2.0)
    stripe_contrast[_SID_WALL_XMIN:_SID_WALL_YMAX + 1] = 0.3
    for obj in objects:
        sid = obj.surface_id
        if obj.kind == "sphere":
            checker_size[sid], checker_contrast[sid] = rng.uniform(0.08, 0.14), 0.35
        elif obj.kind == "cylinder":
            stripe_dir[sid] = (0.0, 0.0, rng.uniform(5.0, 8.0))  # horizontal rings
            stripe_contrast[sid] = 0.35
        else:
            v = rng.normal(size=3)
            stripe_dir[sid] = v / np.linalg.norm(v) * rng.uniform(4.0, 7.0)
            stripe_contrast[sid] = 0.25

    return SyntheticScene(
        seed=seed,
        room_min=np.asarray(room_min, np.float64).copy(),
        room_max=np.asarray(room_max, np.float64).copy(),
        objects=tuple(objects),
        noise=noise,
        tex_c0=c0.astype(np.float32),
        tex_c1=c1.astype(np.float32),
        tex_scale=tex_scale.astype(np.float32),
        tex_offset=tex_offset.astype(np.float32),
        checker_size=checker_size.astype(np.float32),
        checker_contrast=checker_contrast.astype(np.float32),
        stripe_dir=stripe_dir.astype(np.float32),
        stripe_contrast=stripe_contrast.astype(np.float32),
    )


def scene_of(spec: SyntheticSpec) -> SyntheticScene:
    """The scene ``spec`` renders: the room of ``build_scene(seed)`` or the suite of that seed."""
    if spec.place == "suite":
        from atlas_pipeline.sensors.synthetic_places import build_suite_scene

        return build_suite_scene(spec.seed)
    return build_scene(spec.seed)
