"""Bad input gets a clear InputError from the library and a one-line error (exit code 2) from the
CLI — never a traceback from deep inside pycolmap, OpenCV or torch (DEVELOPERS.md, "Rules").

Every case fails before any heavy work (no SfM, no network), so the whole file runs in seconds.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import load_frames, reconstruct_window

from sfm_ttr_ros.core.errors import InputError
from sfm_ttr_ros.core.frames import (
    Frame,
    Intrinsics,
    check_window,
    list_images,
    load_rgb,
)
from sfm_ttr_ros.core.sfm.reconstruction import SfmReconstructor
from sfm_ttr_ros.data.sequence import open_image_folder
from sfm_ttr_ros.tools.cli import main

W, H = 128, 96
INTR = Intrinsics(100.0, 100.0, 63.5, 47.5, W, H)


def image(seed: int = 0, size=(W, H)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (size[1], size[0], 3), np.uint8)


def write_folder(root: Path, n: int = 3, size=(W, H)) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(root / f"{i:04d}.png"), image(i, size))
    return root


def truncate(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


class NeverCalled:
    """Stands in for the SfM reconstructor / network: bad input must be rejected before them."""

    def __getattr__(self, name):
        raise AssertionError(f"heavy work ({name}) started on bad input")


# ------------------------------------------------------------------------------ library
def test_input_error_is_a_value_error():
    assert issubclass(InputError, ValueError)


@pytest.mark.parametrize("window", [[], ()])
def test_empty_window(window):
    with pytest.raises(InputError, match="empty window"):
        check_window(window, INTR)
    with pytest.raises(InputError, match="empty window"):
        reconstruct_window(window, INTR)


def test_frames_of_differing_sizes():
    frames = [Frame(0, image(0)), Frame(1, image(1, (W + 8, H)))]
    with pytest.raises(InputError, match=r"frame 0000000001 is 136x96 .* one size"):
        reconstruct_window(frames, INTR)


def test_intrinsics_for_another_image_size():
    frames = [Frame(i, image(i)) for i in range(2)]
    big = Intrinsics(200.0, 200.0, 127.5, 95.5, 2 * W, 2 * H)
    with pytest.raises(InputError, match=r"128x96 but the intrinsics are for 256x192"):
        reconstruct_window(frames, big)
    # A K meant for a bigger image puts the principal point outside this one (KITTI's K on a
    # 128 x 96 image here): caught where the intrinsics are made, before any frame is seen.
    with pytest.raises(InputError, match=r"principal point .* another image size"):
        Intrinsics.from_K(np.array([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]]), W, H)


@pytest.mark.parametrize(
    ("values", "match"),
    [
        ((math.nan, 100.0, 63.5, 47.5, W, H), "finite"),
        ((100.0, math.inf, 63.5, 47.5, W, H), "finite"),
        ((100.0, 100.0, math.nan, 47.5, W, H), "finite"),
        ((0.0, 100.0, 63.5, 47.5, W, H), "focal lengths must be positive"),
        ((100.0, -5.0, 63.5, 47.5, W, H), "focal lengths must be positive"),
        ((100.0, 100.0, 63.5, 47.5, 0, H), "image size"),
        ((100.0, 100.0, 63.5, 47.5, W, -96), "image size"),
        ((100.0, 100.0, 63.5, 47.5, math.nan, H), "image size"),
        ((100.0, 100.0, 63.5, 47.5, math.inf, H), "image size"),
        ((100.0, 100.0, 63.5, 47.5, 128.5, H), "whole numbers"),
        ((None, 100.0, 63.5, 47.5, W, H), "must be numbers"),
        (("f", 100.0, 63.5, 47.5, W, H), "must be numbers"),
        ((100.0, 100.0, -3.0, 47.5, W, H), "principal point"),
        ((100.0, 100.0, 63.5, 200.0, W, H), "principal point"),
    ],
)
def test_bad_intrinsics(values, match):
    with pytest.raises(InputError, match=match):
        Intrinsics(*values)


def test_intrinsics_normalised_and_non_finite_K():
    intr = Intrinsics(np.float32(100), 100, 63.5, 47.5, np.int64(W), float(H))
    assert type(intr.fx) is float and type(intr.width) is int and type(intr.height) is int
    assert intr == INTR
    with pytest.raises(InputError, match="finite"):
        Intrinsics.from_K(np.full((3, 3), np.nan), W, H)
    with pytest.raises(InputError, match="3x3"):
        Intrinsics.from_K(np.eye(2), W, H)


def test_bad_window_items_and_intrinsics_type():
    frames = [Frame(i, image(i)) for i in range(2)]
    with pytest.raises(InputError, match="must be an Intrinsics, got NoneType"):
        check_window(frames, None)
    with pytest.raises(InputError, match="sequence .* got generator"):
        check_window((f for f in frames), INTR)
    with pytest.raises(InputError, match="item 1 is a ndarray, not a Frame"):
        check_window([frames[0], image(1)], INTR)
    with pytest.raises(InputError, match="unique"):
        check_window([frames[0], Frame(5, image(5), name=frames[0].name)], INTR)
    bad_images = [
        (image(0).astype(np.float32), "expected uint8"),
        (np.zeros((H, W, 4), np.uint8), "H x W x 3"),
        (np.zeros((0, W, 3), np.uint8), "zero-size"),
        (image(0).tolist(), "numpy array"),
    ]
    for img, match in bad_images:
        with pytest.raises(InputError, match=match):
            check_window([Frame(0, img), frames[1]], INTR)


def test_grayscale_frames_are_expanded_for_every_later_stage():
    # Used to pass the check and then crash deep in the SfM stage (colour lookup of the points).
    gray = image(0)[:, :, 0].copy()
    frames = [Frame(0, gray), Frame(1, image(1))]
    check_window(frames, INTR)
    assert frames[0].image.shape == (H, W, 3) and frames[0].image.dtype == np.uint8
    np.testing.assert_array_equal(frames[0].image[:, :, 2], gray)


def test_bad_window_rejected_before_sfm_or_network():
    import torch
    from torch import nn

    from sfm_ttr_ros.core.models.base import EncoderDecoder
    from sfm_ttr_ros.core.pipeline import SfmTTR, TTRConfig
    from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig

    torch.manual_seed(0)
    model = EncoderDecoder(nn.Conv2d(3, 4, 3, padding=1),
                           nn.Sequential(nn.Conv2d(4, 1, 3, padding=1), nn.Sigmoid()), (32, 32))
    ttr = SfmTTR(model, TTRConfig(sfm=SfmConfig(mode="batch")))  # the batch mapper: spied on
    real = ttr.sfm.reconstructor
    ttr.sfm.reconstructor = NeverCalled()
    ttr.predictor.predict = _never  # the network must not run either
    try:
        with pytest.raises(InputError, match="empty window"):
            ttr.process_window([], INTR)
        with pytest.raises(InputError, match="one size"):
            ttr.process_window([Frame(0, image(0)), Frame(1, image(1, (W, H + 2)))], INTR)
        with pytest.raises(InputError, match="for 256x192"):
            ttr.process_window([Frame(0, image(0)), Frame(1, image(1))],
                               Intrinsics(200.0, 200.0, 127.5, 95.5, 2 * W, 2 * H))
        with pytest.raises(InputError, match="uint8"):
            ttr.process_window([Frame(0, image(0).astype(float)), Frame(1, image(1))], INTR)
    finally:
        ttr.sfm.reconstructor = real
        ttr.close()
    with SfmReconstructor() as rec:
        with pytest.raises(InputError, match="one size"):
            rec.reconstruct([Frame(0, image(0)), Frame(1, image(1, (W, H + 2)))], INTR)
        assert not rec.workspace.database_path.exists()  # rejected before pycolmap saw anything


def _never(*args, **kwargs):
    raise AssertionError("the network ran on bad input")


def test_unreadable_and_corrupt_image_files(tmp_path):
    folder = write_folder(tmp_path / "imgs", 2)
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"this is not an image")
    cv2.imwrite(str(tmp_path / "cut.png"), image(3))
    cv2.imwrite(str(tmp_path / "cut.jpg"), image(4))
    cases = {
        tmp_path / "missing.png": "image file not found",
        tmp_path: "image file not found",  # a folder, not a file
        garbage: "cannot decode image file",
        truncate(tmp_path / "cut.png"): "truncated PNG",
        # OpenCV decodes a truncated JPEG without an error (the rest grey): caught explicitly.
        truncate(tmp_path / "cut.jpg"): "truncated JPEG",
    }
    for path, match in cases.items():
        with pytest.raises(InputError, match=match):
            load_rgb(path)
    with pytest.raises(InputError, match="cannot decode"):
        load_frames([folder / "0000.png", garbage])
    assert load_rgb(folder / "0000.png").shape == (H, W, 3)  # whole files still load


def test_missing_or_empty_folders(tmp_path):
    K = tmp_path / "K.txt"
    K.write_text("100 0 63.5\n0 100 47.5\n0 0 1\n")
    with pytest.raises(InputError, match="image folder not found"):
        list_images(tmp_path / "nope")
    with pytest.raises(InputError, match="image folder not found"):
        open_image_folder(tmp_path / "nope", K)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images"):
        open_image_folder(tmp_path / "empty", K)
    good = write_folder(tmp_path / "good")
    with pytest.raises(InputError, match="GT depth folder not found"):
        open_image_folder(good, K, gt_depth=tmp_path / "no_gt")
    with pytest.raises(InputError, match="cannot read intrinsics"):
        open_image_folder(good, tmp_path / "no_K.txt")


def test_image_folder_with_a_corrupt_or_odd_sized_later_frame(tmp_path):
    K = tmp_path / "K.txt"
    K.write_text("100 100 63.5 47.5\n")
    folder = write_folder(tmp_path / "imgs", 3)
    seq = open_image_folder(folder, K)
    assert len(seq) == 3 and seq.intrinsics == INTR
    truncate(folder / "0001.png")
    with pytest.raises(InputError, match="0001.png: truncated PNG"):
        seq.frames()
    cv2.imwrite(str(folder / "0001.png"), image(1, (W + 8, H)))
    with pytest.raises(InputError, match="0001.png is 136x96, the sequence's intrinsics are for"):
        seq.frames()


# ---------------------------------------------------------------------------------- CLI
@pytest.fixture
def cli_data(tmp_path) -> dict[str, Path]:
    d = {"good": write_folder(tmp_path / "good"), "root": tmp_path}
    d["empty"] = tmp_path / "empty"
    d["empty"].mkdir()
    d["garbage"] = write_folder(tmp_path / "garbage")
    (d["garbage"] / "0000.png").write_bytes(b"not a png")
    d["cut"] = write_folder(tmp_path / "cut")
    truncate(d["cut"] / "0002.png")
    d["mixed"] = write_folder(tmp_path / "mixed")
    cv2.imwrite(str(d["mixed"] / "0001.png"), image(1, (W + 8, H)))
    for name, text in {
        "K": "100 0 63.5\n0 100 47.5\n0 0 1\n",
        "K_nan": "nan 0 63.5\n0 100 47.5\n0 0 1\n",
        "K_neg": "-100 0 63.5\n0 100 47.5\n0 0 1\n",
        "K_text": "focal length is 100\n",
        "K_five": "100 100 63.5 47.5 1\n",
        "K_kitti": "721.5 0 609.6\n0 721.5 172.9\n0 0 1\n",  # for 1242 x 375, not 128 x 96
    }.items():
        d[name] = tmp_path / f"{name}.txt"
        d[name].write_text(text)
    d["a_file"] = tmp_path / "a_file"
    d["a_file"].write_text("x")
    return d


CLI_CASES = {
    "missing folder": (["--images", "{root}/nope", "--intrinsics", "{K}"],
                       "image folder not found"),
    "empty folder": (["--images", "{empty}", "--intrinsics", "{K}"], "no images"),
    "garbage image": (["--images", "{garbage}", "--intrinsics", "{K}"],
                      "cannot decode image file"),
    "truncated later image": (["--images", "{cut}", "--intrinsics", "{K}"], "truncated PNG"),
    "differing sizes": (["--images", "{mixed}", "--intrinsics", "{K}"],
                        "0001.png is 136x96, the sequence's intrinsics are for 128x96"),
    "non-finite K": (["--images", "{good}", "--intrinsics", "{K_nan}"], "must be finite"),
    "negative focal": (["--images", "{good}", "--intrinsics", "{K_neg}"],
                       "focal lengths must be positive"),
    "unparsable K": (["--images", "{good}", "--intrinsics", "{K_text}"],
                     "cannot read intrinsics"),
    "wrong count K": (["--images", "{good}", "--intrinsics", "{K_five}"],
                      "expected 9 numbers"),
    "missing K": (["--images", "{good}", "--intrinsics", "{root}/none.txt"],
                  "cannot read intrinsics"),
    "K of another size": (["--images", "{good}", "--intrinsics", "{K_kitti}"],
                          "another image size"),
    "images without K": (["--images", "{good}"], "--images needs --intrinsics"),
    "no sequence": ([], "give a sequence"),
    "missing KITTI drive": (["--kitti-raw", "{root}/raw", "--drive",
                             "2011_09_26_drive_0001_sync"], "KITTI drive folder not found"),
    "bad KITTI drive name": (["--kitti-raw", "{root}", "--drive", "drive1"],
                             "bad KITTI drive name"),
    "start past the end": (["--images", "{good}", "--intrinsics", "{K}", "--start", "3"],
                           r"--start 3 is outside the sequence's 3 frames"),
    "negative steps": (["--images", "{good}", "--intrinsics", "{K}", "--steps", "-1"],
                       "steps must be >= 0"),
    "zero tau": (["--images", "{good}", "--intrinsics", "{K}", "--tau", "0"], "tau"),
    "unwritable output": (["--images", "{good}", "--intrinsics", "{K}", "--out",
                           "{a_file}/out"], "cannot create the output folder"),
}


@pytest.mark.parametrize("case", list(CLI_CASES))
def test_cli_bad_input_exits_2_with_one_line(case, cli_data, capfd):
    args, match = CLI_CASES[case]
    argv = ["run", *(a.format(**cli_data) for a in args), "--model", "mobilenet"]
    if "--out" not in argv:
        argv += ["--out", str(cli_data["root"] / "out")]
    rc = main(argv)
    out, err = capfd.readouterr()  # file-descriptor level: C libraries' messages count too
    assert rc == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("sfm-ttr: error: ") and "Traceback" not in err
    assert re.search(match, lines[0]), lines[0]


def test_fallback_principal_point_outside_the_frame_gives_intrinsics_for_another_size():
    from sfm_ttr_ros.ros.camera import FallbackIntrinsics, IntrinsicsResolver

    kitti = FallbackIntrinsics(721.5377, 721.5377, 609.5593, 172.854)
    assert kitti.for_size(1242, 375) == Intrinsics(721.5377, 721.5377, 609.5593, 172.854,
                                                   1242, 375)
    for size in ((416, 128), (100, 50), (1242, 100), (300, 375)):
        intr = kitti.for_size(*size)  # never raises: the stream sees intrinsics_mismatch
        assert (intr.width, intr.height) != size
        assert intr.width >= size[0] and intr.height >= size[1]
        assert (intr.cx, intr.cy) == (609.5593, 172.854)
    assert FallbackIntrinsics(100.0, 100.0, 5000.0, 0.0).for_size(64, 48).width == 5001
    resolver = IntrinsicsResolver(lambda: kitti)
    ready = resolver.add_frame(Frame(0, np.zeros((50, 100, 3), np.uint8), 1.0), None).ready
    assert len(ready) == 1 and ready[0][1].width != 100
    # a fallback that cannot make intrinsics at all holds the frame instead of raising

    def broken():
        raise InputError("fallback unreadable")

    held = IntrinsicsResolver(broken)
    assert held.add_frame(Frame(1, np.zeros((50, 100, 3), np.uint8), 2.0), None).ready == []
    assert held.held == 1


def test_no_parameter_reaches_a_pycolmap_option_that_ends_the_process():
    import dataclasses

    from sfm_ttr_ros.core import params
    from sfm_ttr_ros.core.sfm import reconstruction as sfm

    # measured with pycolmap 4.2.1: max_image_size 1 segfaults SIFT extraction; an initial
    # triangulation angle of 0 fails the mapper's options check in every window
    assert "or >= 16" in params.validate({"sfm.max_image_size": 1})
    assert params.validate({"sfm.max_image_size": 0}) == ""
    assert params.validate({"sfm.max_image_size": 16}) == ""
    assert "init_min_tri_angle" in params.validate({"sfm.init_min_tri_angle": 0.0})
    with pytest.raises(InputError, match="max_image_size"):
        sfm.SfmConfig(max_image_size=8)
    # loop detection (aborts offline: no vocabulary tree) is not an option of ours at all
    fields = {f.name for f in dataclasses.fields(sfm.SfmConfig)}
    assert not any("loop" in name or "vocab" in name for name in fields)
    assert not any("loop" in t or "vocab" in t for p in params.PARAMS for t in p.targets)
    from sfm_ttr_ros.core.sfm import extraction

    source = Path(extraction.__file__).read_text()
    assert "pairing.loop_detection = False" in source
