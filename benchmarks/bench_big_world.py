"""Big worlds: time and peak memory to save, load and render a world of N Gaussians.

Scene: a deterministic synthetic world in a 4 x 4.5 x 2.6 m room (walls, floor, ceiling and three
boxes), Gaussians spread over its surfaces by area: flat discs oriented with the surface, tangential
standard deviations log-uniform in [3 mm, 20 mm], 1 mm along the normal; opacities 70 % in
[0.8, 1], 30 % in [0.1, 0.8]; one voxel of statistics per Gaussian (as the voxel merge makes them),
so ``world.npz`` holds what a mapped world holds. The camera stands inside the room (Kinect-like
intrinsics, fx = fy = 525 at 640x480, scaled for 1280x960) and sees about a third of the Gaussians.

Every step runs in a fresh subprocess (so one step's allocations never hide another's), which
first builds or loads its input, then resets the kernel's peak-RSS counter (``/proc/self/clear_refs``)
and runs the step alone:

* ``save``: ``write_world_bundle`` with the ``GaussianWorld`` as extra: ``gaussians.ply``,
  ``gaussians.bin``, ``world.npz``, checksums in ``metadata.json``;
* ``load``: ``load_world_bundle`` (``gaussians.bin``, every listed file verified) and
  ``GaussianWorld.load`` (``world.npz``), together;
* ``render``: one view at 640x480, one at 1280x960 (after one warm-up render, so the JIT is
  compiled or loaded from its cache).

For each step: wall seconds, peak RSS of the process (MB), the step's own peak above what the
process held before it (``step MB``), and the stated bound (``atlas_pipeline.gaussian_world.render``
``render_peak_bytes`` / ``field.FIELD_BYTES_PER_GAUSSIAN`` ...: ``bound MB``) that the step's own
peak must stay under.

Run: ``python benchmarks/bench_big_world.py [--sizes 100000 500000 2000000] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

WIDTH, HEIGHT = 640, 480
K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])  # [3, 3] Kinect-like
ROOM_MIN = np.array([-2.0, -0.5, 0.0])  # world z up
ROOM_MAX = np.array([2.0, 4.0, 2.6])
BOXES = [  # (min corner, max corner)
    (np.array([-1.2, 1.2, 0.0]), np.array([-0.5, 1.8, 0.7])),
    (np.array([0.3, 2.0, 0.0]), np.array([1.3, 2.6, 1.1])),
    (np.array([-0.3, 3.0, 0.0]), np.array([0.4, 3.5, 1.5])),
]
EYE = np.array([0.0, -0.3, 1.4])  # camera centre inside the room
TARGET = np.array([0.0, 3.0, 0.8])
SCALE_RANGE_M = (0.003, 0.02)  # tangential standard deviations of a mapped surface (log-uniform)
NORMAL_SCALE_M = 0.001  # thin along the normal
VOXEL_M = 0.01  # the voxel size the synthetic statistics claim
GEN_CHUNK = 1 << 18  # Gaussians generated per chunk: float64 temporaries stay ~100 MB at any N
SIZES = (100_000, 500_000, 2_000_000)
STEPS = ("save", "load", "render")
MB = 1 << 20


def _faces() -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Rectangles ``(origin [3], edge_a [3], edge_b [3], normal [3])`` of the room and the boxes."""
    out = []

    def box_faces(lo, hi, inward):
        size = hi - lo
        for ax in range(3):
            a, b = (ax + 1) % 3, (ax + 2) % 3
            ea, eb = np.zeros(3), np.zeros(3)
            ea[a], eb[b] = size[a], size[b]
            for side, sign in ((lo, -1.0), (hi, 1.0)):
                o = lo.copy()
                o[ax] = side[ax]
                n = np.zeros(3)
                n[ax] = -sign if inward else sign
                if not inward and ax == 2 and sign < 0:
                    continue  # a box's bottom lies on the floor, unseen
                out.append((o, ea, eb, n))

    box_faces(ROOM_MIN, ROOM_MAX, inward=True)
    for lo, hi in BOXES:
        box_faces(lo, hi, inward=False)
    return out


