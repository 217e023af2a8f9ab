"""``sfm-ttr benchmark --split FILE`` and ``sfm-ttr run --split FILE``: many sequences in one
command, in this process or on Ray (tools/split/).

Three tiny generated drives (8 frames at 320x96, a tiny network, 5 steps) and a fourth
without ground truth:

* in process, interrupted by a real SIGINT after its first sequence, then resumed: the finished
  sequence is not computed again, the rest are (these results are the sequential reference);
* on a Ray cluster of two nodes on this machine, with one worker killed during its task: the
  task is retried, the split completes, every sequence's metrics equal the sequential ones
  (same seeds, 1 thread for SfM and torch), and the bad sequence is reported with its reason;
* the file format (kinds, Eigen lines), the Eigen frame selection, a bag read as the drive it
  was made from, and the pooled metrics.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import write_small_kitti_params

from sfm_ttr_ros.core.errors import InputError

REPO = Path(__file__).resolve().parents[1]
N_FRAMES, GT_SKIP = 8, 1
DRIVES = (1, 2, 3)
MODES = ("no_ttr", "sfm_ttr_online")
METRIC_KEYS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3", "frames",
               "refined_frames")


def drive(k: int) -> str:
    return f"2011_09_26_drive_{k:04d}_sync"


@pytest.fixture(scope="module")
def data(tmp_path_factory, tiny_plugin):
    """Drives 1-3 (each in its own root: the generator's intrinsics differ with the seed) with
    ground truth, drive 4 without; the tiny network as a plug-in; small windows."""
    from sfm_ttr_ros.data.kitti import write_kitti_drive
    from sfm_ttr_ros.data.synthetic import make_sequence

    root = tmp_path_factory.mktemp("split")
    for k in (*DRIVES, 4):
        seq = make_sequence(seed=k, domain="B", num_frames=N_FRAMES, width=320, height=96)
        write_kitti_drive(seq, root / f"d{k}" / "raw", root / f"d{k}" / "gt" if k != 4 else None,
                          drive_number=k, gt_skip_ends=GT_SKIP)
    plugin = tiny_plugin(root / "split_tiny_model.py", 64, 192)
    plugin.write_text(plugin.read_text() + PAUSING_FACTORY)
    write_small_kitti_params(REPO, root / "small.yaml")
    good = "".join(f"kitti {drive(k)} raw=d{k}/raw gt=d{k}/gt\n" for k in DRIVES)
    (root / "good.txt").write_text("# three generated drives\n" + good)
    (root / "mixed.txt").write_text(good + f"kitti {drive(4)} raw=d4/raw gt=d1/gt  # no GT\n")
    sys.path.insert(0, str(root))
    yield root
    sys.path.remove(str(root))


def split_args(root: Path, split: str, out: Path, *extra: str) -> list[str]:
    return ["benchmark", "--split", str(root / split), "--out", str(out),
            "--params-file", str(root / "small.yaml"), "--model",
            "python:split_tiny_model:factory", "--steps", "5", "--lr", "1e-3",
            "--set", "refinement.photometric_weight=5.0", "--modes", *MODES,
            "--threads", "1", "--set", "sfm.num_threads=1", "--figure-frames", "0", *extra]


def main(argv: list[str]) -> int:
    import torch

    from sfm_ttr_ros.tools.cli import main as cli_main

    threads = torch.get_num_threads()
    try:
        return cli_main(argv)
    finally:
        torch.set_num_threads(threads)


def per_sequence(out: Path) -> dict[str, dict]:
    res = json.loads((out / "results.json").read_text())
    return {q["id"]: q for q in res["sequences"]}


def frame_rows(out: Path) -> dict[tuple[str, str], dict]:
    with open(out / "per_frame.csv", newline="") as fh:
        return {(r["sequence"], r["name"]): r for r in csv.DictReader(fh)}


# ---------------------------------------------------------------------------------------------
# In process: interrupted, resumed (the sequential reference)
# ---------------------------------------------------------------------------------------------


#: Appended to the tiny model's module: in a process whose environment sets
#: :data:`PAUSE_ENV` (the interrupted subprocess only; same model spec, so the same resume key)
#: every model built after the first waits, so that the SIGINT sent once the first sequence is
#: stored lands while the split still runs, however fast the tiny sequences are.
PAUSE_ENV = "SPLIT_TEST_PAUSE_AFTER_FIRST"
PAUSING_FACTORY = f"""

import os as _os
import time as _time

if _os.environ.get({PAUSE_ENV!r}):
    _unpaused, _built = factory, []

    def factory(*args, **kwargs):
        _built.append(1)
        if len(_built) > 1:
            _time.sleep(60.0)
        return _unpaused(*args, **kwargs)
"""


@pytest.fixture(scope="module")
def sequential(data):
    """The good split in a subprocess, SIGINT as soon as its first sequence is stored (its
    later sequences wait: :data:`PAUSING_FACTORY`); then the same command again in this
    process."""
    out = data / "sequential"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(data), str(REPO)]), PAUSE_ENV: "1"}
    proc = subprocess.Popen([sys.executable, "-m", "sfm_ttr_ros",
                             *split_args(data, "good.txt", out)], cwd=data, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            # Ctrl-C's default even where this process ignores SIGINT (a child
                            # inherits SIG_IGN, and Python then raises no KeyboardInterrupt)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    first = out / "sequences" / drive(1) / "sequence.json"
    deadline = time.monotonic() + 120
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    log, _ = proc.communicate(timeout=120)
    interrupted = json.loads((out / "results.json").read_text())
    interrupted_md = (out / "results.md").read_text()
    stamps = {p.parent.name: (p.stat().st_mtime_ns, p.read_bytes())
              for p in (out / "sequences").glob("*/sequence.json")}
    assert main(split_args(data, "good.txt", out)) == 0
    resumed = json.loads((out / "results.json").read_text())
    return {"rc": proc.returncode, "log": log, "interrupted": interrupted,
            "interrupted_md": interrupted_md, "stamps": stamps,
            "resumed": resumed, "out": out}


@pytest.mark.slow
def test_interrupt_keeps_finished_sequences(sequential):
    res, log = sequential["interrupted"], sequential["log"]
    assert sequential["rc"] == 130, log[-3000:]
    assert res["interrupted"] is True
    c = res["counts"]
    assert c["sequences"] == 3 and c["done"] == 1, (c, log[-2000:])
    assert c["done"] + c["not_run"] == 3 and c["failed"] == 0
    done = [q["id"] for q in res["sequences"] if q["status"] == "done"]
    assert drive(1) in done and set(sequential["stamps"]) == set(done)
    assert "INTERRUPTED" in sequential["interrupted_md"]
    # the kept sequences' rows are in the pooled metrics and the per-frame CSV at once
    assert res["pooled"]["no_ttr"]["frames"] == c["done"] * (N_FRAMES - 2 * GT_SKIP)


@pytest.mark.slow
def test_resume_does_not_recompute_finished_sequences(sequential):
    res = sequential["resumed"]
    before = sequential["stamps"]
    c = res["counts"]
    assert c["done"] == 3 and c["failed"] == 0 and c["not_run"] == 0
    assert c["reused"] == len(before) and c["computed"] == 3 - len(before)
    out = sequential["out"]
    for sid, (mtime, content) in before.items():
        marker = out / "sequences" / sid / "sequence.json"
        assert (marker.stat().st_mtime_ns, marker.read_bytes()) == (mtime, content), sid
    rows = per_sequence(out)
    assert {sid for sid, q in rows.items() if q["reused"]} == set(before)
    assert len(frame_rows(out)) == 3 * (N_FRAMES - 2 * GT_SKIP)


@pytest.mark.slow
def test_changed_settings_or_overwrite_recompute(sequential, data):
    """A sequence is reused only under the same key: another step count is another result."""
    from sfm_ttr_ros.tools.split import cache
    from sfm_ttr_ros.tools.split.spec import read_split
    from sfm_ttr_ros.tools.split.task import SplitJob

    spec = read_split(data / "good.txt")[0]
    job = SplitJob("benchmark", {"refinement.steps": 5, "torch_num_threads": 1}, "", {})
    key = cache.sequence_key(spec, job)
    assert key == cache.sequence_key(spec, SplitJob(
        "benchmark", {"refinement.steps": 5, "torch_num_threads": 2}, "", {}, threads=2))
    assert key != cache.sequence_key(spec, SplitJob(
        "benchmark", {"refinement.steps": 6, "torch_num_threads": 1}, "", {}))
    stored = json.loads((sequential["out"] / "sequences" / spec.id / "sequence.json").read_text())
    assert cache.load_done(sequential["out"], spec, stored["key"]) is not None
    assert cache.load_done(sequential["out"], spec, key) is None


# ---------------------------------------------------------------------------------------------
# A Ray cluster of two nodes; a worker killed; a bad sequence
# ---------------------------------------------------------------------------------------------


def kill_one_task_worker(title: str, stop: threading.Event, killed: list) -> None:
    """SIGKILL the worker process while it runs the task of that process title."""
    import psutil

    def running(p) -> bool:
        try:
            return " ".join(p.cmdline()).startswith(title)
        except psutil.Error:
            return False

    while not stop.is_set() and not killed:
        for p in psutil.process_iter():
            if running(p):
                time.sleep(0.3)  # inside the task's work, not at its very start
                if not running(p):
                    continue
                p.kill()
                killed.append(p.pid)
                return
        time.sleep(0.05)


@pytest.fixture(scope="module")
def on_cluster(data):
    pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    saved = os.environ.get("PYTHONPATH")
    # the workers (started by the nodes from this environment) import the tiny plug-in
    os.environ["PYTHONPATH"] = os.pathsep.join([str(data), str(REPO)])
    cluster = Cluster(initialize_head=True,
                      head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        stop, killed = threading.Event(), []
        killer = threading.Thread(target=kill_one_task_worker, daemon=True,
                                  args=(f"ray::sequence_task:{drive(2)}", stop, killed))
        killer.start()
        out = data / "cluster"
        rc = main(split_args(data, "mixed.txt", out, "--ray-address", cluster.address,
                             "--retries", "2"))
        stop.set()
        killer.join(timeout=5)
        # a task on a CUDA device declares a GPU: this cluster has none
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            rc_gpu = main(split_args(data, "good.txt", data / "gpu", "--ray-address",
                                     cluster.address, "--device", "cuda"))
    finally:
        cluster.shutdown()
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved
    return {"rc": rc, "out": out, "killed": killed, "gpu": (rc_gpu, err.getvalue()),
            "results": json.loads((out / "results.json").read_text())}


@pytest.mark.slow
def test_cluster_matches_sequential_runs(on_cluster, sequential):
    ray_rows, seq_rows = per_sequence(on_cluster["out"]), per_sequence(sequential["out"])
    hosts = set()
    for k in DRIVES:
        a, b = ray_rows[drive(k)], seq_rows[drive(k)]
        assert a["status"] == b["status"] == "done"
        for mode in MODES:
            assert {m: a["modes"][mode][m] for m in METRIC_KEYS} == \
                   {m: b["modes"][mode][m] for m in METRIC_KEYS}, (k, mode)
        assert a["modes"]["sfm_ttr_online"]["refined_frames"] > 0
        hosts.add(a["host"])
    assert len(hosts) >= 2  # the tasks ran in several worker processes
    cluster_frames, seq_frames = frame_rows(on_cluster["out"]), frame_rows(sequential["out"])
    assert cluster_frames == seq_frames
    pooled = on_cluster["results"]["pooled"]
    assert pooled == sequential["resumed"]["pooled"]
    assert pooled["no_ttr"]["frames"] == 3 * (N_FRAMES - 2 * GT_SKIP)


@pytest.mark.slow
def test_killed_worker_is_retried_and_the_split_completes(on_cluster):
    assert len(on_cluster["killed"]) == 1, "no task worker was found to kill"
    c = on_cluster["results"]["counts"]
    assert c["retried"] == 1 and c["retries"] == 1
    assert c["done"] == 3 and c["not_run"] == 0
    rows = per_sequence(on_cluster["out"])
    assert {sid: q["attempts"] for sid, q in rows.items()} == {
        drive(1): 1, drive(2): 2, drive(3): 1, drive(4): 1}
    assert rows[drive(2)]["retries"] == 1 and rows[drive(2)]["status"] == "done"
    assert on_cluster["results"]["engine"]["where"].startswith("Ray cluster")


@pytest.mark.slow
def test_cuda_tasks_declare_a_gpu(on_cluster):
    rc, err = on_cluster["gpu"]
    assert rc == 2 and "has 0 GPUs: a task needs 1 (device cuda)" in err, err


@pytest.mark.slow
def test_bad_sequence_is_reported_with_its_reason(on_cluster):
    assert on_cluster["rc"] == 1  # a sequence failed: the command says so
    bad = per_sequence(on_cluster["out"])[drive(4)]
    assert bad["status"] == "failed"
    assert "ground truth" in bad["reason"]
    assert on_cluster["results"]["counts"]["failed"] == 1
    failed = json.loads((on_cluster["out"] / "failed" / f"{drive(4)}.json").read_text())
    assert failed["reason"] == bad["reason"]
    assert bad["reason_key"] == failed["reason_key"] == "input_error"  # the key beside the text
    assert f"{drive(4)} | failed" in (on_cluster["out"] / "results.md").read_text()


# ---------------------------------------------------------------------------------------------
# The file, the Eigen frames, bags, pooling
# ---------------------------------------------------------------------------------------------


def test_a_ray_address_where_nothing_listens_is_one_error_line(tmp_path):
    with socket.socket() as sock:  # a port nothing listens on once this socket is closed
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    split = tmp_path / "split.txt"
    split.write_text(f"kitti {drive(1)} raw=raw gt=gt\n")
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "sfm_ttr_ros.tools.cli", "benchmark", "--split", str(split),
         "--out", str(tmp_path / "out"), "--ray-address", f"127.0.0.1:{port}"],
        capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.splitlines() == [
        f"sfm-ttr: error: --ray-address 127.0.0.1:{port}: no Ray cluster answers there "
        f"(Connection refused); start its head (ray start --head --port {port}) or check the "
        "address"]
    assert time.monotonic() - t0 < 60 and not (tmp_path / "out").exists()
    bad = subprocess.run(
        [sys.executable, "-m", "sfm_ttr_ros.tools.cli", "benchmark", "--split", str(split),
         "--out", str(tmp_path / "out"), "--ray-address", "headnode"],
        capture_output=True, text=True, timeout=120, cwd=REPO)
    assert bad.returncode == 2 and "expected HOST:PORT" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_split_file_kinds_and_eigen_lines(tmp_path):
    from sfm_ttr_ros.tools.split.spec import read_split

    (tmp_path / "s.txt").write_text(
        "2011_09_26/2011_09_26_drive_0002_sync 0000000069 l\n"
        "kitti 2011_09_26_drive_0005_sync start=3 frames=20   # whole drive, from frame 3\n"
        "images room K=room/K.txt gt=room/depth gt_scale=1000 name=room1\n"
        "2011_09_26/2011_09_26_drive_0002_sync 0000000054 l\n"
        "bag bags/run1 image=/cam/image_raw\n"
        "2011_09_26/2011_09_26_drive_0002_sync 0000000042 r\n")
    specs = read_split(tmp_path / "s.txt", kitti_raw="raw", kitti_gt="gt", context=5)
    assert [s.id for s in specs] == ["2011_09_26_drive_0002_sync", "2011_09_26_drive_0005_sync",
                                     "room1", "run1", "2011_09_26_drive_0002_sync_right"]
    eigen = specs[0]
    assert eigen.kind == "kitti" and eigen.eval_frames == ("0000000069", "0000000054")
    assert eigen.camera == "02" and eigen.context == 5 and eigen.lines == (1, 4)
    assert eigen.options == {"raw": str(tmp_path / "raw"), "gt": str(tmp_path / "gt")}
    assert specs[4].camera == "03" and specs[4].eval_frames == ("0000000042",)
    assert specs[1].start == 3 and specs[1].frames == 20 and specs[1].eval_frames is None
    assert specs[2].options == {"K": str(tmp_path / "room/K.txt"),
                                "gt": str(tmp_path / "room/depth"), "gt_scale": "1000"}
    assert specs[3].path == str(tmp_path / "bags/run1")
    assert specs[3].options == {"image": "/cam/image_raw"}


@pytest.mark.parametrize("text, message", [
    ("kitti 2011_09_26_drive_0005_sync\n", "needs raw=DIR or --kitti-raw"),
    ("images room\n", "needs K=FILE"),
    ("bag b fps=3\n", "unknown option 'fps'"),
    ("images a K=k\nimages b/a K=k\n", "already used on line 1"),
    ("kitti d raw=r start=-1\n", "must be >= 0"),
    ("frames 1 2 3\n", "expected a line"),
    ("# nothing\n\n", "lists no sequence"),
    ("2011_09_26/2011_09_26_drive_0002_sync 0000000069 l\n"
     "2011_09_26/2011_09_26_drive_0002_sync 0000000069 l\n", "listed twice"),
])
def test_split_file_errors(tmp_path, text, message):
    from sfm_ttr_ros.tools.split.spec import read_split

    (tmp_path / "s.txt").write_text(text)
    raw = None if "needs raw" in message else "raw"
    with pytest.raises(InputError, match=re.escape(message)):
        read_split(tmp_path / "s.txt", kitti_raw=raw)


def test_eigen_drive_runs_around_its_listed_frames(data, tmp_path):
    from sfm_ttr_ros.tools.split.sources import open_spec
    from sfm_ttr_ros.tools.split.spec import read_split

    (tmp_path / "eigen.txt").write_text(
        f"2011_09_26/{drive(1)} 0000000004 l\n2011_09_26/{drive(1)} 0000000003 l\n"
        f"2011_09_26/{drive(1)} 0000000007 l\n")  # frame 7 has no GT (the last GT_SKIP frames)
    spec, = read_split(tmp_path / "eigen.txt", data / "d1" / "raw", data / "d1" / "gt",
                       context=1)
    opened = open_spec(spec, tmp_path / "scratch")
    assert (opened.start, opened.max_frames) == (2, 6)  # frames 2 .. 7 (8 frames in the drive)
    assert sorted(opened.seq.gt_paths) == ["0000000003", "0000000004"]
    assert opened.notes == {"listed_frames": 3, "listed_without_gt": 1}
    (tmp_path / "missing.txt").write_text(f"2011_09_26/{drive(1)} 0000000099 l\n")
    spec, = read_split(tmp_path / "missing.txt", data / "d1" / "raw", data / "d1" / "gt")
    with pytest.raises(InputError, match="0000000099 not in the drive"):
        open_spec(spec, tmp_path / "scratch2")


@pytest.mark.slow
def test_a_bag_is_the_drive_it_was_made_from(data, tmp_path):
    """A bag written from drive 1 (the node's KITTI topics) runs with the same metrics as the
    drive itself, in one in-process split with the two."""
    from sfm_ttr_ros.ros.kitti_bag import kitti_to_bag

    kitti_to_bag(data / "d1" / "raw", drive(1), tmp_path / "d1bag", data / "d1" / "gt")
    (tmp_path / "two.txt").write_text(f"kitti {drive(1)} raw={data}/d1/raw gt={data}/d1/gt\n"
                                      "bag d1bag\n")
    out = tmp_path / "out"
    argv = split_args(data, "good.txt", out)
    argv[2] = str(tmp_path / "two.txt")
    argv[argv.index("--modes") + 1:argv.index("--modes") + 3] = ["no_ttr", "sfm_ttr_offline"]
    assert main(argv) == 0
    rows = per_sequence(out)
    a, b = rows[drive(1)], rows["d1bag"]
    assert a["frames_total"] == b["frames_total"] == N_FRAMES
    for mode in ("no_ttr", "sfm_ttr_offline"):
        for m in METRIC_KEYS:
            assert b["modes"][mode][m] == pytest.approx(a["modes"][mode][m], rel=1e-5), (mode, m)


def test_run_split_writes_before_and_after(data, tmp_path):
    """``sfm-ttr run --split``: one window per sequence, before/after pooled."""
    out = tmp_path / "run"
    (tmp_path / "one.txt").write_text(f"kitti {drive(2)} raw={data}/d2/raw gt={data}/d2/gt\n")
    argv = ["run", "--split", str(tmp_path / "one.txt"), "--out", str(out), "--model",
            "python:split_tiny_model:factory", "--steps", "3", "--threads", "1",
            "--set", "sfm.max_num_features=2048", "--set", "sfm.init_min_tri_angle=1.0",
            "--set", "min_supervision_points=20"]
    assert main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["modes"] == ["no_ttr", "sfm_ttr"] and res["counts"]["done"] == 1
    seq_dir = out / "sequences" / drive(2)
    assert (seq_dir / "summary.json").is_file()
    summary = json.loads((seq_dir / "summary.json").read_text())
    row = per_sequence(out)[drive(2)]
    assert row["reason"] == summary["reason"]  # the window's outcome: the text and its key
    assert "reason_key" in row and row["reason_key"] == summary.get("reason_key")
    assert len(list((seq_dir / "after").glob("*.npy"))) == N_FRAMES
    assert res["pooled"]["no_ttr"]["frames"] == N_FRAMES - 2 * GT_SKIP
    assert len(frame_rows(out)) == N_FRAMES - 2 * GT_SKIP


def test_pooled_metrics_weigh_every_frame():
    """The pool is the mean over all frames, not the mean of the sequences' means."""
    from sfm_ttr_ros.core.evaluation import METRICS
    from sfm_ttr_ros.tools.split.split_report import pooled_metrics

    def row(frames, value):
        return {"modes": {"no_ttr": {**{m: value for m in METRICS}, "frames": frames,
                                     "refined_frames": 0, "processed_frames": frames}}}

    pooled = pooled_metrics([row(1, 0.4), row(3, 0.2), row(0, float("nan"))], ["no_ttr"])
    assert pooled["no_ttr"]["abs_rel"] == pytest.approx((0.4 + 3 * 0.2) / 4)
    assert pooled["no_ttr"]["frames"] == 4 and pooled["no_ttr"]["sequences"] == 2


class _Terminal:
    """A stream that says it is a terminal (what tqdm draws on)."""

    def __init__(self) -> None:
        self.text = ""

    def write(self, s: str) -> int:
        self.text += s
        return len(s)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return True


def test_progress_bar_on_a_terminal_lines_otherwise():
    from sfm_ttr_ros.tools.split.progress import SplitProgress

    done = {"id": "a", "status": "done", "seconds": 2.0, "attempts": 2,
            "row": {"frames_total": 30}}
    failed = {"id": "b", "status": "failed", "reason": "no ground truth", "seconds": 0.1,
              "row": {}}
    log = io.StringIO()
    p = SplitProgress(3, reused=1, stream=log, label="benchmark")
    p.update(done)
    p.update(failed)
    p.close()
    lines = log.getvalue().splitlines()
    assert lines[0] == "sfm-ttr benchmark: 1 of 3 sequences already done (resumed)"
    assert lines[1].startswith("sfm-ttr benchmark: [2/3] a: done in 2.0 s, 30 frames, 1 retry;")
    assert "ETA" in lines[1] and "30 frames so far, 0 failed" in lines[1]
    assert "[3/3] b: FAILED (no ground truth)" in lines[2] and "ETA" not in lines[2]
    term = _Terminal()
    p = SplitProgress(3, reused=1, stream=term)
    p.update(done)
    p.update(failed)
    p.close()
    assert "3/3" in term.text and "frames=30" in term.text and "failed=1" in term.text
    assert "b: failed: no ground truth" in term.text


def test_bag_default_topics():
    """The node's own topics first, else KITTI's, else the only colour image topic; the
    CameraInfo and the ground truth beside the image."""
    from sfm_ttr_ros.ros.bag import BagTopic
    from sfm_ttr_ros.ros.bag_sequence import default_topics

    def bag(**topics):
        return {t: BagTopic(t, kind, 1) for t, kind in topics.items()}

    img, info, cmp = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo",
                      "sensor_msgs/msg/CompressedImage")
    node = bag(**{"/image": img, "/camera_info": info, "/kitti/camera_color_left/image_raw": img,
                  "/kitti/camera_color_left/camera_info": info})
    assert default_topics(node) == ("/image", "/camera_info", None)
    kitti = bag(**{"/kitti/camera_color_left/image_raw/compressed": cmp,
                   "/kitti/camera_color_left/camera_info": info,
                   "/kitti/camera_color_left/depth_gt": img})
    assert default_topics(kitti) == ("/kitti/camera_color_left/image_raw/compressed",
                                     "/kitti/camera_color_left/camera_info",
                                     "/kitti/camera_color_left/depth_gt")
    other = bag(**{"/cam/rgb": img, "/cam/camera_info": info, "/cam/depth": img})
    assert default_topics(other) == ("/cam/rgb", "/cam/camera_info", None)
    with pytest.raises(InputError, match="cannot tell the image topic"):
        default_topics(bag(**{"/a/rgb": img, "/b/rgb": img}))
    with pytest.raises(InputError, match="no CameraInfo topic /cam/camera_info"):
        default_topics(bag(**{"/cam/rgb": img}))
    with pytest.raises(InputError, match="not in the bag"):
        default_topics(other, gt="/cam/gt")
