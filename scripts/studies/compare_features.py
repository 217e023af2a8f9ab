"""Compare the two SfM feature paths (sfm.features colmap / torch) on the same windows.

For each window and each path, one fresh :class:`SfmReconstructor` (the package's SfM with its
default options otherwise): registered frames, 3D points, the mean reprojection error (per
observation), the SfM depth error against ground truth (median of |s·D_sfm − D_gt| / D_gt over
the window's observations after ONE best-fit scale s = median(D_gt / D_sfm)), keypoints per
frame, verified pairs, and seconds per stage (extract, match, map; the torch path also its
steps: detect_describe / write, match / verify). The torch features run on ``--device``; CUDA
is warmed up (kernels, allocator) on one frame before any window is timed.

Windows: the first ``--hololens-frames`` frames of ``../shared/data/hololens_000`` (one window;
skipped when absent) and non-overlapping ``--window``-frame windows of a generated KITTI-size
street drive (``--drive-frames`` frames, 1242 x 375, the generator of ``sfm-ttr generate``, made
in memory; or an existing KITTI-layout drive with ``--kitti-raw``/``--drive``/``--kitti-gt``).
Nothing is downloaded. Writes one JSON file (``--out``) and prints a table.

    nice -n 10 .venv/bin/python scripts/studies/compare_features.py --device cpu --out cpu.json
    .venv/bin/python scripts/studies/compare_features.py --device cuda --out cuda.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from sfm_ttr_ros.core.frames import Frame  # noqa: E402
from sfm_ttr_ros.core.sfm.config import FEATURE_BACKENDS, SfmConfig  # noqa: E402
from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor  # noqa: E402


def depth_error(result, frames, gt) -> float | None:
    """Median relative SfM depth error after one best-fit (median) scale; None without GT."""
    d_sfm, d_gt = [], []
    for f in frames:
        obs, g = result.frames.get(f.name), gt.get(f.name)
        if obs is None or g is None:
            continue
        h, w = g.shape
        px = np.clip(np.rint(obs.pixels).astype(int), 0, [w - 1, h - 1])
        v = g[px[:, 1], px[:, 0]]
        d_sfm.append(obs.depths[v > 0])
        d_gt.append(v[v > 0])
    if not d_sfm or not sum(map(len, d_gt)):
        return None
    d_sfm, d_gt = np.concatenate(d_sfm), np.concatenate(d_gt)
    s = float(np.median(d_gt / d_sfm))
    return float(np.median(np.abs(s * d_sfm - d_gt) / d_gt))


def database_stats(rec: SfmReconstructor) -> dict:
    import pycolmap

    with pycolmap.Database.open(rec.workspace.database_path) as db:
        kp = [db.num_keypoints_for_image(i.image_id) for i in db.read_all_images()]
        _, geoms = db.read_two_view_geometries()
        inl = [0 if g.inlier_matches is None else len(g.inlier_matches) for g in geoms]
    return {"keypoints_per_frame": float(np.mean(kp)) if kp else 0.0,
            "pairs": len(inl), "verified_pairs": int(sum(n >= 15 for n in inl)),
            "inliers_per_pair": float(np.mean(inl)) if inl else 0.0}


def run_window(features: str, frames, intrinsics, gt, device: str, config: dict) -> dict:
    cfg = SfmConfig(features=features, **config)
    t0 = time.perf_counter()
    with SfmReconstructor(cfg, feature_device=device) as rec:
        res = rec.reconstruct(frames, intrinsics)
        stats = database_stats(rec)
    total = time.perf_counter() - t0
    return {"features": features, "ok": res.ok, "reason": res.reason, "frames": len(frames),
            "registered": res.num_registered, "points": res.num_points,
            "reprojection_error_px": res.reprojection_error,
            "depth_error": depth_error(res, frames, gt),
            "seconds": {**{k: round(v, 4) for k, v in res.timings.items()},
                        "total": round(total, 4)},
            "mapper_attempts": len(res.attempts), **stats}


def hololens_windows(root: Path, n: int):
    from sfm_ttr_ros.data.sequence import open_image_folder

    if not (root / "images").is_dir():
        print(f"[compare] {root} not found: no hololens window", file=sys.stderr)
        return []
    seq = open_image_folder(root / "images", root / "K.txt", root / "depth", gt_scale=1000.0)
    frames = seq.frames(0, min(n, len(seq)))
    return [(f"hololens_000[0:{len(frames)}]", frames, seq.intrinsics,
             {f.name: seq.gt(f.name) for f in frames})]


def drive_windows(args):
    if args.drive_frames <= 0:
        return []
    if args.kitti_raw:
        from sfm_ttr_ros.data.sequence import open_kitti

        seq = open_kitti(args.kitti_raw, args.drive, args.kitti_gt)
        frames = seq.frames(0, min(args.drive_frames, len(seq)))
        gt = {f.name: seq.gt(f.name) for f in frames}
        intr, label = seq.intrinsics, args.drive
    else:
        from sfm_ttr_ros.data.synthetic import make_sequence

        t0 = time.perf_counter()
        seq = make_sequence(seed=args.seed, domain="A", num_frames=args.drive_frames,
                            width=args.width, height=args.height)
        print(f"[compare] generated {args.drive_frames} frames {args.width}x{args.height} in "
              f"{time.perf_counter() - t0:.1f} s", file=sys.stderr)
        frames = [Frame(i, im, stamp=s) for i, (im, s) in
                  enumerate(zip(seq.images, seq.stamps, strict=True))]
        gt = {f.name: seq.depths[f.index] for f in frames}
        intr, label = seq.intrinsics, f"generated_street_seed{args.seed}"
    out = []
    for a in range(0, len(frames) - args.window + 1, args.window):
        w = frames[a:a + args.window]
        out.append((f"{label}[{a}:{a + args.window}]", w, intr, {f.name: gt[f.name] for f in w}))
    return out


def warm_up(device: str, frame) -> None:
    """One frame's features and a self-match on the device, untimed (CUDA context, kernels)."""
    from sfm_ttr_ros.core.sfm.features.database import downscale
    from sfm_ttr_ros.core.sfm.features.matching_torch import match_mutual_ratio
    from sfm_ttr_ros.core.sfm.features.sift_torch import detect_and_describe

    f = detect_and_describe(downscale(frame.image, 640)[0], device=device)
    match_mutual_ratio(f.descriptors, f.descriptors)


