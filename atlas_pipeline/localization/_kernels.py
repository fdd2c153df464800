"""Compiled inner loops of the RGB-D tracker (Numba): image pyramids, surfel splatting of the map
into a model view, and the Gauss-Newton normal equations of the hybrid residual.

Conventions: ``T_*`` are 4x4 float64 camera-to-world poses; images are row-major ``[h, w]``; a
level-``l`` pixel ``(i, j)`` covers the full-resolution block starting at ``(s*i, s*j)`` with
``s = 2**l``, so its centre is at ``s*i + (s-1)/2`` full-resolution pixels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = ["downsample_depth", "downsample_mean", "image_gradients", "splat_surfels", "accumulate_normal_equations"]


@njit(cache=True)
def downsample_depth(depth_m, max_jump_m):
    """2x2 mean of valid depths ``[h, w]`` -> ``[h/2, w/2]``; a block whose readings spread more
    than ``max_jump_m`` + 2 % of depth straddles an edge and is left invalid (0) so no flying point
    is made between foreground and background."""
    h, w = depth_m.shape[0] // 2, depth_m.shape[1] // 2
    out = np.zeros((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            s = 0.0
            n = 0
            lo = 1e9
            hi = 0.0
            for di in range(2):
                for dj in range(2):
                    d = depth_m[2 * i + di, 2 * j + dj]
                    if d > 0.0:
                        s += d
                        n += 1
                        lo = min(lo, d)
                        hi = max(hi, d)
            if n >= 2 and hi - lo < max_jump_m + 0.02 * lo:
                out[i, j] = s / n
    return out


@njit(cache=True)
def downsample_mean(img):
    """2x2 block mean of a float image ``[h, w]`` -> ``[h/2, w/2]``."""
    h, w = img.shape[0] // 2, img.shape[1] // 2
    out = np.empty((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            out[i, j] = 0.25 * (img[2 * i, 2 * j] + img[2 * i + 1, 2 * j] + img[2 * i, 2 * j + 1] + img[2 * i + 1, 2 * j + 1])
    return out


@njit(cache=True)
def image_gradients(img):
    """Central-difference gradients ``(gx, gy)`` of ``[h, w]`` (zero on the border)."""
    h, w = img.shape
    gx = np.zeros((h, w), np.float32)
    gy = np.zeros((h, w), np.float32)
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            gx[i, j] = 0.5 * (img[i, j + 1] - img[i, j - 1])
            gy[i, j] = 0.5 * (img[i + 1, j] - img[i - 1, j])
    return gx, gy


@njit(cache=True, parallel=True)
def splat_surfels(pos_w, nrm_w, radius_m, T_world_cam, fx, fy, cx, cy, w, h, max_px):
    """Render oriented disks (surfels) into a pinhole view with a z-buffer.

    Args:
        pos_w, nrm_w: ``[N, 3]`` float64 surfel centres and unit normals (world).
        radius_m: disk radius.
        T_world_cam: ``[4, 4]`` pose of the view.
    Returns:
        ``(points_cam [h, w, 3], normals_cam [h, w, 3])`` float64, NaN where nothing was hit;
        each pixel holds the exact ray / disk-plane intersection, so the model surface is smooth
        and point-to-plane residuals against it are sub-voxel.
    """
    R = T_world_cam[:3, :3]
    t = T_world_cam[:3, 3]
    zbuf = np.full((h, w), np.inf)
    pts = np.full((h, w, 3), np.nan)
    nrm = np.full((h, w, 3), np.nan)
    r2 = radius_m * radius_m
    n = pos_w.shape[0]
    # Pass 1 (parallel over surfels): camera-frame centre, camera-facing normal, pixel box.
    cam = np.empty((n, 7))  # xc yc zc nx ny nz n.c
    box = np.full((n, 4), -1, np.int64)  # ulo uhi vlo vhi; -1 = not visible
    for k in prange(n):
        dx = pos_w[k, 0] - t[0]
        dy = pos_w[k, 1] - t[1]
        dz = pos_w[k, 2] - t[2]
        xc = R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz
        yc = R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz
        zc = R[0, 2] * dx + R[1, 2] * dy + R[2, 2] * dz
        if zc < 0.05:
            continue
        nx = R[0, 0] * nrm_w[k, 0] + R[1, 0] * nrm_w[k, 1] + R[2, 0] * nrm_w[k, 2]
        ny = R[0, 1] * nrm_w[k, 0] + R[1, 1] * nrm_w[k, 1] + R[2, 1] * nrm_w[k, 2]
        nz = R[0, 2] * nrm_w[k, 0] + R[1, 2] * nrm_w[k, 1] + R[2, 2] * nrm_w[k, 2]
        ndotc = nx * xc + ny * yc + nz * zc
        if ndotc > 0.0:  # face the camera: a visible surface's normal points back to the viewer
            nx, ny, nz, ndotc = -nx, -ny, -nz, -ndotc
        u0 = fx * xc / zc + cx
        v0 = fy * yc / zc + cy
        rp = min(int(math.ceil(max(fx, fy) * radius_m / zc)), max_px)
        ulo = max(int(u0) - rp, 0)
        uhi = min(int(u0) + rp + 1, w - 1)
        vlo = max(int(v0) - rp, 0)
        vhi = min(int(v0) + rp + 1, h - 1)
        if ulo > uhi or vlo > vhi:
            continue
        cam[k, 0], cam[k, 1], cam[k, 2] = xc, yc, zc
        cam[k, 3], cam[k, 4], cam[k, 5], cam[k, 6] = nx, ny, nz, ndotc
        box[k, 0], box[k, 1], box[k, 2], box[k, 3] = ulo, uhi, vlo, vhi
    # Pass 2 (parallel over image bands): each band writes only its own rows, so there is no
    # race on the z-buffer and the result does not depend on the number of threads.
    n_bands = 4
    band_h = (h + n_bands - 1) // n_bands
    for band in prange(n_bands):
        _splat_band(band * band_h, min(h, (band + 1) * band_h), cam, box, r2, fx, fy, cx, cy, zbuf, pts, nrm)
    return pts, nrm


@njit(cache=True)
def _splat_band(row_lo, row_hi, cam, box, r2, fx, fy, cx, cy, zbuf, pts, nrm):
    """Surfels into rows ``row_lo:row_hi`` of the buffers (see :func:`splat_surfels`)."""
    for k in range(cam.shape[0]):
        if box[k, 0] < 0 or box[k, 3] < row_lo or box[k, 2] >= row_hi:
            continue
        xc, yc, zc = cam[k, 0], cam[k, 1], cam[k, 2]
        nx, ny, nz, ndotc = cam[k, 3], cam[k, 4], cam[k, 5], cam[k, 6]
        for v in range(max(box[k, 2], row_lo), min(box[k, 3], row_hi - 1) + 1):
            ry = (v - cy) / fy
            for u in range(box[k, 0], box[k, 1] + 1):
                rx = (u - cx) / fx
                denom = nx * rx + ny * ry + nz
                if denom > -0.15:  # grazing (> ~80 deg) or back-facing ray
                    continue
                z = ndotc / denom
                if z <= 0.0 or z >= zbuf[v, u]:
                    continue
                ex = rx * z - xc
                ey = ry * z - yc
                ez = z - zc
                if ex * ex + ey * ey + ez * ez > r2:
                    continue
                zbuf[v, u] = z
                pts[v, u, 0] = rx * z
                pts[v, u, 1] = ry * z
                pts[v, u, 2] = z
                nrm[v, u, 0] = nx
                nrm[v, u, 1] = ny
                nrm[v, u, 2] = nz


@njit(cache=True)
def _bilinear(img, x, y):
    """Bilinear sample of ``img`` at (x, y); NaN outside or next to an invalid (<= 0 for depth) sample."""
    h, w = img.shape
    if not (x >= 0.0 and y >= 0.0 and x < w - 1 and y < h - 1):
        return np.nan
    i = int(y)
    j = int(x)
    a = x - j
    b = y - i
    return ((1 - a) * (1 - b) * img[i, j] + a * (1 - b) * img[i, j + 1]
            + (1 - a) * b * img[i + 1, j] + a * b * img[i + 1, j + 1])


@njit(cache=True, inline="always")
def _add_residual(H, g, J, px, py, pz, ax, ay, az, wgt, r):
    """Add one weighted residual ``r`` whose gradient w.r.t. a world-frame point is ``a`` to the
    normal equations: for ``T <- exp(xi) T``, ``dr/dv = a`` and ``dr/domega = p x a``."""
    J[0], J[1], J[2] = ax, ay, az
    J[3] = py * az - pz * ay
    J[4] = pz * ax - px * az
    J[5] = px * ay - py * ax
    for a in range(6):
        g[a] += wgt * J[a] * r
        for b in range(a, 6):
            H[a, b] += wgt * J[a] * J[b]


@njit(cache=True)
def _accumulate_range(
    lo, hi, H, g, stats,
    pts_cam, inten_cur, T,
    model_pts, model_nrm, T_ref, mfx, mfy, mcx, mcy, max_dist_m, delta_g,
    ref_I, ref_gx, ref_gy, ref_D, T_pref, pfx, pfy, pcx, pcy, dist, w_photo, delta_p, occl_m,
    noise_a, noise_b, noise_z0, noise_ref,
):
    """One chunk of :func:`accumulate_normal_equations`: adds points ``lo:hi`` into ``H``
    (upper triangle), ``g`` and ``stats``.
    """
    R = T[:3, :3]
    t = T[:3, 3]
    Rr = T_ref[:3, :3]
    tr = T_ref[:3, 3]
    Rp = T_pref[:3, :3]
    tp = T_pref[:3, 3]
    mh, mw = model_pts.shape[0], model_pts.shape[1]
    J = np.zeros(6)
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    has_dist = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    for k in range(lo, hi):
        px = R[0, 0] * pts_cam[k, 0] + R[0, 1] * pts_cam[k, 1] + R[0, 2] * pts_cam[k, 2] + t[0]
        py = R[1, 0] * pts_cam[k, 0] + R[1, 1] * pts_cam[k, 1] + R[1, 2] * pts_cam[k, 2] + t[1]
        pz = R[2, 0] * pts_cam[k, 0] + R[2, 1] * pts_cam[k, 1] + R[2, 2] * pts_cam[k, 2] + t[2]
        # --- geometric term against the model view
        dx, dy, dz = px - tr[0], py - tr[1], pz - tr[2]
        xr = Rr[0, 0] * dx + Rr[1, 0] * dy + Rr[2, 0] * dz
        yr = Rr[0, 1] * dx + Rr[1, 1] * dy + Rr[2, 1] * dz
        zr = Rr[0, 2] * dx + Rr[1, 2] * dy + Rr[2, 2] * dz
        if zr > 0.05:
            u = int(mfx * xr / zr + mcx + 0.5)
            v = int(mfy * yr / zr + mcy + 0.5)
            if 0 <= u < mw and 0 <= v < mh and model_pts[v, u, 2] == model_pts[v, u, 2]:
                stats[6] += 1
                ex = xr - model_pts[v, u, 0]
                ey = yr - model_pts[v, u, 1]
                ez = zr - model_pts[v, u, 2]
                if ex * ex + ey * ey + ez * ez < max_dist_m * max_dist_m:
                    nrx, nry, nrz = model_nrm[v, u, 0], model_nrm[v, u, 1], model_nrm[v, u, 2]
                    r = nrx * ex + nry * ey + nrz * ez
                    # normal in world
                    nwx = Rr[0, 0] * nrx + Rr[0, 1] * nry + Rr[0, 2] * nrz
                    nwy = Rr[1, 0] * nrx + Rr[1, 1] * nry + Rr[1, 2] * nrz
                    nwz = Rr[2, 0] * nrx + Rr[2, 1] * nry + Rr[2, 2] * nrz
                    ar = abs(r)
                    # Sensor model: the residual is whitened by this point's depth noise relative
                    # to a point at the reference depth (weight ratio^2, Huber threshold / ratio).
                    ratio = 1.0
                    if noise_a > 0.0:
                        zc = pts_cam[k, 2]
                        dz_ = zc - noise_z0 if zc > noise_z0 else 0.0
                        ratio = noise_ref / (noise_a + noise_b * dz_ * dz_)
                    dg = delta_g / ratio
                    wgt = 1.0 if ar <= dg else dg / ar
                    _add_residual(H, g, J, px, py, pz, nwx, nwy, nwz, wgt * ratio * ratio, r)
                    stats[0] += wgt * r * r
                    stats[1] += 1
                    stats[4] += r * r
        # --- photometric term against the reference image
        if w_photo > 0.0:
            dx, dy, dz = px - tp[0], py - tp[1], pz - tp[2]
            xk = Rp[0, 0] * dx + Rp[1, 0] * dy + Rp[2, 0] * dz
            yk = Rp[0, 1] * dx + Rp[1, 1] * dy + Rp[2, 1] * dz
            zk = Rp[0, 2] * dx + Rp[1, 2] * dy + Rp[2, 2] * dz
            if zk > 0.05:
                xn = xk / zk
                yn = yk / zk
                if has_dist:  # reference images are raw (distorted) sensor images
                    r2 = xn * xn + yn * yn
                    rad = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
                    xd = xn * rad + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
                    yd = yn * rad + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
                else:
                    xd = xn
                    yd = yn
                uf = pfx * xd + pcx
                vf = pfy * yd + pcy
                ui = int(uf + 0.5)
                vi = int(vf + 0.5)
                dref = ref_D[vi, ui] if 0 <= ui < ref_D.shape[1] and 0 <= vi < ref_D.shape[0] else 0.0
                # occlusion / missing depth test: the reference must see this same surface
                if dref == dref and dref > 0.0 and abs(dref - zk) < occl_m:
                    iref = _bilinear(ref_I, uf, vf)
                    gxv = _bilinear(ref_gx, uf, vf)
                    gyv = _bilinear(ref_gy, uf, vf)
                    if not (iref == iref and gxv == gxv and gyv == gyv):  # on the image border
                        continue
                    r = iref - inten_cur[k]
                    ar = abs(r)
                    wgt = w_photo * (1.0 if ar <= delta_p else delta_p / ar)
                    # d r / d x_k (pinhole; distortion's own derivative neglected: it only slows convergence)
                    d0 = gxv * pfx / zk
                    d1 = gyv * pfy / zk
                    d2 = -(gxv * pfx * xk + gyv * pfy * yk) / (zk * zk)
                    awx = Rp[0, 0] * d0 + Rp[0, 1] * d1 + Rp[0, 2] * d2
                    awy = Rp[1, 0] * d0 + Rp[1, 1] * d1 + Rp[1, 2] * d2
                    awz = Rp[2, 0] * d0 + Rp[2, 1] * d1 + Rp[2, 2] * d2
                    _add_residual(H, g, J, px, py, pz, awx, awy, awz, wgt, r)
                    stats[2] += wgt * r * r
                    stats[3] += 1


@njit(cache=True, parallel=True)
def accumulate_normal_equations(
    pts_cam, inten_cur, T,
    model_pts, model_nrm, T_ref, mfx, mfy, mcx, mcy, max_dist_m, delta_g,
    ref_I, ref_gx, ref_gy, ref_D, T_pref, pfx, pfy, pcx, pcy, dist, w_photo, delta_p, occl_m,
    noise_a=0.0, noise_b=0.0, noise_z0=0.0, noise_ref=1.0,
):
    """Gauss-Newton normal equations of the hybrid residual for a left world-frame update
    ``T <- exp(xi) T`` with ``xi = (v, omega)``.

    Geometric: point-to-plane ``n . (x - q)`` against the model view (projective association,
    pixels of ``model_pts`` / ``model_nrm`` in the camera ``T_ref``). Photometric: intensity of the
    reference image ``ref_I`` at the point's projection minus the point's own intensity, weighted
    by ``w_photo`` (0 disables it). Huber weights with thresholds ``delta_g`` (m) and ``delta_p``.
    With ``noise_a > 0`` each geometric residual is weighted by the depth-noise model
    ``sigma(z) = noise_a + noise_b (z - noise_z0)^2`` relative to ``noise_ref = sigma(reference depth)``.
    Points are split into chunks summed in parallel, then added in chunk order (deterministic).

    Returns ``(H [6, 6], g [6], stats [7])`` with stats = (sum w r^2 geometric, n geometric,
    sum w r^2 photometric, n photometric, sum r^2 geometric inliers, n points, n points that
    land on the model view).
    """
    n_pts = pts_cam.shape[0]
    n_chunks = 16
    Hs = np.zeros((n_chunks, 6, 6))
    gs = np.zeros((n_chunks, 6))
    ss = np.zeros((n_chunks, 7))
    step = (n_pts + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        lo = c * step
        hi = min(n_pts, lo + step)
        if lo < hi:
            _accumulate_range(lo, hi, Hs[c], gs[c], ss[c], pts_cam, inten_cur, T,
                              model_pts, model_nrm, T_ref, mfx, mfy, mcx, mcy, max_dist_m, delta_g,
                              ref_I, ref_gx, ref_gy, ref_D, T_pref, pfx, pfy, pcx, pcy, dist, w_photo, delta_p, occl_m,
                              noise_a, noise_b, noise_z0, noise_ref)
    H = np.zeros((6, 6))
    g = np.zeros(6)
    stats = np.zeros(7)
    for c in range(n_chunks):
        H += Hs[c]
        g += gs[c]
        stats += ss[c]
    stats[5] = n_pts
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, stats
