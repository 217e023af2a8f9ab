"""What ``~/cloud`` costs per frame: building the PointCloud2 of one live depth
(:func:`msg_adapters.depth_to_pointcloud2`, the node's code path: back-projection with the
CameraInfo beside the depth, every ``stride``-th pixel, packed RGB) and serialising it, on a
generated KITTI-size frame (its exact depth: sky and beyond 200 m invalid), per stride and
range limit; and the CameraInfo republished beside each depth image (:func:`camera_info_for`).

Answered for docs/node.md ("Dense cloud"): default ``cloud.stride`` 4.

    .venv/bin/python scripts/studies/cloud_cost.py [--width 1242 --height 375 --repeats 100]
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import time

import numpy as np


def _median_ms(fn, repeats: int) -> tuple[float, float]:
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    times.sort()
    return statistics.median(times) * 1e3, times[int(0.95 * (len(times) - 1))] * 1e3


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--width", type=int, default=1242)
    p.add_argument("--height", type=int, default=375)
    p.add_argument("--repeats", type=int, default=100)
    p.add_argument("--strides", type=int, nargs="+", default=[2, 4, 8])
    args = p.parse_args(argv)

    from rclpy.serialization import serialize_message
    from std_msgs.msg import Header

    from msg_adapters import camera_info_for, depth_to_pointcloud2, intrinsics_to_camera_info
    from sfm_ttr_ros.data.synthetic import make_sequence

    seq = make_sequence(seed=0, domain="B", num_frames=1, width=args.width, height=args.height)
    depth = np.where(seq.depths[0] > 0, seq.depths[0], np.nan).astype(np.float32)
    rgb = seq.images[0]
    info = intrinsics_to_camera_info(seq.intrinsics, Header(frame_id="camera"))
    rows = []
    for stride in args.strides:
        for max_range in (0.0, 40.0):
            build = functools.partial(depth_to_pointcloud2, depth, rgb, info, stride, max_range)
            msg = build()
            med, p95 = _median_ms(build, args.repeats)
            ser, _ = _median_ms(functools.partial(serialize_message, msg), args.repeats)
            rows.append({"stride": stride, "max_range": max_range, "points": int(msg.width),
                         "bytes": len(msg.data), "build_ms_median": round(med, 3),
                         "build_ms_p95": round(p95, 3), "serialize_ms_median": round(ser, 3)})
            print(json.dumps(rows[-1]))
    info_ms, _ = _median_ms(lambda: camera_info_for(info, args.width, args.height, Header()),
                            args.repeats)
    print(json.dumps({"camera_info_ms_median": round(info_ms, 4)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
