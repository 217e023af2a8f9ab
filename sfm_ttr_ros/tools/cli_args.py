"""Arguments shared by ``sfm-ttr run`` and ``sfm-ttr benchmark``: the sequence, and the
parameters of the one schema (:mod:`sfm_ttr_ros.core.params`) as ``--params-file FILE``,
repeated ``--set name=value`` and a few short flags, each ONE row of :data:`PARAM_FLAGS`.

Precedence, lowest first: the schema's defaults < the parameter file < the flags <
``--set``. A flag's type and choices come from its parameter; its argparse default is None
(= not given)."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core import params as schema
from sfm_ttr_ros.core.errors import InputError

#: flag → (parameter, group). Groups: ``model``, ``method`` (both commands), ``windows``
#: (``benchmark`` only: ``run`` is one window over the whole sequence).
PARAM_FLAGS: dict[str, tuple[str, str]] = {
    "--model": ("model_type", "model"),
    "--encoder": ("encoder_path", "model"),
    "--decoder": ("decoder_path", "model"),
    "--model-path": ("model_path", "model"),
    "--device": ("device", "model"),
    "--threads": ("torch_num_threads", "model"),
    "--steps": ("refinement.steps", "method"),
    "--lr": ("refinement.lr", "method"),
    "--weighting": ("refinement.weighting", "method"),
    "--tau": ("alignment.tau", "method"),
    "--sfm-max-image-size": ("sfm.max_image_size", "method"),
    "--seed": ("seed", "method"),
    "--window-size": ("window_size", "windows"),
    "--window-stride": ("window_stride", "windows"),
    "--policy": ("weight_policy", "windows"),
}
GROUP_TITLES = {"model": "model", "method": "SfM-TTR method", "windows": "online windows"}


def parse_bool(text: str) -> bool:
    t = str(text).strip().lower()
    if t in ("true", "1", "yes", "on"):
        return True
    if t in ("false", "0", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _dest(flag: str) -> str:
    return flag.lstrip("-").replace("-", "_")


def add_parameter_args(p: argparse.ArgumentParser, groups: tuple[str, ...],
                       default_file: str) -> None:
    """``--params-file``, ``--set`` and the :data:`PARAM_FLAGS` of ``groups`` on ``p``;
    ``default_file`` says in the help what is used without ``--params-file``."""
    g = p.add_argument_group("parameters (`sfm-ttr params` lists them)")
    g.add_argument("--params-file", default="", metavar="FILE",
                   help=f"a ROS 2 parameter file of the refiner node (default: {default_file})")
    g.add_argument("--set", dest="set", action="append", default=[], metavar="NAME=VALUE",
                   help="set one parameter (repeatable; over the file and the flags), e.g. "
                        "--set refinement.steps=50")
    for group in groups:
        g = p.add_argument_group(f"{GROUP_TITLES[group]} (short for --set)")
        for flag, (name, in_group) in PARAM_FLAGS.items():
            if in_group != group:
                continue
            param = schema.SCHEMA[name]
            kind = parse_bool if param.type is bool else param.type
            g.add_argument(flag, dest=_dest(flag), type=kind, default=None,
                           choices=list(param.choices) or None,
                           metavar="{true,false}" if param.type is bool else None,
                           help=f"{param.description} [= --set {name}=V; default: the "
                                f"file's, else {param.default!r}]".replace("%", "%%"))


def parameter_values(args: argparse.Namespace, default_file: Path | None = None,
                     overrides: list[str] | None = None) -> tuple[Path | None, dict[str, Any]]:
    """(the parameter file read, or None; the values): the file's (``--params-file``, else
    ``default_file``), then the flags given, then ``overrides`` (default: ``--set``). A
    ``--model`` flag drops the file's encoder, decoder and model paths and output kind (they
    belong to its model). The commands' one way of reading parameters (the file through
:func:`sfm_ttr_ros.tools.benchmark.settings.read_params_file`, the reader the demo and the
benchmark's defaults use too)."""
    path = Path(args.params_file) if args.params_file else default_file
    values: dict[str, Any] = {}
    if path is not None:
        from sfm_ttr_ros.tools.benchmark.settings import read_params_file

        values.update(read_params_file(path))
    if getattr(args, "model", None) is not None:
        values["encoder_path"], values["decoder_path"] = "", ""
        values["model_path"], values["output_kind"] = "", ""
    for flag, (name, _) in PARAM_FLAGS.items():
        v = getattr(args, _dest(flag), None)
        if v is not None:
            values[name] = v
    values.update(schema.parse_overrides(args.set or [] if overrides is None else overrides))
    return path, values


def build_model_for(settings: schema.Settings):
    """The network of ``settings`` with torch's threads and the start-up weights applied, as
    the node does at start-up."""
    import torch

    from sfm_ttr_ros.core.models import build_model
    from sfm_ttr_ros.ros.encoder_file import load_encoder

    if settings.node.torch_num_threads > 0:
        torch.set_num_threads(settings.node.torch_num_threads)
    model = build_model(settings.model)
    path = settings.node.load_weights_path
    if path:  # these become the "original" weights, read as the node reads them
        load_encoder(model, path)
    return model


def add_sequence_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("sequence (a KITTI raw drive, or an image folder + K)")
    g.add_argument("--kitti-raw", help="KITTI raw root (holds <date>/<drive>/image_02)")
    g.add_argument("--drive", help="<date>_drive_XXXX_sync")
    g.add_argument("--kitti-gt", help="KITTI depth GT root (holds {train,val}/<drive>/...)")
    g.add_argument("--images", help="folder of images (any other sequence)")
    g.add_argument("--intrinsics", help="K file for --images: 3x3 or fx fy cx cy")
    g.add_argument("--gt-depth", help="GT depth PNG folder for --images (depth x gt-scale)")
    g.add_argument("--gt-scale", type=float, default=256.0)
    g.add_argument("--start", type=int, default=0, help="first frame index")
    g.add_argument("--max-frames", type=int, default=0, help="0 = all")


def open_sequence(args: argparse.Namespace):
    from sfm_ttr_ros.data.sequence import open_image_folder, open_kitti

    if args.kitti_raw:
        if not args.drive:
            raise InputError("--kitti-raw needs --drive <date>_drive_XXXX_sync")
        return open_kitti(args.kitti_raw, args.drive, args.kitti_gt)
    if args.images:
        if not args.intrinsics:
            raise InputError("--images needs --intrinsics K.txt")
        return open_image_folder(args.images, args.intrinsics, args.gt_depth, args.gt_scale)
    raise InputError("give a sequence: --kitti-raw RAW --drive D, or --images DIR --intrinsics K")


def command_line() -> str:
    """The command line as typed (recorded in the results)."""
    prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "sfm-ttr"
    if prog in ("__main__.py", "-m", "-c"):
        prog = "python -m sfm_ttr_ros"
    return shlex.join([prog, *sys.argv[1:]])
