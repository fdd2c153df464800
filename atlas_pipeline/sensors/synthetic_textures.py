"""Procedural surface colour (value-noise fBm, checker, stripes; a function of the 3D point) and
Lambertian shading from fixed directional lights.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from atlas_pipeline.sensors.synthetic_scene import _NOISE_N, _T_C0, _T_C1, _T_CHK, _T_OFF, _T_SCALE, _T_STRIPE

if TYPE_CHECKING:
    from atlas_pipeline.sensors.synthetic_scene import SyntheticScene


# Lighting: ambient + a key light from above and a weak fill, both directional (view-independent).
_AMBIENT = 0.35
_LIGHTS = (
    (np.array([0.5, 0.35, 1.0]) / np.linalg.norm([0.5, 0.35, 1.0]), 0.55),
    (np.array([-0.6, -0.4, 0.3]) / np.linalg.norm([-0.6, -0.4, 0.3]), 0.2),
)
_EPS_T = 1e-6


def _value_noise(lattice: np.ndarray, qx, qy, qz) -> np.ndarray:
    """Trilinear value noise ``[N]`` in [0, 1] at lattice coordinates ``q*`` ``[N]`` (float32).

    ``lattice`` is the flattened ``[65, 65, 65]`` padded lattice (period 64), so the ``+1``
    corners never need a second wrap.
    """
    n, s = _NOISE_N, _NOISE_N + 1
    fx, fy, fz = np.floor(qx), np.floor(qy), np.floor(qz)
    ux, uy, uz = qx - fx, qy - fy, qz - fz
    # Smoothstep weights: C1 continuous noise, so image gradients have no seams at cell borders.
    ux = ux * ux * (3.0 - 2.0 * ux)
    uy = uy * uy * (3.0 - 2.0 * uy)
    uz = uz * uz * (3.0 - 2.0 * uz)
    base = ((fx.astype(np.int32) & (n - 1)) * s + (fy.astype(np.int32) & (n - 1))) * s + (
        fz.astype(np.int32) & (n - 1)
    )
    g = lattice
    v000, v001 = g.take(base), g.take(base + 1)
    v010, v011 = g.take(base + s), g.take(base + s + 1)
    v100, v101 = g.take(base + s * s), g.take(base + s * s + 1)
    v110, v111 = g.take(base + s * s + s), g.take(base + s * s + s + 1)
    a = v000 + (v001 - v000) * uz
    b = v010 + (v011 - v010) * uz
    c = v100 + (v101 - v100) * uz
    d = v110 + (v111 - v110) * uz
    a = a + (b - a) * uy
    c = c + (d - c) * uy
    return a + (c - a) * ux


def _tri(x: np.ndarray) -> np.ndarray:
    """Triangle wave in [0, 1] with period 1 (a sine look-alike without transcendental calls)."""
    return np.abs(2.0 * (x - np.floor(x)) - 1.0)


def _albedo(scene: SyntheticScene, P: np.ndarray, sid: np.ndarray) -> np.ndarray:
    """Surface colour ``[N, 3]`` float32 at world points ``P`` ``[N, 3]`` with surface ids ``[N]``.

    A pure function of the 3D point and surface, hence identical from every viewpoint.
    """
    # One gather of all per-surface parameters: rows are contiguous [N] arrays.
    tab = scene.texture_table()[:, sid]  # [16, N]
    px, py, pz = (P[:, a].astype(np.float32) for a in range(3))
    scale = tab[_T_SCALE]
    qx = px * scale + tab[_T_OFF]
    qy = py * scale + tab[_T_OFF + 1]
    qz = pz * scale + tab[_T_OFF + 2]
    # fBm, 4 octaves; lacunarity 2.37 (non-integer) so lattices of different octaves do not align.
    f = _value_noise(scene.noise, qx, qy, qz)
    amp, total = 1.0, 1.0
    for k in range(1, 4):
        amp *= 0.7  # strong fine octaves: gradients at pixel scale, not only large blotches
        m = np.float32(2.37**k)
        shift = np.float32(13.7 * k)
        octave = _value_noise(scene.noise, qx * m + shift, qy * m + shift, qz * m + shift)
        f += np.float32(amp) * octave
        total += amp
    # Stretch the fBm (which clusters near 0.5) to use the full colour range.
    w = np.clip(f * np.float32(2.6 / total) - np.float32(0.8), 0.0, 1.0)

    # Checker (offset by 0.37 cells so planes at round coordinates do not sit on a cell border)
    # and stripes multiply the colour.
    inv_cs = tab[_T_CHK]
    parity = (
        np.floor(px * inv_cs + 0.37) + np.floor(py * inv_cs + 0.37) + np.floor(pz * inv_cs + 0.37)
    )
    odd = parity - 2.0 * np.floor(parity * 0.5)
    phase = px * tab[_T_STRIPE] + py * tab[_T_STRIPE + 1] + pz * tab[_T_STRIPE + 2]
    mod = 1.0 - tab[_T_CHK + 1] * odd - tab[_T_STRIPE + 3] * _tri(phase)
    col = np.empty((P.shape[0], 3), dtype=np.float32)
    for c in range(3):
        c0 = tab[_T_C0 + c]
        col[:, c] = (c0 + (tab[_T_C1 + c] - c0) * w) * mod
    return col


def _shade(nrm: np.ndarray) -> np.ndarray:
    """Lambertian irradiance ``[N]`` float32 from the fixed lights (view-independent)."""
    s = np.full(nrm.shape[0], _AMBIENT, dtype=np.float64)
    for ldir, w in _LIGHTS:
        ndl = nrm[:, 0] * ldir[0] + nrm[:, 1] * ldir[1] + nrm[:, 2] * ldir[2]
        s += w * np.maximum(ndl, 0.0)
    return s.astype(np.float32)
