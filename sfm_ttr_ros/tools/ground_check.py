"""The camera-height metric estimate per window on generated drives, against the truth.

For each window of ``--window`` frames (side by side) of a generated drive, SfM reconstructs
it and core/metric/ground.py estimates metres per SfM unit from the camera's height; the truth
is the similarity scale between SfM's and the drive's camera centres. Prints each window's
estimate over the truth (1 = exact; the target: within 3 %) and the worst per drive.

    python -m sfm_ttr_ros.tools.ground_check --domain C A --seeds 0 1 2 --frames 45
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from sfm_ttr_ros.core.geometry import camera_centre
from sfm_ttr_ros.core.metric.ground import cameras


def true_metres_per_unit(sfm, registered, cam_from_world, index) -> float:
    """The similarity scale between the drive's camera centres and SfM's (metres per unit)."""
    sfm_c = cameras(sfm, registered)[0]
    true_c = np.stack([camera_centre(cam_from_world[index[n]]) for n in registered])
    a, b = true_c - true_c.mean(0), sfm_c - sfm_c.mean(0)
    return float(math.sqrt((a * a).sum() / (b * b).sum()))


def check_drive(domain: str, seed: int, frames: int, window: int, size: tuple[int, int]
                ) -> list[float]:
    """Each window's estimate over the truth (NaN: no estimate) of one generated drive."""
    from sfm_ttr_ros.core.frames import Frame
    from sfm_ttr_ros.core.metric.ground import ground_plane
    from sfm_ttr_ros.core.metric.metric_config import MetricConfig
    from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor
    from sfm_ttr_ros.data.synthetic import make_sequence

    seq = make_sequence(seed=seed, domain=domain, num_frames=frames, width=size[0],
                        height=size[1])
    cfg = MetricConfig(source="camera_height", camera_height=seq.params.camera_height)
    all_frames = [Frame(i, im, stamp=s) for i, (im, s) in
                  enumerate(zip(seq.images, seq.stamps, strict=True))]
    index = {f.name: f.index for f in all_frames}
    ratios = []
    with SfmReconstructor() as rec:
        for start in range(0, frames - window + 1, window):
            sfm = rec.reconstruct(all_frames[start:start + window], seq.intrinsics)
            registered = sorted(sfm.frames, key=index.get) if sfm.ok else []
            if len(registered) < 3:
                ratios.append(float("nan"))
                print(f"  {domain}{seed} frames {start}-{start + window - 1}: SfM failed")
                continue
            plane = ground_plane(sfm, registered, cfg)
            truth = true_metres_per_unit(sfm, registered, seq.cam_from_world, index)
            est = cfg.camera_height / plane.height if math.isfinite(plane.height) else math.nan
            ratios.append(est / truth)
            why = f", {plane.reason}" if plane.reason else ""
            print(f"  {domain}{seed} frames {start}-{start + window - 1}: estimate / truth "
                  f"{est / truth:.3f} ({plane.inliers} inliers{why})", flush=True)
    return ratios


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--domain", nargs="+", default=["C"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--window", type=int, default=15)
    ap.add_argument("--width", type=int, default=621)
    ap.add_argument("--height", type=int, default=188)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    worst = []
    for domain in args.domain:
        for seed in args.seeds:
            r = np.array(check_drive(domain, seed, args.frames, args.window,
                                     (args.width, args.height)))
            err = np.abs(r - 1)
            worst.append(float(np.nanmax(err)) if np.isfinite(r).any() else math.nan)
            print(f"{domain}{seed}: worst {worst[-1]:.3f}, estimates {np.isfinite(r).sum()} of "
                  f"{r.size}", flush=True)
    print(f"worst over all drives {np.nanmax(worst):.3f} ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
