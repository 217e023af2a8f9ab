"""rosbag2 side of KITTI end to end: drive -> bag (mcap, sqlite3), reading back, the real
calibration, playing into rclpy subscribers (+ /clock, + recording), evaluating a bag, errors."""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from msg_adapters.image import image_to_depth, image_to_numpy
from msg_adapters.odometry import odometry_to_position
from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.evaluation import EvalConfig
from sfm_ttr_ros.data.kitti import read_depth_png, write_kitti_drive
from sfm_ttr_ros.data.synthetic import make_sequence
from sfm_ttr_ros.ros.bag import STORAGES, BagRecorder, bag_topics, depth_msg, read_bag
from sfm_ttr_ros.ros.bag_evaluation import DEFAULT_PRED_TOPIC, evaluate_bag
from sfm_ttr_ros.ros.kitti_bag import (
    CAMERA_INFO_TOPIC,
    DEPTH_GT_TOPIC,
    IMAGE_TOPIC,
    ODOM_TOPIC,
    kitti_timestamp_ns,
    kitti_to_bag,
)

REPO = Path(__file__).resolve().parents[1]
REAL_CALIB = REPO.parent / "shared" / "data" / "kitti_calib_2011_09_26" / "calib_cam_to_cam.txt"
N_FRAMES, GT_SKIP = 8, 2  # frames 2..5 have ground truth
W, H = 160, 48


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    root = tmp_path_factory.mktemp("kitti")
    seq = make_sequence(seed=0, domain="A", num_frames=N_FRAMES, width=W, height=H)
    name = write_kitti_drive(seq, root / "raw", root / "gt", gt_skip_ends=GT_SKIP)
    return root / "raw", root / "gt", name, seq


@pytest.fixture(scope="module")
def bags(drive, tmp_path_factory):
    raw, gt, name, _ = drive
    out = tmp_path_factory.mktemp("bags")
    return {s: kitti_to_bag(raw, name, out / f"drive_{s}", gt, storage=s).path for s in STORAGES}


def _drive_dir(raw: Path, name: str) -> Path:
    return raw / name[:10] / name


def _file_stamps_ns(raw: Path, name: str) -> list[int]:
    lines = (_drive_dir(raw, name) / "image_02" / "timestamps.txt").read_text().splitlines()
    return [kitti_timestamp_ns(s) for s in lines if s.strip()]


# ---------------------------------------------------------------------------------------------
# Conversion and reading
# ---------------------------------------------------------------------------------------------


def test_timestamp_ns_is_exact():
    assert kitti_timestamp_ns("2011-09-26 13:02:25.964389445") == 1317042145964389445
    assert kitti_timestamp_ns("1970-01-01 00:00:01") == 1_000_000_000
    assert kitti_timestamp_ns("1970-01-01 00:00:01.5") == 1_500_000_000
    with pytest.raises(InputError, match="timestamp"):
        kitti_timestamp_ns("26/09/2011")


