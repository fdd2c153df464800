"""How the Gaussian world looks against the real images, and what it costs on disk.

    python benchmarks/bench_photometric.py                 # TUM teddy (when present) and synthetic
    python benchmarks/bench_photometric.py --datasets teddy fr1 synthetic --sources estimated
    python benchmarks/bench_photometric.py --json out.json
    python benchmarks/bench_photometric.py --datasets teddy --unfitted   # also without the keyframe fit
    python benchmarks/bench_photometric.py --datasets teddy --sources ground_truth --set fusion.max_depth_m=8
    python benchmarks/bench_photometric.py --datasets --synthetic synthetic-handheld --sensor colour_delay_s=0.015

For each dataset and each way of mapping (ground-truth poses, and the tracker's own poses with no
ground truth), the world is built with the default profile (voxel Gaussians, then fitted to the
keyframe images and depths: mapping.fit.epochs), every frame is localized against it,
and every held-out frame (not a keyframe: it never fed the map) is rendered from its *estimated*
pose and compared with the real image: PSNR over the whole frame, PSNR over the pixels with a
sensor depth reading (what a depth-built map can hold), SSIM, depth L1. The world bundle is then
written, and its size and bytes per Gaussian reported.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def run(manifest, cfg) -> dict:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.gaussian_world.evaluation import evaluate_rendering
    from atlas_pipeline.localization.localizer import localize, tracking_map
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.scene_memory.binary import BYTES_PER_GAUSSIAN
    from atlas_pipeline.scene_memory.bundle import write_world_bundle
    from atlas_pipeline.scene_memory.metadata import bundle_metadata

    assert isinstance(cfg, PipelineConfig)
    fused = fuse(manifest, cfg)
    kf = select_keyframes_stage(manifest, fused, cfg)
    t_build = time.perf_counter()
    world = build_gaussian_world(fused, kf, cfg, manifest=manifest)
    t_build = time.perf_counter() - t_build
    report = localize(manifest, world, cfg)
    t0 = time.perf_counter()
    ev = evaluate_rendering(manifest, world, report, cfg)
    dt = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        meta = bundle_metadata(manifest.dataset, manifest.dataset, world, manifest, cfg)
        b = write_world_bundle(Path(tmp) / "bundle", world.field, meta, localization=report,
                               surfels=tracking_map(world))
        sizes = {p.name: p.stat().st_size for p in Path(b).iterdir() if p.is_file()}
        magic = (Path(b) / "gaussians.bin").read_bytes()[:8].decode()
    version = 2 if magic == "ATLASGS2" else 1
    s = ev.summary
    return {"pose_source": kf.pose_source, "n_gaussians": len(world.field), "anisotropic": not world.field.is_isotropic,
            "n_keyframes": int(len(world.keyframe_indices)), "n_views": s["n_views"],
            "psnr_db": s["mean_psnr_db"], "psnr_masked_db": s["mean_psnr_masked_db"], "ssim": s["mean_ssim"],
            "depth_l1_m": s["mean_depth_l1_m"], "depth_coverage": s["mean_depth_coverage"],
            "localization_ate_m": report.summary.get("ate_rmse_m"), "eval_seconds_per_view": dt / max(s["n_views"], 1),
            "bin_format": magic, "bytes_per_gaussian_bin": BYTES_PER_GAUSSIAN[version],
            "gaussians_bin_bytes": sizes.get("gaussians.bin"), "gaussians_ply_bytes": sizes.get("gaussians.ply"),
            "bundle_bytes": int(sum(sizes.values())), "build_seconds": t_build, "fit": world.fit}


FR1_XYZ = ROOT.parent / "shared" / "data" / "tum_fr1_xyz_10"


def _load(name: str):
    """The dataset's manifest, or None when its TUM frames are not present."""
    from bench_tracking import _load as load_teddy_or_synthetic

    if name != "fr1":
        return load_teddy_or_synthetic(name)
    from atlas_pipeline.sensors.camera import TUM_CAMERAS
    from atlas_pipeline.sensors.tum import load_tum_sequence

    if not (FR1_XYZ / "rgb.txt").is_file():
        return None
    return load_tum_sequence(FR1_XYZ, TUM_CAMERAS["freiburg1"], "tum_fr1_xyz_10")


