"""The demo end to end: a generated drive → rosbag2 → played into the `refiner` node (a real
subprocess, as `ros2 run` starts it) → recorded ~/depth/image → evaluated against the GT topic.

The refined depth must beat the unrefined one on abs rel and RMSE for that drive. Small frames
and windows (8 frames every 4) keep it near a minute on 2 cores; everything
else (node, parameters file, QoS, player, recorder, evaluation) is what `sfm-ttr demo` runs."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest

from sfm_ttr_ros.core.models.registry import default_weights_available
from sfm_ttr_ros.tools.demo import (
    DemoOptions,
    _gain_by_part,
    _live_accounting,
    _live_line,
    run_demo,
)

pytestmark = pytest.mark.skipif(not default_weights_available(),
                                reason="default weights not trained yet")


def test_demo_replays_a_drive_through_refiner_and_refinement_helps(tmp_path):
    opts = DemoOptions(out=tmp_path / "demo", frames=16, width=640, height=192, domain="B",
                       seed=3, gt_skip_ends=1, timeout_s=400.0,
                       overrides=["window_size=8", "window_stride=4",
                                  "refinement.steps=60"])
    res = run_demo(opts)

    # every frame came back from the node, which then exited cleanly on SIGINT
    assert res["frames"] == 16
    assert res["refiner"]["received"] == 16
    assert res["refiner"]["exit_code"] == 0
    # every live frame is accounted: recorded, or counted as skipped by the node; none is lost
    # between node and recorder (the recorder matches the node's publishers before playing)
    node = res["refiner"]
    assert node["live_published"] + node["live_skipped"] == 16, node
    assert node["live_received"] == node["live_published"], node
    live = res["metrics"]["sfm_ttr_live"]
    base = res["metrics"].get("no_ttr (live's frames)", res["metrics"]["no_ttr"])
    assert live["frames"] == base["frames"] > 0
    before, after = res["metrics"]["no_ttr"], res["metrics"]["sfm_ttr"]
    assert before["frames"] == after["frames"] == res["gt_frames"] == 14
    assert after["abs_rel"] < before["abs_rel"], (before, after)
    assert after["rmse"] < before["rmse"], (before, after)
    assert res["relative_gain"]["abs_rel"] > 0 and res["relative_gain"]["rmse"] > 0
    # the live output by third of the drive, each third against no TTR on the same frames
    thirds = res["relative_gain_live_by_third"]
    assert len(thirds) == 3 and all(math.isfinite(g["abs_rel"]) for g in thirds), thirds

    out = tmp_path / "demo"
    assert json.loads((out / "results.json").read_text())["gt_frames"] == 14
    md = (out / "results.md").read_text()
    assert "abs_rel" in md and "positive = lower error" in md
    # the benchmark's report writer: the same metric table (4 decimals) and per-frame columns
    assert f"| sfm_ttr | {after['abs_rel']:.4f} |" in md
    rows = list(csv.DictReader(open(out / "per_frame.csv")))
    assert len(rows) == 14 and float(rows[0]["sfm_ttr_abs_rel"]) > 0
    assert list(rows[0])[:4] == ["index", "name", "no_ttr_abs_rel", "no_ttr_rmse"]
    assert (out / "figure.png").stat().st_size > 10_000
    shown = res["figure_frame"]  # the frame of median gain, and the results say which
    assert shown["count"] == 14 and shown["rank"] == 7 and shown["worst"] <= shown["best"]
    assert "The figure's frame: median frame by abs rel change (7 of 14)" in md
    log = (out / "refiner.log").read_text()
    assert "Traceback" not in log


def test_the_demo_tells_skipped_from_lost_live_frames():
    node = {"live_received": 12, "live_published": 28, "live_skipped": 2}
    line = _live_line(node, 30)
    assert line.startswith("12/30 live frames recorded")
    assert "skipped 2 under load" in line and "16 published by the node but not recorded" in line
    assert _live_line({"live_received": 30, "live_published": 30, "live_skipped": 0}, 30) == \
        "30/30 live frames recorded"


def test_the_demo_reads_the_nodes_live_count_from_its_accounting_file(tmp_path):
    from sfm_ttr_ros.ros.accounting import write_accounting

    path = tmp_path / "refiner_accounting.json"
    write_accounting(path, {"frames_received": 30, "live.received": 30, "live.published": 27,
                            "live.skipped": 3, "live.skipped.overflow": 3})
    assert _live_accounting(path) == {"live_published": 27, "live_skipped": 3}
    path.write_text("not json, as a node killed while writing would leave it")
    assert _live_accounting(path) == {"live_published": None, "live_skipped": None}
    assert _live_accounting(tmp_path / "absent.json") == {"live_published": None,
                                                          "live_skipped": None}


def test_the_demo_starts_the_node_with_its_accounting_file():
    from sfm_ttr_ros.ros.accounting import accounting_path
    from sfm_ttr_ros.tools.demo import refiner_command

    cmd = refiner_command(Path("kitti.yaml"), ["window_size=8"], accounting=Path("a.json"))
    assert accounting_path(cmd[2:]) == Path("a.json")  # as the node reads its sys.argv
    assert accounting_path(refiner_command(Path("kitti.yaml"), [])[2:]) is None


def test_the_figure_shows_the_frame_of_median_gain_and_says_so():
    from sfm_ttr_ros.tools.demo_figure import choose_frame

    # abs rel before -> after; relative change (+ = lower error): a +50%, b -15.5% (worse,
    # e.g. a close-by box), c +10%, d +20%, e 0%; f only before: not scored after
    before = {"1.000000000": 0.2, "2.000000000": 0.252, "3.000000000": 0.1,
              "4.000000000": 0.1, "5.000000000": 0.3, "6.000000000": 0.3}
    after = {"1.000000000": 0.1, "2.000000000": 0.291, "3.000000000": 0.09,
             "4.000000000": 0.08, "5.000000000": 0.3}
    rows = lambda d: [{"name": n, "abs_rel": v} for n, v in d.items()]  # noqa: E731
    shown = choose_frame(rows(before), rows(after))
    assert (shown.name, shown.rank, shown.count) == ("3.000000000", 3, 5)  # the median: +10%
    assert shown.change == pytest.approx(0.1)
    assert shown.worst == pytest.approx((0.252 - 0.291) / 0.252) and shown.best == 0.5
    assert shown.stamp_ns == 3_000_000_000
    text = "\n".join(shown.caption())
    assert "median frame" in text and "0.100 -> 0.090 (+10.0%" in text
    assert "-15.5% (worst) to +50.0% (best)" in text
    assert all(len(line) <= 80 for line in shown.caption())  # the legend's width
    # an even count: the lower middle (less gain), never the best frame
    del after["5.000000000"]
    assert choose_frame(rows(before), rows(after)).name == "3.000000000"
    assert choose_frame(rows(before), []) is None


def test_the_demo_takes_set_as_every_command_does():
    """``--set NAME=VALUE`` is checked by the schema before the node starts and reaches the
    node as a typed ``-p`` (a float keeps its dot, a string its quotes)."""
    from sfm_ttr_ros.core.errors import InputError
    from sfm_ttr_ros.tools.demo import refiner_command

    cmd = refiner_command(Path("kitti.yaml"), ["refinement.lr=1e-5", "window_size=8",
                                               "refinement.loss=sfm", "outputs=depth,points"])
    assert cmd[-8:] == ["-p", "refinement.lr:=1.0e-05", "-p", "window_size:=8", "-p",
                        'refinement.loss:="sfm"', "-p", 'outputs:="depth,points"']
    for bad in ("refinement.lr=fast", "no_such_parameter=1", "window_size=1",
                "ttr.predict_batch=4"):
        with pytest.raises(InputError):
            refiner_command(Path("kitti.yaml"), [bad])


def test_the_demo_gives_the_live_gain_by_third_of_the_drive_in_stamp_order():
    from sfm_ttr_ros.core.evaluation import METRICS

    def row(name, err):
        return {**{m: err for m in METRICS}, "name": name}

    # nine frames (the bag's order need not be the stamps'); no TTR errs 1.0 everywhere, the
    # live output 1.0 on the start-up weights, then 0.8, then 0.5; a frame only no TTR has
    # (skipped live) is left out of both
    stamps = [f"{sec}.{ns:09d}" for sec, ns in [(9, 5), (10, 0), (10, 100), (10, 200),
                                                (11, 0), (11, 50), (12, 0), (12, 1), (13, 0)]]
    base = [row(s, 1.0) for s in stamps] + [row("14.000000000", 1.0)]
    errors = [1.0] * 3 + [0.8] * 3 + [0.5] * 3
    live = [row(s, e) for s, e in zip(stamps, errors, strict=True)][::-1]
    thirds = _gain_by_part(base, live)
    assert [round(g["abs_rel"], 6) for g in thirds] == [0.0, 0.2, 0.5]
    assert [round(g["rmse"], 6) for g in thirds] == [0.0, 0.2, 0.5]


def test_the_demo_writes_an_image_folder_as_a_kitti_drive(tmp_path):
    """``--images/--intrinsics/--gt-depth``: the folder's frames, K and GT reach the KITTI
    layouts the rest of the demo reads; a frame without GT gets none."""
    import cv2
    import numpy as np

    from sfm_ttr_ros.core.errors import InputError
    from sfm_ttr_ros.data.sequence import open_kitti
    from sfm_ttr_ros.tools.demo import _image_folder_drive

    rng = np.random.default_rng(0)
    images, gt_dir = tmp_path / "images", tmp_path / "depth"
    images.mkdir()
    gt_dir.mkdir()
    rgb = [rng.integers(0, 255, (48, 64, 3), np.uint8) for _ in range(3)]
    depth_mm = rng.integers(500, 9000, (48, 64)).astype(np.uint16)
    for i, img in enumerate(rgb):
        cv2.imwrite(str(images / f"{i + 7:05d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        if i != 1:  # frame 1 has no GT
            cv2.imwrite(str(gt_dir / f"{i + 7:05d}.png"), depth_mm)
    (tmp_path / "K.txt").write_text("50 0 31.5\n0 51 23.5\n0 0 1\n")
    opts = DemoOptions(images=str(images), intrinsics=str(tmp_path / "K.txt"),
                       gt_depth=str(gt_dir), gt_scale=1000.0)
    raw, gt, drive = _image_folder_drive(opts, tmp_path / "out")

    seq = open_kitti(raw, drive, gt)
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.intrinsics.cx) == (50.0, 51.0, 31.5)
    assert all(np.array_equal(f.image, img) for f, img in zip(seq.frames(), rgb, strict=True))
    assert seq.gt(seq.names[1]) is None
    np.testing.assert_allclose(seq.gt(seq.names[2]), depth_mm / 1000.0, atol=1 / 256)
    with pytest.raises(InputError, match="--gt-depth"):
        _image_folder_drive(DemoOptions(images=str(images), intrinsics=str(tmp_path / "K.txt")),
                            tmp_path / "out2")


def test_the_poses_beside_an_image_folder_reach_the_bag_as_odometry(tmp_path):
    """hololens_000's layout: ``poses.txt`` beside ``images/`` (4x4 camera-to-world per image)
    becomes the drive's ``poses.txt`` and ``/kitti/odom`` in the bag, frame by frame."""
    import cv2
    import numpy as np

    from msg_adapters.odometry import odometry_to_position, quaternion_to_rotation
    from sfm_ttr_ros.core.errors import InputError
    from sfm_ttr_ros.ros.bag import read_bag
    from sfm_ttr_ros.ros.kitti_bag import IMAGE_TOPIC, ODOM_TOPIC, kitti_to_bag
    from sfm_ttr_ros.tools.demo import _image_folder_drive

    images, gt_dir = tmp_path / "images", tmp_path / "depth"
    images.mkdir()
    gt_dir.mkdir()
    poses = []
    for i in range(4):
        cv2.imwrite(str(images / f"{i:05d}.png"), np.full((24, 32, 3), 40 * i, np.uint8))
        cv2.imwrite(str(gt_dir / f"{i:05d}.png"), np.full((24, 32), 2000, np.uint16))
        a = 0.1 * i
        T = np.eye(4)
        T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        T[:3, 3] = [0.08 * i, -0.01 * i, 0.5]
        poses.append(T)
    np.savetxt(tmp_path / "poses.txt", np.array(poses).reshape(4, 16))
    (tmp_path / "K.txt").write_text("30 0 15.5\n0 30 11.5\n0 0 1\n")
    opts = DemoOptions(images=str(images), intrinsics=str(tmp_path / "K.txt"),
                       gt_depth=str(gt_dir), gt_scale=1000.0)
    raw, gt, drive = _image_folder_drive(opts, tmp_path / "out")
    res = kitti_to_bag(raw, drive, tmp_path / "bag", gt, start=1)
    assert res.odometry == "poses.txt" and res.counts[ODOM_TOPIC] == 3
    msgs = list(read_bag(tmp_path / "bag", [IMAGE_TOPIC, ODOM_TOPIC]))
    images_ns = [st for topic, _, st, _ in msgs if topic == IMAGE_TOPIC]
    odom = [m for topic, _, _, m in msgs if topic == ODOM_TOPIC]
    assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in odom] == images_ns
    assert [odometry_to_position(m)[0] for m in odom] == pytest.approx(
        [st / 1e9 for st in images_ns], abs=1e-6)
    for m, T in zip(odom, poses[1:], strict=True):
        assert (m.header.frame_id, m.child_frame_id) == ("odom", "camera_color_left")
        np.testing.assert_allclose(odometry_to_position(m)[1], T[:3, 3], atol=1e-12)
        o = m.pose.pose.orientation
        np.testing.assert_allclose(quaternion_to_rotation([o.x, o.y, o.z, o.w]), T[:3, :3],
                                   atol=1e-9)
    # a poses.txt that does not match the folder is refused, not guessed
    np.savetxt(tmp_path / "poses.txt", np.array(poses[:3]).reshape(3, 16))
    with pytest.raises(InputError, match="3 poses for 4 frames"):
        _image_folder_drive(opts, tmp_path / "out3")