def summarise(rows: list[dict]) -> dict:
    out = {}
    for feat in FEATURE_BACKENDS:
        rs = [r for r in rows if r["features"] == feat]
        if not rs:
            continue
        de = [r["depth_error"] for r in rs if r["depth_error"] is not None]
        secs = {}
        for k in sorted({k for r in rs for k in r["seconds"]}):
            secs[k] = round(float(np.mean([r["seconds"].get(k, 0.0) for r in rs])), 4)
        out[feat] = {
            "windows": len(rs), "ok": sum(r["ok"] for r in rs),
            "registered": f"{sum(r['registered'] for r in rs)}/{sum(r['frames'] for r in rs)}",
            "points_mean": float(np.mean([r["points"] for r in rs])),
            "reprojection_error_px_mean": float(np.nanmean(
                [r["reprojection_error_px"] for r in rs])),
            "depth_error_median_of_windows": float(np.median(de)) if de else None,
            "seconds_mean_per_window": secs,
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="JSON output file")
    ap.add_argument("--device", default="auto", help="torch device of the torch features: "
                    "cpu, cuda (auto: cuda when torch sees a GPU)")
    ap.add_argument("--features", nargs="+", default=list(FEATURE_BACKENDS),
                    choices=FEATURE_BACKENDS)
    ap.add_argument("--shared-data", default=str(REPO.parent / "shared" / "data"))
    ap.add_argument("--hololens-frames", type=int, default=15)
    ap.add_argument("--drive-frames", type=int, default=30)
    ap.add_argument("--window", type=int, default=10)
    ap.add_argument("--width", type=int, default=1242)
    ap.add_argument("--height", type=int, default=375)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kitti-raw", help="an existing KITTI-layout drive instead of generating")
    ap.add_argument("--drive", help="its drive folder name (with --kitti-raw)")
    ap.add_argument("--kitti-gt", help="its improved-GT root (with --kitti-raw)")
    ap.add_argument("--threads", type=int, default=2, help="sfm.num_threads and torch threads")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="other SfmConfig fields, e.g. first_octave=0")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    device = args.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    config = {"num_threads": args.threads}
    for item in args.set:
        k, _, v = item.partition("=")
        config[k] = type(getattr(SfmConfig(), k))(v)

    windows = hololens_windows(Path(args.shared_data) / "hololens_000", args.hololens_frames)
    windows += drive_windows(args)
    if "torch" in args.features:
        warm_up(device, windows[0][1][0])
    rows = []
    for label, frames, intr, gt in windows:
        for feat in args.features:
            row = {"window": label, **run_window(feat, frames, intr, gt, device, config)}
            rows.append(row)
            de = row["depth_error"]
            print(f"{label:34s} {feat:6s} reg {row['registered']:2d}/{row['frames']:2d} "
                  f"pts {row['points']:5d} reproj {row['reprojection_error_px']:.3f} px "
                  f"depth err {'-' if de is None else f'{100 * de:.2f} %':>8s} "
                  f"kp {row['keypoints_per_frame']:6.0f} "
                  f"extract {row['seconds'].get('extract', 0):6.2f} "
                  f"match {row['seconds'].get('match', 0):6.2f} "
                  f"map {row['seconds'].get('map', 0):5.2f} s", flush=True)
    info = {"device": device, "torch": torch.__version__,
            "gpu": torch.cuda.get_device_name(0) if device.startswith("cuda") else None,
            "cpu_threads": args.threads, "host": platform.node(), "config": config,
            "machine_cores": __import__("os").cpu_count()}
    result = {"info": info, "summary": summarise(rows), "windows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(json.dumps(result["summary"], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
