"""The keyframe fit's optimizer: its state (the Gaussians in 3DGS's parametrisation and their Adam
moments) and one fused Adam step over every Gaussian (selective or dense)."""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from atlas_pipeline.gaussian_world.field import GaussianField, canonicalize, sh_rest_count
from atlas_pipeline.gaussian_world.fit_kernels import N_PARAM, P_COL, P_LOG_SCALE, P_LOGIT, P_POS, P_ROT, P_SH
from atlas_pipeline.gaussian_world.raster import GaussianArrays
from atlas_pipeline.geometry import quat_xyzw_to_rotmat

logger = logging.getLogger(__name__)

__all__ = ["ADAM_BLOCK", "LOGIT_CLAMP", "CHILD_ID_BIT", "AdamHyper", "FitParams", "FitState", "adam_step",
           "bias_corrections"]

LOGIT_CLAMP = 12.0  # opacity logits stay within +-12 (sigmoid 6e-6 .. 1 - 6e-6)
# Ids of Gaussians made by densification: the top bit (voxel ids use 63 bits) and a counter.
CHILD_ID_BIT = np.uint64(1 << 63)


class AdamHyper(NamedTuple):
    """One step's Adam settings."""

    lr: np.ndarray  # [R] float64 step size per gradient row (P_* rows; R = N_PARAM + 3 K with SH)
    beta1: float
    beta2: float
    eps: float
    inv_bias1: np.ndarray  # [T + 1] float32 1 / (1 - beta1 ** t), t = a step count
    inv_bias2: np.ndarray  # [T + 1] float32
    t_all: int  # the fit's step (dense Adam's bias correction)
    log_scale_min: float  # clamp of the log scales (log metres)
    log_scale_max: float


_NO_SH = np.zeros((0, 0, 3), np.float32)


class FitParams(NamedTuple):
    """The fitted parameters (float32, in place) and the values derived from them."""

    positions: np.ndarray  # [N, 3] world (m)
    log_scales: np.ndarray  # [N, 3] log metres
    rotations_xyzw: np.ndarray  # [N, 4] unit quaternions
    logits: np.ndarray  # [N] opacity logits
    colors01: np.ndarray  # [N, 3] in [0, 1]
    scales: np.ndarray  # [N, 3] exp(log_scales)
    opacities: np.ndarray  # [N] sigmoid(logits)
    sh_rest: np.ndarray = _NO_SH  # [N, K', 3] SH coefficients; the first (R - N_PARAM) / 3 are stepped


ADAM_BLOCK = 2048  # Gaussians per block of the fused Adam pass