@pytest.mark.parametrize("storage", STORAGES)
def test_converted_bag_roundtrip(drive, bags, storage):
    raw, gt_root, name, _ = drive
    bag = bags[storage]
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == storage
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert {t: v["message_count"] for t, v in topics.items()} == {
        IMAGE_TOPIC: N_FRAMES, CAMERA_INFO_TOPIC: N_FRAMES, DEPTH_GT_TOPIC: N_FRAMES - 2 * GT_SKIP,
        ODOM_TOPIC: N_FRAMES}
    for t in topics.values():
        assert t["topic_metadata"]["serialization_format"] == "cdr"
    # The type hashes are those of the installed Jazzy message packages (ros2 bag play checks).
    share = Path(sys.prefix) / "share"
    for tmeta in (t["topic_metadata"] for t in topics.values()):
        jpath = share / (tmeta["type"] + ".json")
        if jpath.is_file():
            hashes = {h["type_name"]: h["hash_string"]
                      for h in json.loads(jpath.read_text())["type_hashes"]}
            assert tmeta["type_description_hash"] == hashes[tmeta["type"]]

    stamps = _file_stamps_ns(raw, name)
    img_dir = _drive_dir(raw, name) / "image_02" / "data"
    gt_dir = gt_root / "val" / name / "proj_depth" / "groundtruth" / "image_02"
    seen = {IMAGE_TOPIC: [], CAMERA_INFO_TOPIC: [], DEPTH_GT_TOPIC: [], ODOM_TOPIC: []}
    order = []
    for topic, msgtype, st, msg in read_bag(bag):
        order.append(topic)
        seen[topic].append(st)
        i = stamps.index(st)
        if topic == ODOM_TOPIC:  # the generated drive's camera pose (poses.txt), metres
            assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "camera_color_left")
            stamp_s, xyz = odometry_to_position(msg)
            assert stamp_s == pytest.approx(st / 1e9, abs=1e-6)
            assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(st, 10**9)
            np.testing.assert_allclose(xyz, np.linalg.inv(drive[3].cam_from_world[i])[:3, 3],
                                       atol=1e-9)
            continue
        assert msg.header.frame_id == "camera_color_left"
        if topic == IMAGE_TOPIC:
            assert msgtype == "sensor_msgs/msg/Image" and msg.encoding == "rgb8"
            png = cv2.cvtColor(cv2.imread(str(img_dir / f"{i:010d}.png")), cv2.COLOR_BGR2RGB)
            np.testing.assert_array_equal(image_to_numpy(msg), png)
        elif topic == CAMERA_INFO_TOPIC:
            assert (msg.width, msg.height) == (W, H)
            np.testing.assert_allclose(msg.k.reshape(3, 3), drive[3].intrinsics.K, rtol=1e-12)
            assert msg.distortion_model == "plumb_bob" and not np.any(msg.d)
            np.testing.assert_array_equal(msg.r, np.eye(3).ravel())
            np.testing.assert_allclose(msg.p.reshape(3, 4)[:, :3], drive[3].intrinsics.K)
        else:
            assert msg.encoding == "32FC1"
            assert GT_SKIP <= i < N_FRAMES - GT_SKIP
            depth = image_to_depth(msg)
            want = read_depth_png(gt_dir / f"{i:010d}.png")
            np.testing.assert_array_equal(np.isnan(depth), want == 0)
            np.testing.assert_array_equal(depth[want > 0], want[want > 0])
    # every frame, in order, stamped exactly as timestamps.txt; camera_info comes first
    assert seen[IMAGE_TOPIC] == stamps == seen[CAMERA_INFO_TOPIC] == seen[ODOM_TOPIC]
    assert seen[DEPTH_GT_TOPIC] == stamps[GT_SKIP:N_FRAMES - GT_SKIP]
    assert order[:2] == [CAMERA_INFO_TOPIC, IMAGE_TOPIC]
    assert set(bag_topics(bag)) == set(seen)
    # filtering by topic
    assert [t for t, *_ in read_bag(bag, [DEPTH_GT_TOPIC])] == [DEPTH_GT_TOPIC] * 4


def test_odometry_comes_from_poses_txt_or_oxts_or_is_absent(drive, tmp_path, capsys):
    from sfm_ttr_ros.tools.cli import main

    raw, _, name, _ = drive
    copy = tmp_path / "raw"
    shutil.copytree(raw, copy)
    drive_dir = _drive_dir(copy, name)
    (drive_dir / "poses.txt").unlink()
    # neither poses.txt nor oxts/: no /kitti/odom, and the command says so
    assert main(["kitti-to-bag", "--kitti-raw", str(copy), "--drive", name, "--out",
                 str(tmp_path / "none"), "--max-frames", "2", "-q"]) == 0
    assert "no odometry (/kitti/odom not written)" in capsys.readouterr().out
    assert ODOM_TOPIC not in bag_topics(tmp_path / "none")
    # real KITTI's GPS/IMU: the IMU's pose (devkit conversion), child frame imu_link
    er, lat0 = 6378137.0, 49.0
    (drive_dir / "oxts" / "data").mkdir(parents=True)
    for i in range(N_FRAMES):  # 1 m a frame to the east, heading east (yaw 0)
        lon = 8.4 + np.degrees(1.0 * i / (er * np.cos(np.radians(lat0))))
        (drive_dir / "oxts" / "data" / f"{i:010d}.txt").write_text(
            " ".join(map(str, [lat0, lon, 110.0, 0.0, 0.0, 0.0] + [0.0] * 24)) + "\n")
    (drive_dir / "oxts" / "timestamps.txt").write_text(
        (drive_dir / "image_02" / "timestamps.txt").read_text())
    res = kitti_to_bag(copy, name, tmp_path / "oxts", start=2, max_frames=3)
    assert res.odometry == "oxts" and res.counts[ODOM_TOPIC] == 3
    odom = [m for _, _, _, m in read_bag(tmp_path / "oxts", [ODOM_TOPIC])]
    assert {(m.header.frame_id, m.child_frame_id) for m in odom} == {("odom", "imu_link")}
    xyz = np.array([odometry_to_position(m)[1] for m in odom])
    np.testing.assert_allclose(xyz, [[2, 0, 0], [3, 0, 0], [4, 0, 0]], atol=1e-6)


