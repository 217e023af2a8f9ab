"""The node's own DDS profile (ros/dds.py): when it is applied, and that Fast DDS takes it and
carries a KITTI-size depth image through it (a profile Fast DDS rejects is only a log line)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from sfm_ttr_ros.ros import dds
from sfm_ttr_ros.ros.share import find_share_file

PROFILE = find_share_file("params", dds.PROFILE_NAME)
VAR = "FASTRTPS_DEFAULT_PROFILES_FILE"


def test_the_profile_ships_with_the_package():
    assert PROFILE is not None and PROFILE.parent.name == "params"


def test_applied_only_where_nobody_chose_otherwise(tmp_path):
    env: dict[str, str] = {}
    assert str(PROFILE) in dds.apply_profile(env, tmp_path) and env[VAR] == str(PROFILE)
    for chosen in ({"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}, {VAR: "/mine.xml"},
                   {"FASTDDS_DEFAULT_PROFILES_FILE": "/mine.xml"}, {"SKIP_DEFAULT_XML_FILE": "1"},
                   {dds.OPT_VAR: "none"}):
        env = dict(chosen)
        note = dds.apply_profile(env, tmp_path)
        assert env.get(VAR) == chosen.get(VAR), (chosen, note)  # untouched
        assert "none" in note or "user's" in note
    env = {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    dds.apply_profile(env, tmp_path)
    assert env[VAR] == str(PROFILE)  # Fast DDS named explicitly
    (tmp_path / "DEFAULT_FASTDDS_PROFILES.xml").write_text("<profiles/>")
    env = {}
    assert "working folder" in dds.apply_profile(env, tmp_path) and VAR not in env
    other = tmp_path / "other.xml"
    other.write_text("<profiles/>")
    env = {dds.OPT_VAR: str(other)}
    dds.apply_profile(env, tmp_path / "nowhere")
    assert env[VAR] == str(other)
    env = {dds.OPT_VAR: str(tmp_path / "missing.xml")}
    assert "not found" in dds.apply_profile(env, tmp_path / "nowhere") and VAR not in env


PUB_SUB = """
import sys, time, numpy as np, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from msg_adapters import make_header, numpy_to_image
rclpy.init()
node = rclpy.create_node("dds_profile_probe")
qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
got = []
node.create_subscription(Image, "probe", got.append, qos)
pub = node.create_publisher(Image, "probe", qos)
depth = np.random.default_rng(0).random((375, 1242)).astype(np.float32)
end = time.monotonic() + 20
while pub.get_subscription_count() < 1 and time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
for i in range(3):
    pub.publish(numpy_to_image(depth, "32FC1", make_header(i, "cam")))
while len(got) < 3 and time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
ok = len(got) == 3 and all(bytes(m.data) == depth.tobytes() for m in got)
print("received", len(got), "intact", ok)
sys.exit(0 if ok else 1)
"""


def run_probe(profile: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, VAR: str(profile)}
    return subprocess.run([sys.executable, "-c", PUB_SUB], env=env, capture_output=True,
                          text=True, timeout=60)


def test_fast_dds_takes_the_profile_and_carries_a_kitti_size_depth_image():
    r = run_probe(PROFILE)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "received 3 intact True" in r.stdout
    assert "Error" not in r.stdout + r.stderr, r.stdout  # Fast DDS logs a rejected profile


def test_a_broken_profile_is_seen(tmp_path):
    """The check above can fail: Fast DDS logs ``[XMLPARSER Error]`` (on stdout) for a profile
    it cannot read, and goes on with its defaults."""
    bad = tmp_path / "bad.xml"
    text = PROFILE.read_text()
    assert "<segment_size>67108864</segment_size>" in text
    bad.write_text(text.replace("<segment_size>67108864", "<segment_size>sixty-four MB"))
    r = run_probe(bad)
    assert "XMLPARSER" in r.stdout and "Error" in r.stdout, r.stdout + r.stderr