@njit(cache=True, parallel=True)
def adam_step(gparam, m1, m2, hyper, params, seen, n_steps):
    """One Adam step (moments per element) with the step sizes ``hyper.lr [R]`` (per gradient
    row, :class:`AdamHyper`); then the clamps (log scales to ``[log_scale_min, log_scale_max]``,
    logits to +-``LOGIT_CLAMP``, colours to [0, 1]), the rotation update ``q <- q exp(w)`` and the
    derived ``scales = exp(log_scales)``, ``opacities = sigmoid(logits)``, all in ``params``
    (:class:`FitParams`), in place.

    ``hyper.inv_bias1``, ``inv_bias2`` ``[T + 1]`` float32: ``1 / (1 - b ** t)`` for each step
    count ``t`` (:func:`bias_corrections`). ``seen [N]`` uint8, ``n_steps [N]`` int32 (empty arrays: dense):
    selective Adam, only the Gaussians the view draws (``seen``) step, each with the bias
    correction of its own step count ``n_steps`` (counted up here); the others keep their
    parameters and moments. Dense (3DGS): every Gaussian steps, with the bias correction of the
    fit's step ``t_all``, and unseen Gaussians keep moving on their momentum.

    ``gparam``, ``m1``, ``m2`` are ``[R, N]`` float32 (one row per scalar parameter: ``N_PARAM``,
    then ``3 K`` SH coefficients ``P_SH + 3 k + c``, stepped without a clamp), so the
    moment update runs along contiguous float32 rows; blocks of ``ADAM_BLOCK`` Gaussians
    run in parallel, each then applies its steps Gaussian by Gaussian."""
    lr, b1, b2, eps, ibc1_t, ibc2_t, t_all, lo, hi = hyper
    pos, log_s, quat, logit, col, scl, opa, sh = params
    n = pos.shape[0]
    n_rows = gparam.shape[0]
    n_sh = (n_rows - N_PARAM) // 3
    selective = seen.shape[0] == n
    n_blocks = (n + ADAM_BLOCK - 1) // ADAM_BLOCK
    fb1 = np.float32(b1)
    fb2 = np.float32(b2)
    c1 = np.float32(1.0 - b1)
    c2 = np.float32(1.0 - b2)
    feps = np.float32(eps)
    for blk in prange(n_blocks):
        i0 = blk * ADAM_BLOCK
        i1 = min(n, i0 + ADAM_BLOCK)
        d = np.empty((n_rows, i1 - i0), dtype=np.float32)
        on = np.ones(i1 - i0, dtype=np.bool_)
        ibc1 = np.empty(i1 - i0, dtype=np.float32)  # 1 / the bias corrections, per Gaussian
        ibc2 = np.empty(i1 - i0, dtype=np.float32)
        for j in range(i1 - i0):
            t = t_all
            if selective:
                on[j] = seen[i0 + j] != 0
                if on[j]:
                    n_steps[i0 + j] += 1
                t = n_steps[i0 + j]
            ibc1[j] = ibc1_t[t]
            ibc2[j] = ibc2_t[t]
        for c in range(n_rows):
            step = np.float32(-lr[c])
            g = gparam[c, i0:i1]
            mm = m1[c, i0:i1]
            vv = m2[c, i0:i1]
            dc = d[c]
            for j in range(i1 - i0):
                if not on[j]:
                    continue
                gj = g[j]
                mj = fb1 * mm[j] + c1 * gj
                vj = fb2 * vv[j] + c2 * gj * gj
                mm[j] = mj
                vv[j] = vj
                dc[j] = step * (mj * ibc1[j]) / (np.sqrt(vj * ibc2[j]) + feps)
        for j in range(i1 - i0):
            if not on[j]:
                continue
            i = i0 + j
            for c in range(3):
                pos[i, c] += d[P_POS + c, j]
                ls = min(hi, max(lo, np.float64(log_s[i, c]) + d[P_LOG_SCALE + c, j]))
                log_s[i, c] = ls
                scl[i, c] = math.exp(np.float64(log_s[i, c]))
                col[i, c] = min(1.0, max(0.0, np.float64(col[i, c]) + d[P_COL + c, j]))
            for k in range(n_sh):
                for c in range(3):
                    sh[i, k, c] += d[P_SH + 3 * k + c, j]
            w0 = np.float64(d[P_ROT + 0, j])
            w1 = np.float64(d[P_ROT + 1, j])
            w2 = np.float64(d[P_ROT + 2, j])
            angle = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            kq = math.sin(0.5 * angle) / angle if angle > 1e-12 else 0.5  # sin(half) / angle -> 1/2
            bx = w0 * kq
            by = w1 * kq
            bz = w2 * kq
            bw = math.cos(0.5 * angle)
            ax = np.float64(quat[i, 0])
            ay = np.float64(quat[i, 1])
            az = np.float64(quat[i, 2])
            aw = np.float64(quat[i, 3])
            qx = aw * bx + ax * bw + ay * bz - az * by  # q <- q exp(w): a local (right) rotation
            qy = aw * by - ax * bz + ay * bw + az * bx
            qz = aw * bz + ax * by - ay * bx + az * bw
            qw = aw * bw - ax * bx - ay * by - az * bz
            qn = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
            quat[i, 0] = qx / qn
            quat[i, 1] = qy / qn
            quat[i, 2] = qz / qn
            quat[i, 3] = qw / qn
            lg = min(LOGIT_CLAMP, max(-LOGIT_CLAMP, np.float64(logit[i]) + d[P_LOGIT, j]))
            logit[i] = lg
            opa[i] = 1.0 / (1.0 + math.exp(-np.float64(logit[i])))