def test_convert_without_gt_and_a_frame_range(drive, tmp_path):
    raw, _, name, _ = drive
    res = kitti_to_bag(raw, name, tmp_path / "b", storage="sqlite3", start=3, max_frames=2)
    assert res.frames == 2 and res.gt_frames == 0
    assert res.counts == {IMAGE_TOPIC: 2, CAMERA_INFO_TOPIC: 2, ODOM_TOPIC: 2}
    stamps = _file_stamps_ns(raw, name)
    assert [st for _, _, st, _ in read_bag(tmp_path / "b", [IMAGE_TOPIC])] == stamps[3:5]


def test_real_calibration_camera_info(tmp_path, shared_data):
    calib = shared_data / "kitti_calib_2011_09_26" / "calib_cam_to_cam.txt"
    if not calib.is_file():
        pytest.skip(f"real KITTI calibration not found: {calib}")
    name = "2011_09_26_drive_0001_sync"
    data = tmp_path / "raw" / "2011_09_26" / name / "image_02" / "data"
    data.mkdir(parents=True)
    shutil.copy(calib, tmp_path / "raw" / "2011_09_26" / "calib_cam_to_cam.txt")
    for i in range(2):  # S_rect_02 of the real file: 1242 x 375
        img = np.full((375, 1242, 3), 40 * i, np.uint8)
        cv2.imwrite(str(data / f"{i:010d}.png"), img)
    (data.parent / "timestamps.txt").write_text(
        "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.074669719\n")
    kitti_to_bag(tmp_path / "raw", name, tmp_path / "bag", storage="mcap")
    infos = [m for _, _, _, m in read_bag(tmp_path / "bag", [CAMERA_INFO_TOPIC])]
    assert len(infos) == 2
    k = infos[0].k.reshape(3, 3)
    assert (k[0, 0], k[1, 1], k[0, 2], k[1, 2]) == pytest.approx(
        (721.5377, 721.5377, 609.5593, 172.854))
    assert (infos[0].width, infos[0].height) == (1242, 375)
    assert infos[0].p.reshape(3, 4)[0, 3] == pytest.approx(44.85728)  # P_rect_02 as it is
    np.testing.assert_array_equal(infos[0].r, np.eye(3).ravel())
    stamps = [st for _, _, st, _ in read_bag(tmp_path / "bag", [IMAGE_TOPIC])]
    assert stamps == [1317042145964389445, 1317042146074669719]


# ---------------------------------------------------------------------------------------------
# Playing (rclpy)
# ---------------------------------------------------------------------------------------------


