"""Depth networks for SfM-TTR: the encoder/decoder interface, Monodepth2 (published weights
load unchanged), a compact MobileNetV2 network, and :func:`build_model` from a config."""

from sfm_ttr_ros.core.models.base import (
    MAX_DEPTH,
    MIN_DEPTH,
    DepthModel,
    EncoderDecoder,
    ModelLoadError,
    disp_to_depth,
)
from sfm_ttr_ros.core.models.depth_decoder import DepthDecoder
from sfm_ttr_ros.core.models.mobilenet import (
    MobileDepthNet,
    MobileNetV2Encoder,
    load_imagenet_mobilenet_v2,
    load_mobile_depth_net,
)
from sfm_ttr_ros.core.models.monodepth2 import Monodepth2, load_monodepth2, save_monodepth2
from sfm_ttr_ros.core.models.registry import ModelConfig, build_model, load_model_files
from sfm_ttr_ros.core.models.resnet import ResnetEncoder

__all__ = [
    "MAX_DEPTH",
    "MIN_DEPTH",
    "DepthDecoder",
    "DepthModel",
    "EncoderDecoder",
    "MobileDepthNet",
    "MobileNetV2Encoder",
    "ModelConfig",
    "ModelLoadError",
    "Monodepth2",
    "ResnetEncoder",
    "build_model",
    "disp_to_depth",
    "load_imagenet_mobilenet_v2",
    "load_model_files",
    "load_mobile_depth_net",
    "load_monodepth2",
    "save_monodepth2",
]