def bias_corrections(beta: float, n_steps: int) -> np.ndarray:
    """``[n_steps + 1]`` float32 ``1 / (1 - beta ** t)`` for ``t = 0 .. n_steps`` (``t = 0`` as 1:
    never read for a Gaussian that steps, which counts its step first)."""
    t = np.maximum(np.arange(n_steps + 1), 1).astype(np.float64)
    return (1.0 / (1.0 - beta ** t)).astype(np.float32)


class FitState:
    """The Gaussians being fitted (float32, 3DGS parametrisation), their Adam moments and the
    densification statistics. Rows may be added (densification) and removed (pruning).

    ``min_scale_m``, ``max_scale_m``: the clamp of the starting scales; ``normal_offset_max_scales``:
    how far a centre may leave its starting surface, in its largest starting scale (0: free);
    ``sh_degree``: the SH degree the fit learns (its coefficients get Adam rows; a field of a
    lower degree gets zeros for the coefficients it lacks)."""

    def __init__(self, field: GaussianField, min_scale_m: float, max_scale_m: float,
                 normal_offset_max_scales: float = 0.0, sh_degree: int = 0) -> None:
        self.pos = np.array(field.positions, np.float32)  # a copy: the fit moves it in place
        self.log_s = np.log(np.clip(field.scales.astype(np.float64), min_scale_m, max_scale_m)).astype(np.float32)
        q = field.rotations_xyzw.astype(np.float64)
        self.quat = np.ascontiguousarray(q / np.linalg.norm(q, axis=1, keepdims=True), np.float32)
        op = np.clip(field.opacities.astype(np.float64), 1e-4, 1 - 1e-4)
        self.logit = np.log(op / (1 - op)).astype(np.float32)
        self.col = (field.colors.astype(np.float64) / 255.0).astype(np.float32)
        self.ids = field.ids.copy()
        # The fit learns the first k_fit coefficients. Those of a higher degree than it learns ride
        # along unchanged (split and cloned Gaussians copy their parent's), so none are dropped.
        self.k_fit = sh_rest_count(sh_degree)
        n_rest = max(self.k_fit, field.sh_rest.shape[1])
        if n_rest == field.sh_rest.shape[1] and not self.k_fit:
            self.sh_rest = field.sh_rest  # [N, K, 3]; not stepped, so not copied
        else:
            self.sh_rest = np.zeros((len(field), n_rest, 3), np.float32)
            self.sh_rest[:, :field.sh_rest.shape[1]] = field.sh_rest
        if field.sh_degree > sh_degree:
            what = "degree-0 colour only" if not sh_degree else f"SH up to degree {sh_degree}"
            logger.warning("the keyframe fit renders and fits %s: the SH coefficients of degree %d "
                           "(view-dependent colour) of the %d Gaussians are kept unchanged beyond it",
                           what, field.sh_degree, len(field))
        # Where each Gaussian started ([N, 3]), its surface normal there ([N, 3], the axis of its
        # smallest scale) and how far along it the fit may move it ([N, 1], normal_offset_max_scales
        # times its largest scale). Without a bound they are [N, 0] and never read: no memory.
        n = len(field)
        width = 3 if normal_offset_max_scales > 0 else 0
        self.anchor = self.pos[:, :width].copy()  # a copy: pos moves in place
        self.anchor_n = np.zeros((n, width), np.float32)
        self.anchor_b = np.zeros((n, min(width, 1)), np.float32)
        if width and n:
            R = quat_xyzw_to_rotmat(self.quat.astype(np.float64))  # [N, 3, 3]
            sc = field.scales.astype(np.float64)
            self.anchor_n = np.ascontiguousarray(R[np.arange(n), :, np.argmin(sc, axis=1)], np.float32)
            self.anchor_b = (normal_offset_max_scales * sc.max(axis=1, keepdims=True)).astype(np.float32)
        rows = P_SH + 3 * self.k_fit
        self.m1 = np.zeros((rows, n), np.float32)  # Adam moments, one row per scalar parameter
        self.m2 = np.zeros((rows, n), np.float32)
        self.n_steps = np.zeros(n, np.int32)  # Adam steps each Gaussian has taken (selective Adam)
        self.refresh()
        self.reset_stats()
        child = self.ids[(self.ids & CHILD_ID_BIT) != 0] & ~CHILD_ID_BIT
        self.next_child = int(child.max()) + 1 if len(child) else 0

    def __len__(self) -> int:
        return len(self.pos)

    def gaussians(self) -> GaussianArrays:
        """The state as the raster stages read it (float32, colours in [0, 1])."""
        return GaussianArrays(self.pos, self.scl, self.quat, self.col, self.opa)

    def params(self) -> FitParams:
        return FitParams(self.pos, self.log_s, self.quat, self.logit, self.col, self.scl, self.opa,
                         self.sh_rest if self.k_fit else _NO_SH)

    def refresh(self) -> None:
        self.scl = np.exp(self.log_s)
        self.opa = (1.0 / (1.0 + np.exp(-self.logit.astype(np.float64)))).astype(np.float32)

    def reset_stats(self) -> None:
        self.vs_sum = np.zeros(len(self))
        self.vs_cnt = np.zeros(len(self), np.int32)

    _ROWS = ("pos", "log_s", "quat", "logit", "col", "ids", "sh_rest", "anchor", "anchor_n", "anchor_b", "n_steps")
    _MOMENTS = ("m1", "m2")  # [N_PARAM + 3 k_fit, N]: Gaussians along axis 1

    def take(self, rows: np.ndarray) -> None:
        for name in self._ROWS:
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[rows]))
        for name in self._MOMENTS:
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[:, rows]))
        self.refresh()

    def append(self, rows: np.ndarray, ids: np.ndarray) -> None:
        """Copies of ``rows`` with new ``ids`` and a fresh optimizer state (3DGS: new Gaussians
        start fresh)."""
        n = len(self)
        for name in self._ROWS:
            a = getattr(self, name)
            setattr(self, name, np.ascontiguousarray(np.concatenate([a, ids if name == "ids" else a[rows]])))
        for name in self._MOMENTS:
            a = getattr(self, name)
            setattr(self, name, np.ascontiguousarray(np.concatenate([a, a[:, rows]], axis=1)))
        self.restart_optimizer(np.arange(n, len(self)))
        self.refresh()

    def restart_optimizer(self, rows: np.ndarray) -> None:
        """Zero moments and no steps taken for ``rows`` (new and split Gaussians)."""
        for name in self._MOMENTS:
            getattr(self, name)[:, rows] = 0.0
        self.n_steps[rows] = 0

    def hold_to_surface(self) -> None:
        """Clamp each centre's offset from its start along its starting normal to ``anchor_b``."""
        off = np.einsum("ij,ij->i", self.pos - self.anchor, self.anchor_n)[:, None]  # [N, 1]
        excess = off - np.clip(off, -self.anchor_b, self.anchor_b)
        self.pos -= excess * self.anchor_n

    def to_field(self, keep: np.ndarray) -> GaussianField:
        return canonicalize(GaussianField(self.pos[keep], np.exp(self.log_s[keep].astype(np.float64)),
                                          self.quat[keep], np.rint(self.col[keep].astype(np.float64) * 255.0),
                                          self.opa[keep], self.ids[keep], self.sh_rest[keep]))