@pytest.fixture()
def ros_sub():
    """An in-process rclpy subscriber node (own context) spinning in a thread."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.context import Context
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("bag_test_sub", context=ctx)
    got: dict[str, list] = {}
    lock = threading.Lock()
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=30,
                     reliability=ReliabilityPolicy.RELIABLE)  # as the refiner subscribes

    def subscribe(topic, cls):
        def cb(msg):
            with lock:
                got.setdefault(topic, []).append(msg)
        node.create_subscription(cls, topic, cb, qos)

    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)

    def spin():
        try:
            ex.spin()
        except ExternalShutdownException:
            pass

    th = threading.Thread(target=spin, daemon=True)
    th.start()

    def wait(counts, timeout=10.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with lock:
                if all(len(got.get(t, [])) >= n for t, n in counts.items()):
                    return True
            time.sleep(0.02)
        return False

    yield subscribe, got, wait
    ex.shutdown(timeout_sec=2.0)
    th.join(timeout=5)
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)


def test_play_into_subscriber_with_clock_and_recording(drive, bags, ros_sub, tmp_path):
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo, Image

    from sfm_ttr_ros.ros.player import TopicRecorder, play_bag

    raw, _, name, _ = drive
    subscribe, got, wait = ros_sub
    subscribe(IMAGE_TOPIC, Image)
    subscribe(CAMERA_INFO_TOPIC, CameraInfo)
    subscribe("/clock", Clock)
    bag = bags["mcap"]
    stamps = _file_stamps_ns(raw, name)
    with TopicRecorder(tmp_path / "rec", {IMAGE_TOPIC: "sensor_msgs/msg/Image"},
                       storage="sqlite3") as rec:
        t0 = time.monotonic()
        res = play_bag(bag, rate=4.0, clock=True, progress=False,
                       wait_topics=[IMAGE_TOPIC, CAMERA_INFO_TOPIC])
        assert rec.wait_for({IMAGE_TOPIC: N_FRAMES}, timeout=10)
    played = time.monotonic() - t0
    assert res.published == {IMAGE_TOPIC: N_FRAMES, CAMERA_INFO_TOPIC: N_FRAMES,
                              DEPTH_GT_TOPIC: N_FRAMES - 2 * GT_SKIP, ODOM_TOPIC: N_FRAMES}
    assert sorted(res.no_subscriber) == sorted([DEPTH_GT_TOPIC, ODOM_TOPIC])
    assert not res.unacked
    # recorded timing: (N-1) x 0.1 s of bag time at 4x
    span = (stamps[-1] - stamps[0]) / 1e9
    assert res.bag_seconds == pytest.approx(span, abs=1e-6)
    assert span / 4 * 0.9 <= res.seconds < span / 4 + 1.0 and played >= span / 4 * 0.9
    assert wait({IMAGE_TOPIC: N_FRAMES, CAMERA_INFO_TOPIC: N_FRAMES, "/clock": res.clock})

    images = got[IMAGE_TOPIC]
    assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in images] == stamps
    first = next(m for _, _, _, m in read_bag(bag, [IMAGE_TOPIC]))
    assert images[0].encoding == "rgb8" and bytes(images[0].data) == bytes(first.data)
    assert got[CAMERA_INFO_TOPIC][0].k[0] == pytest.approx(drive[3].intrinsics.fx)
    clocks = [m.clock.sec * 10**9 + m.clock.nanosec for m in got["/clock"]]
    assert clocks == sorted(clocks) and set(stamps) <= set(clocks)
    assert stamps[0] <= clocks[0] and clocks[-1] == stamps[-1]
    # the recording holds the very bytes that were played
    assert rec.counts == {IMAGE_TOPIC: N_FRAMES}
    a = [(st, bytes(m.data)) for _, _, st, m in read_bag(bag, [IMAGE_TOPIC])]
    b = [(st, bytes(m.data)) for _, _, st, m in read_bag(tmp_path / "rec", [IMAGE_TOPIC])]
    assert a == b


def test_play_errors(bags, tmp_path):
    pytest.importorskip("rclpy")
    from sfm_ttr_ros.ros.player import play_bag

    with pytest.raises(InputError, match="no subscriber on each of /kitti/camera_color_left/"
                                         "depth_gt after 0.3 s"):
        play_bag(bags["sqlite3"], wait_topics=[DEPTH_GT_TOPIC], wait_timeout=0.3,
                 progress=False)
    with pytest.raises(InputError, match="not in bag"):
        play_bag(bags["sqlite3"], topics=["/nope"], progress=False)
    with pytest.raises(InputError, match="rate"):
        play_bag(bags["sqlite3"], rate=0.0)
    with pytest.raises(InputError, match="not found"):
        play_bag(tmp_path / "missing")


PLAY_SCRIPT = """
import argparse, sys
from sfm_ttr_ros.tools.cli_bag import add_commands
p = argparse.ArgumentParser()
add_commands(p.add_subparsers(dest="command", required=True))
a = p.parse_args(sys.argv[1:])
sys.exit(a.func(a))
"""


def test_play_ctrl_c_exits_130_without_traceback(bags):
    pytest.importorskip("rclpy")
    # A shell's background job inherits SIGINT ignored, and Python then installs no
    # KeyboardInterrupt handler: give the player the default disposition a terminal gives it.
    proc = subprocess.Popen(
        [sys.executable, "-c", PLAY_SCRIPT, "play", str(bags["mcap"]), "--rate", "0.02",
         "--no-wait"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        first = proc.stderr.readline()  # the progress bar's first line: playback has begun
        assert first.startswith("play drive_mcap 1/"), first
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in err and "interrupted after" in err


# ---------------------------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------------------------


def _gt_frames(bag):
    return [(st, image_to_depth(m)) for _, _, st, m in read_bag(bag, [DEPTH_GT_TOPIC])]


def test_evaluate_bag_matches_by_stamp(bags, tmp_path):
    gt_bag = bags["mcap"]
    gts = _gt_frames(gt_bag)
    assert len(gts) == 4
    pred_bag = tmp_path / "pred"
    extra = gts[-1][0] + 123  # a prediction with no GT frame
    with BagRecorder(pred_bag, "sqlite3") as rec:
        rec.add_topic(DEFAULT_PRED_TOPIC, "sensor_msgs/msg/Image")
        for st, gt in gts[:-1]:  # the last GT frame gets no prediction
            rec.write(DEFAULT_PRED_TOPIC, depth_msg(2.0 * gt, st, "camera_color_left"))
        rec.write(DEFAULT_PRED_TOPIC, depth_msg(gts[0][1], extra, "camera_color_left"))

    res = evaluate_bag(pred_bag, gt_bag, config=EvalConfig(median_scaling=True))
    assert res["frames"] == 3 and res["matched"] == 3
    assert res["missing_gt"] == 1 and res["missing_pred"] == 1
    assert res["pred_frames"] == 4 and res["gt_frames"] == 4
    assert res["abs_rel"] == pytest.approx(0.0, abs=1e-6) and res["a1"] == 1.0
    assert res["ratio_median"] == pytest.approx(0.5)

    res = evaluate_bag(pred_bag, gt_bag, config=EvalConfig(median_scaling=False))
    want = []
    for _, gt in gts[:-1]:
        v = gt[(gt > 1e-3) & (gt < 80)].astype(np.float64)
        want.append(np.mean(np.abs(v - np.clip(2 * v, 1e-3, 80)) / v))
    assert res["abs_rel"] == pytest.approx(float(np.mean(want)), rel=1e-6)
    assert res["abs_rel"] > 0.5

    # predictions and GT in one bag
    both = tmp_path / "both"
    with BagRecorder(both, "mcap") as rec:
        rec.add_topic(DEPTH_GT_TOPIC, "sensor_msgs/msg/Image")
        rec.add_topic("/pred", "sensor_msgs/msg/Image")
        for st, gt in gts:
            rec.write(DEPTH_GT_TOPIC, depth_msg(gt, st, "c"))
            rec.write("/pred", depth_msg(3.0 * gt, st, "c"))
    res = evaluate_bag(both, pred_topic="/pred")
    assert res["frames"] == 4 and res["missing_gt"] == res["missing_pred"] == 0
    assert res["abs_rel"] == pytest.approx(0.0, abs=1e-6)


def test_evaluate_bag_reads_the_refiners_relative_twin_beside_its_metric_topic(tmp_path):
    """Depth not yet in metres comes on ~/depth_relative/image (REP 118): the evaluation of the
    refiner's depth topic takes each frame from whichever of the two carries it."""
    from sfm_ttr_ros.ros import names

    gts = [(st, np.full((8, 12), 2.0 + st / 1e9, np.float32)) for st in
           (1_000_000_000, 2_000_000_000, 3_000_000_000, 4_000_000_000)]
    relative = names.relative_twin_of(DEFAULT_PRED_TOPIC)
    bag = tmp_path / "mixed"
    with BagRecorder(bag, "mcap") as rec:
        for topic in (DEPTH_GT_TOPIC, DEFAULT_PRED_TOPIC, relative):
            rec.add_topic(topic, "sensor_msgs/msg/Image")
        for i, (st, gt) in enumerate(gts):
            rec.write(DEPTH_GT_TOPIC, depth_msg(gt, st, "c"))
            # the first two frames before the scale was known: network units (x 3)
            rec.write(relative if i < 2 else DEFAULT_PRED_TOPIC,
                      depth_msg(gt * (3.0 if i < 2 else 1.0), st, "c"))
    res = evaluate_bag(bag)
    assert res["frames"] == 4 and res["pred_relative_frames"] == 2
    assert res["pred_topic"] == f"{DEFAULT_PRED_TOPIC} + {relative}"
    assert res["abs_rel"] == pytest.approx(0.0, abs=1e-6)  # median-scaled: either unit
    metres = evaluate_bag(bag, config=EvalConfig(median_scaling=False))
    assert metres["abs_rel"] == pytest.approx(1.0, abs=1e-6)  # (0 + 0 + 2 + 2) / 4