def main(argv: list[str] | None = None) -> int:

    from atlas_pipeline.config import load_profile

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="*", default=["teddy", "synthetic"], choices=["synthetic", "teddy", "fr1"])
    ap.add_argument("--synthetic", nargs="+", default=[], metavar="PRESET",
                    help="registered synthetic presets too (generated when missing), e.g. synthetic-handheld")
    ap.add_argument("--sensor", action="append", default=[], metavar="KEY=VALUE",
                    help="with --synthetic: variants of the presets with this SyntheticSpec field changed, "
                         "e.g. colour_delay_s=0.015 (as bench_robustness.py)")
    ap.add_argument("--view-stride", type=int, default=1, help="evaluate every n-th held-out frame")
    ap.add_argument("--unfitted", action="store_true",
                    help="also run with mapping.fit.epochs 0 (the voxel field with fitted colours only)")
    ap.add_argument("--sources", nargs="+", default=["ground_truth", "estimated"], choices=["ground_truth", "estimated"],
                    help="mapping pose sources to run")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every run, e.g. fusion.max_depth_m=8 (the masked PSNR then counts "
                         "pixels with depth within that range)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    from atlas_pipeline.config import parse_set_overrides
    from atlas_pipeline.errors import ConfigError

    try:
        overrides = parse_set_overrides(args.set)
        sensor = parse_set_overrides(args.sensor, "--sensor")
    except ConfigError as exc:
        ap.error(str(exc))
    results = {}
    manifests = {name: (lambda name=name: _load(name)) for name in args.datasets}
    variant_tmp = tempfile.TemporaryDirectory(prefix="atlas-sensor-variants-") if sensor else None
    if args.synthetic:
        from bench_robustness import _synthetic_sequences

        from atlas_pipeline.sensors.registry import read_dataset_manifest

        for seq in _synthetic_sequences(args.synthetic, sensor, Path(variant_tmp.name) if variant_tmp else None):
            manifests[seq.name] = lambda e=seq.entry: read_dataset_manifest(e)
    for name, load in manifests.items():
        m = load()
        if m is None:
            print(f"{name}: skipped (TUM frames not found)")
            continue
        results[name] = {}
        epochs = load_profile("default").mapping.fit.epochs
        variants = [(src, epochs) for src in args.sources] + ([("ground_truth", 0)] if args.unfitted else [])
        for source, n_epochs in variants:
            cfg = load_profile("default").with_overrides({**overrides, "mapping.pose_source": source,
                                                          "mapping.fit.epochs": n_epochs,
                                                          "evaluation.view_stride": args.view_stride})
            label = source if n_epochs else f"{source}, unfitted"
            results[name][label] = r = run(m, cfg)
            print(f"{name:10} mapped from {label:12}: build {r['build_seconds']:.1f} s, {r['n_views']} held-out views  PSNR {r['psnr_db']:.2f} dB "
                  f"(pixels with depth {r['psnr_masked_db']:.2f} dB)  SSIM {r['ssim']:.3f}  depth L1 "
                  f"{100 * r['depth_l1_m']:.2f} cm (coverage {100 * r['depth_coverage']:.0f} %)  | "
                  f"{r['n_gaussians']:,} Gaussians, {r['bin_format']} {r['bytes_per_gaussian_bin']} B/Gaussian, "
                  f"bundle {r['bundle_bytes'] / 1e6:.1f} MB | {r['eval_seconds_per_view']:.2f} s/view | "
                  f"localization ATE {1000 * (r['localization_ate_m'] or float('nan')):.1f} mm")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