def make_field(n: int, seed: int = 0):
    """A deterministic :class:`GaussianField` of ``n`` Gaussians on the room's surfaces (float32,
    ids sorted and unique), generated in chunks of ``GEN_CHUNK``."""
    from atlas_pipeline.gaussian_world.field import GaussianField, canonicalize
    from atlas_pipeline.geometry import rotmat_to_quat_xyzw

    faces = _faces()
    areas = np.array([np.linalg.norm(np.cross(ea, eb)) for _, ea, eb, _ in faces])
    pos = np.empty((n, 3), np.float32)
    scl = np.empty((n, 3), np.float32)
    rot = np.empty((n, 4), np.float32)
    col = np.empty((n, 3), np.uint8)
    opa = np.empty(n, np.float32)
    for c0 in range(0, n, GEN_CHUNK):
        m = min(GEN_CHUNK, n - c0)
        rng = np.random.default_rng([seed, c0])  # per chunk: the same Gaussians whatever GEN_CHUNK divides
        f = rng.choice(len(faces), size=m, p=areas / areas.sum())
        o = np.stack([faces[k][0] for k in range(len(faces))])[f]
        ea = np.stack([faces[k][1] for k in range(len(faces))])[f]
        eb = np.stack([faces[k][2] for k in range(len(faces))])[f]
        nrm = np.stack([faces[k][3] for k in range(len(faces))])[f]
        p = o + rng.random((m, 1)) * ea + rng.random((m, 1)) * eb
        t1 = ea / np.linalg.norm(ea, axis=1, keepdims=True)
        t2 = np.cross(nrm, t1)
        ang = rng.uniform(0, 2 * np.pi, m)[:, None]
        t1, t2 = np.cos(ang) * t1 + np.sin(ang) * t2, -np.sin(ang) * t1 + np.cos(ang) * t2
        R = np.stack([t1, t2, nrm], axis=2)  # [m, 3, 3] columns: local x, y, z (the normal)
        pos[c0:c0 + m] = p
        rot[c0:c0 + m] = rotmat_to_quat_xyzw(R)
        scl[c0:c0 + m, :2] = np.exp(rng.uniform(np.log(SCALE_RANGE_M[0]), np.log(SCALE_RANGE_M[1]), (m, 2)))
        scl[c0:c0 + m, 2] = NORMAL_SCALE_M
        texture = 0.5 + 0.5 * np.sin(p[:, :1] * 9.0 + p[:, 1:2] * 5.0 + p[:, 2:3] * 3.0 + [0.0, 2.0, 4.0])
        col[c0:c0 + m] = np.clip(texture * 220 + rng.normal(0, 15, (m, 3)), 0, 255)
        opa[c0:c0 + m] = np.where(rng.random(m) < 0.7, rng.uniform(0.8, 1.0, m), rng.uniform(0.1, 0.8, m))
    ids = np.arange(n, dtype=np.uint64) * np.uint64(7919) + np.uint64(1 << 40)  # sorted, unique, not 0..n
    # values the PLY reproduces bit for bit, as a built world's (VoxelGaussianBuilder.to_field)
    return canonicalize(GaussianField(pos, scl, rot, col, opa, ids))


def make_world(n: int, seed: int = 0):
    """A ``GaussianWorld`` around :func:`make_field` with one voxel of statistics per Gaussian."""
    from atlas_pipeline.gaussian_world.builder import GaussianWorld, VoxelGaussianBuilder

    fld = make_field(n, seed)
    cnt = (np.arange(n) % 23 + 1).astype(np.int64)  # points per voxel
    b = VoxelGaussianBuilder(VOXEL_M, fld.ids.copy(), cnt, fld.positions * cnt[:, None].astype(np.float64),
                             fld.colors * cnt[:, None].astype(np.float64), np.zeros((n, 6)),
                             (np.arange(n) % 7 + 1).astype(np.int32))
    b.sum_sq[:, [0, 3, 5]] = b.sum_xyz ** 2 / cnt[:, None]
    n_kf = 40
    poses = np.repeat(camera_pose()[None], n_kf, axis=0)
    return GaussianWorld(fld, b, np.arange(n_kf, dtype=np.int64) * 10, poses, "estimated",
                         np.linspace(n / n_kf, n, n_kf).astype(np.int64))