def test_evaluate_bag_command(bags, tmp_path, capsys):
    from sfm_ttr_ros.tools.cli_bag import evaluate_bag_command

    both = tmp_path / "both"
    gts = _gt_frames(bags["sqlite3"])
    with BagRecorder(both, "sqlite3") as rec:
        rec.add_topic(DEPTH_GT_TOPIC, "sensor_msgs/msg/Image")
        rec.add_topic(DEFAULT_PRED_TOPIC, "sensor_msgs/msg/Image")
        for st, gt in gts:
            rec.write(DEPTH_GT_TOPIC, depth_msg(gt, st, "c"))
            rec.write(DEFAULT_PRED_TOPIC, depth_msg(gt * 1.1, st, "c"))
    out = tmp_path / "res.json"
    args = argparse.Namespace(bag=str(both), gt_bag=None, pred_topic=DEFAULT_PRED_TOPIC,
                              gt_topic=DEPTH_GT_TOPIC, eigen_crop=True, median_scaling=False,
                              max_depth=80.0, out=str(out), quiet=True)
    assert evaluate_bag_command(args) == 0
    text = capsys.readouterr().out
    assert "| /refiner/depth/image |" in text and "eigen crop on" in text
    saved = json.loads(out.read_text())
    assert saved["frames"] == 4 and saved["abs_rel"] == pytest.approx(0.1, abs=1e-4)
    # no prediction stamp matches a GT stamp: exit code 1 and the counts, not an exception
    shifted = tmp_path / "shifted"
    with BagRecorder(shifted, "mcap") as rec:
        rec.add_topic(DEFAULT_PRED_TOPIC, "sensor_msgs/msg/Image")
        for st, gt in gts:
            rec.write(DEFAULT_PRED_TOPIC, depth_msg(gt, st + 1, "c"))
    args.bag, args.gt_bag, args.out = str(shifted), str(bags["mcap"]), None
    assert evaluate_bag_command(args) == 1
    captured = capsys.readouterr()
    assert "4 predictions without GT, 4 GT frames without a prediction" in captured.out
    assert "no frame could be evaluated" in captured.err
    args.gt_topic = IMAGE_TOPIC  # rgb8: not a depth image
    args.bag = str(both)
    with pytest.raises(InputError, match="32FC1"):
        evaluate_bag_command(args)


# ---------------------------------------------------------------------------------------------
# Bad input, CLI glue, ROS-free import
# ---------------------------------------------------------------------------------------------


def _parser():
    from sfm_ttr_ros.tools.cli_bag import add_commands

    p = argparse.ArgumentParser(prog="sfm-ttr")
    add_commands(p.add_subparsers(dest="command", required=True))
    return p


def test_bad_input(drive, bags, tmp_path):
    raw, gt, name, _ = drive
    missing = "2011_09_26_drive_0099_sync"
    with pytest.raises(InputError, match="drive folder not found"):
        kitti_to_bag(raw, missing, tmp_path / "x")
    with pytest.raises(InputError, match="no ground truth for"):
        kitti_to_bag(raw, name, tmp_path / "x", gt_root=tmp_path)
    with pytest.raises(InputError, match="exists already"):
        kitti_to_bag(raw, name, bags["mcap"])
    with pytest.raises(InputError, match="unknown bag storage"):
        kitti_to_bag(raw, name, tmp_path / "x", storage="rosbag1")
    assert not (tmp_path / "x").exists()
    # a missing calibration file
    raw2 = tmp_path / "raw2"
    shutil.copytree(raw, raw2)
    (raw2 / "2011_09_26" / "calib_cam_to_cam.txt").unlink()
    with pytest.raises(InputError, match="calib_cam_to_cam.txt"):
        kitti_to_bag(raw2, name, tmp_path / "x")
    # an image whose size differs from S_rect: no partial bag is left behind
    img = _drive_dir(raw2, name) / "image_02" / "data" / "0000000003.png"
    shutil.copy(raw / "2011_09_26" / "calib_cam_to_cam.txt", raw2 / "2011_09_26")
    cv2.imwrite(str(img), np.zeros((10, 20, 3), np.uint8))
    with pytest.raises(InputError, match="S_rect_02"):
        kitti_to_bag(raw2, name, tmp_path / "x")
    assert not (tmp_path / "x").exists()

    # unreadable bags, unknown topics
    (tmp_path / "notabag").mkdir()
    with pytest.raises(InputError, match="no metadata.yaml"):
        list(read_bag(tmp_path / "notabag"))
    broken = tmp_path / "broken"
    shutil.copytree(bags["sqlite3"], broken)
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: [garbage\n")
    with pytest.raises(InputError, match="cannot read bag"):
        list(read_bag(broken))
    with pytest.raises(InputError, match="not found"):
        list(read_bag(tmp_path / "nope"))
    with pytest.raises(InputError, match="/nope not in bag"):
        list(read_bag(bags["mcap"], ["/nope"]))
    with pytest.raises(InputError, match="topic /refiner/depth/image not in bag"):
        evaluate_bag(bags["mcap"])
    with pytest.raises(InputError, match="CameraInfo, not"):
        evaluate_bag(bags["mcap"], pred_topic=CAMERA_INFO_TOPIC)

    # the CLI commands raise InputError (cli.main maps it to exit code 2)
    args = _parser().parse_args(["kitti-to-bag", "--kitti-raw", str(raw), "--drive", missing,
                                 "--out", str(tmp_path / "y"), "-q"])
    with pytest.raises(InputError, match="not found"):
        args.func(args)
    args = _parser().parse_args(["play", str(tmp_path / "nope"), "--no-wait", "-q"])
    with pytest.raises(InputError, match="bag not found"):
        args.func(args)


def test_cli_kitti_to_bag(drive, tmp_path, capsys):
    raw, gt, name, _ = drive
    out = tmp_path / "cli_bag"
    args = _parser().parse_args(["kitti-to-bag", "--kitti-raw", str(raw), "--drive", name,
                                 "--kitti-gt", str(gt), "--out", str(out), "--storage",
                                 "sqlite3", "-q"])
    assert args.func(args) == 0
    assert f"{N_FRAMES} frames {W}x{H}, {N_FRAMES - 2 * GT_SKIP} with ground truth" in (
        capsys.readouterr().out)
    assert (out / "metadata.yaml").is_file() and list(out.glob("*.db3"))


def test_bag_module_is_ros_free():
    """The bag tools run without ROS: converting, reading and evaluating import neither rclpy
    nor a message package (msg_adapters builds the rosbags messages, ROS-free)."""
    code = ("import sys, sfm_ttr_ros.ros.bag, sfm_ttr_ros.ros.kitti_bag, "
            "sfm_ttr_ros.ros.bag_evaluation, sfm_ttr_ros.tools.cli_bag, sfm_ttr_ros.ros.player\n"
            "import msg_adapters.image, msg_adapters.camera_info\n"
            "bad = [m for m in sys.modules if m.split('.')[0] in ('rclpy', 'sensor_msgs', "
            "'std_msgs', 'builtin_interfaces', 'rcl_interfaces')]\n"
            "assert not bad, bad\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert out.returncode == 0, out.stderr


def test_compressed_bag_holds_jpeg_images_of_the_drive(drive, tmp_path):
    from msg_adapters.compressed import compressed_to_rgb8
    from sfm_ttr_ros.ros.kitti_bag import COMPRESSED_IMAGE_MSGTYPE

    raw, _, name, seq = drive
    res = kitti_to_bag(raw, name, tmp_path / "c", storage="mcap", max_frames=4, compressed=True)
    topic = IMAGE_TOPIC + "/compressed"
    assert res.counts == {topic: 4, CAMERA_INFO_TOPIC: 4, ODOM_TOPIC: 4}
    assert bag_topics(tmp_path / "c")[topic].msgtype == COMPRESSED_IMAGE_MSGTYPE
    msgs = [m for _, _, _, m in read_bag(tmp_path / "c", [topic])]
    assert [m.format for m in msgs] == ["rgb8; jpeg compressed bgr8"] * 4
    for m, rgb in zip(msgs, seq.images[:4], strict=True):
        decoded = compressed_to_rgb8(m)
        assert decoded.shape == rgb.shape
        assert np.abs(decoded.astype(int) - rgb).mean() < 6  # JPEG quality 95
    raw_res = kitti_to_bag(raw, name, tmp_path / "r", storage="mcap", max_frames=4)
    size = {p: sum(f.stat().st_size for f in (tmp_path / p).rglob("*")) for p in ("c", "r")}
    assert size["c"] < size["r"] and raw_res.frames == 4