def camera_pose() -> np.ndarray:
    """``[4, 4]`` camera-to-world pose of the benchmark view."""
    from atlas_pipeline.geometry import look_at

    return look_at(EYE, TARGET)


def camera(width: int, height: int) -> np.ndarray:
    """``[3, 3]`` intrinsics of the benchmark view at ``width x height`` (same field of view)."""
    from atlas_pipeline.gaussian_world.raster import scale_intrinsics

    return scale_intrinsics(K, width / WIDTH, height / HEIGHT)


# ---- memory of this process -------------------------------------------------------------------
def _status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        m = re.search(rf"^{key}:\s+(\d+) kB", f.read(), re.M)
    return int(m.group(1)) / 1024.0 if m else float("nan")


def rss_mb() -> float:
    """Resident set size now (MB)."""
    return _status_mb("VmRSS")


def reset_peak() -> bool:
    """Reset the kernel's peak-RSS counter of this process (Linux >= 4.0); False where it cannot."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_mb() -> float:
    """Peak resident set size since the last :func:`reset_peak` (MB)."""
    return _status_mb("VmHWM")


_PROCESS_PEAK_MB = [0.0]  # the process's own peak across resets of the counter


def process_peak_mb() -> float:
    """Peak RSS of the whole process so far (MB), resets of the counter included."""
    _PROCESS_PEAK_MB[0] = max(_PROCESS_PEAK_MB[0], peak_mb())
    return _PROCESS_PEAK_MB[0]


def _measure(fn):
    """``(result, seconds, base MB, peak MB)`` of ``fn()`` with the peak counter reset before it."""
    process_peak_mb()
    base = rss_mb()
    reset_peak()
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    return out, dt, base, peak_mb()


# ---- one step, in its own process --------------------------------------------------------------
def run_step(step: str, n: int, folder: Path) -> dict:
    from atlas_pipeline.gaussian_world import render as R
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.scene_memory.bundle import load_world_bundle, write_world_bundle

    res: dict = {"step": step, "n": n, "python_mb": rss_mb()}
    if step == "save":
        t0 = time.perf_counter()
        world = make_world(n)
        res["make_s"] = time.perf_counter() - t0
        _, res["seconds"], res["base_mb"], res["peak_mb"] = _measure(
            lambda: write_world_bundle(folder, world.field, {"name": "big-world-bench"}, extras=(world,)))
        res["bound_mb"] = _bound_mb("save_peak_bytes", n)
        res["files_mb"] = {p.name: p.stat().st_size / MB for p in sorted(folder.iterdir())
                           if p.is_file() and not p.name.startswith(".")}
        disk = _bound_mb("bundle_disk_bytes", n, n)  # {file: bytes} where stated
        res["files_ok"] = all(res["files_mb"][k] * MB <= v for k, v in disk.items()) if isinstance(disk, dict) else None
    elif step == "load":
        def load():
            b = load_world_bundle(folder, source="bin", verify=True)
            w = GaussianWorld.load(folder)
            return b, w

        (bundle, world), res["seconds"], res["base_mb"], res["peak_mb"] = _measure(load)
        assert len(bundle.field) == n and world.field.equals(bundle.field)
        res["bound_mb"] = _bound_mb("load_peak_bytes", n, n)
    elif step == "render":
        fld = load_world_bundle(folder, source="bin", verify=False).field
        T = camera_pose()
        args = (fld.positions, fld.scales, fld.rotations_xyzw, fld.colors, fld.opacities, T)
        small = [a[:1000] for a in args[:5]]  # JIT compile or cache load, without big allocations
        R.render_gaussians(*small, T, camera(64, 48), 64, 48)
        for w, h in ((WIDTH, HEIGHT), (2 * WIDTH, 2 * HEIGHT)):
            out, dt, base, peak = _measure(lambda: R.render_gaussians(*args, camera(w, h), w, h))
            res[f"render_{w}"] = {"seconds": dt, "base_mb": base, "peak_mb": peak,
                                  "bound_mb": _bound_mb("render_peak_bytes", n, w, h),
                                  "covered": float(np.mean(out.alpha > 0.5))}
            del out
    else:
        raise ValueError(f"unknown step {step!r}")
    res["process_peak_mb"] = process_peak_mb()
    return res


def _bound_mb(name: str, *args):
    """A stated bound (``render.<name>(*args)`` or ``bundle.<name>(*args)``) in MB (a dict of bytes
    stays as it is); inf where this version states none."""
    from atlas_pipeline.gaussian_world import render as R
    from atlas_pipeline.scene_memory import bundle as Bu

    fn = getattr(R, name, None) or getattr(Bu, name, None)
    if fn is None:
        return float("inf")
    out = fn(*args)
    return out if isinstance(out, dict) else out / MB


# glibc adapts its mmap threshold upwards after a large free, after which freed arrays stay in the
# heap and inflate the next step's baseline; a fixed threshold returns every large array to the OS.
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(128 * 1024), "MALLOC_TRIM_THRESHOLD_": str(128 * 1024)}


def _subprocess(step: str, n: int, folder: Path) -> dict:
    cmd = [sys.executable, __file__, "--step", step, "--n", str(n), "--folder", str(folder)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=False, env={**os.environ, **MALLOC_ENV})
    if out.returncode != 0:
        raise SystemExit(f"step {step} n={n} failed:\n{out.stderr[-4000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--step", choices=STEPS, help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--folder", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.step:
        print(json.dumps(run_step(args.step, args.n, args.folder)))
        return

    rows = []
    for n in args.sizes:
        tmp = Path(tempfile.mkdtemp(prefix="bench_big_world_"))
        try:
            folder = tmp / "world"
            save = _subprocess("save", n, folder)
            load = _subprocess("load", n, folder)
            rend = _subprocess("render", n, folder)
            rows.append({"n": n, "save": save, "load": load, "render": rend})
            r640, r1280 = rend["render_640"], rend["render_1280"]
            print(f"N={n}: make {save['make_s']:.1f} s, save {save['seconds']:.2f} s, load {load['seconds']:.2f} s, "
                  f"render 640 {r640['seconds']:.2f} s / 1280 {r1280['seconds']:.2f} s, "
                  f"files {', '.join(f'{k} {v:.0f} MB' for k, v in save['files_mb'].items())}", flush=True)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def step_mb(d: dict) -> float:
        return d["peak_mb"] - d["base_mb"]

    print("\n| N | save s | load s | render 640x480 s | render 1280x960 s | peak RSS MB (save / load / render) "
          "| step peak MB: save / load / render 640 / 1280 | stated bound MB: save / load / render 640 / 1280 "
          "| ratio to first row (N, render 1280 s, render 1280 step MB) |")
    print("|---|---|---|---|---|---|---|---|---|")
    first = rows[0]
    ok = True
    for r in rows:
        s, l, r6, r12 = r["save"], r["load"], r["render"]["render_640"], r["render"]["render_1280"]
        steps = [step_mb(s), step_mb(l), step_mb(r6), step_mb(r12)]
        bounds = [s["bound_mb"], l["bound_mb"], r6["bound_mb"], r12["bound_mb"]]
        ok &= all(a <= b for a, b in zip(steps, bounds)) and s.get("files_ok") is not False
        f12 = first["render"]["render_1280"]
        print(f"| {r['n']:,} | {s['seconds']:.2f} | {l['seconds']:.2f} | {r6['seconds']:.2f} | {r12['seconds']:.2f} "
              f"| {s['process_peak_mb']:.0f} / {l['process_peak_mb']:.0f} / {r['render']['process_peak_mb']:.0f} "
              f"| {' / '.join(f'{x:.0f}' for x in steps)} | {' / '.join(f'{x:.0f}' for x in bounds)} "
              f"| {r['n'] / first['n']:.0f}x, {r12['seconds'] / f12['seconds']:.1f}x, "
              f"{step_mb(r12) / max(step_mb(f12), 1e-9):.1f}x |")
    print(f"\nevery step's own peak within its stated bound, every file within bundle_disk_bytes: "
          f"{'yes' if ok else 'NO'}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    if not ok:
        sys.exit(1)


if __name__ == "__main__":
    main()
