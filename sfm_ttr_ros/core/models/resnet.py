"""Monodepth2's ResNet encoder, written out in torchvision's exact module layout.

torchvision is not a dependency, so the ResNet is defined here with the same attribute names
(``conv1``, ``bn1``, ``relu``, ``maxpool``, ``layer1`` … ``layer4``, ``fc``; blocks with
``conv1``/``bn1``/…/``downsample.{0,1}``) so that Monodepth2's published ``encoder.pth`` files
(keys ``encoder.conv1.weight`` …) and torchvision ImageNet state dicts load unchanged.
Bottleneck blocks carry the stride on their 3×3 convolution, as torchvision always has.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from sfm_ttr_ros.core.models.base import ModelLoadError

# blocks per stage, block type
RESNET_SPECS: dict[int, tuple[list[int], str]] = {
    18: ([2, 2, 2, 2], "basic"),
    34: ([3, 4, 6, 3], "basic"),
    50: ([3, 4, 6, 3], "bottleneck"),
    101: ([3, 4, 23, 3], "bottleneck"),
    152: ([3, 8, 36, 3], "bottleneck"),
}


def _conv3x3(in_planes: int, out_planes: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_planes, out_planes, kernel_size=3, stride=stride, padding=1, bias=False)


def _conv1x1(in_planes: int, out_planes: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_planes, out_planes, kernel_size=1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, inplanes: int, planes: int, stride: int = 1,
                 downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = _conv3x3(inplanes, planes, stride)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv3x3(planes, planes)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample
        self.stride = stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int = 1,
                 downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = _conv1x1(inplanes, planes)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = _conv3x3(planes, planes, stride)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = _conv1x1(planes, planes * self.expansion)
        self.bn3 = nn.BatchNorm2d(planes * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample
        self.stride = stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


class ResNet(nn.Module):
    """torchvision's ``ResNet`` (same module names, same initialisation)."""

    def __init__(self, num_layers: int = 18, num_classes: int = 1000):
        super().__init__()
        if num_layers not in RESNET_SPECS:
            raise ModelLoadError(f"unsupported ResNet depth {num_layers!r}; "
                                 f"choose one of {sorted(RESNET_SPECS)}")
        blocks, kind = RESNET_SPECS[num_layers]
        block = BasicBlock if kind == "basic" else Bottleneck
        self.inplanes = 64
        self.conv1 = nn.Conv2d(3, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(block, 64, blocks[0])
        self.layer2 = self._make_layer(block, 128, blocks[1], stride=2)
        self.layer3 = self._make_layer(block, 256, blocks[2], stride=2)
        self.layer4 = self._make_layer(block, 512, blocks[3], stride=2)
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.fc = nn.Linear(512 * block.expansion, num_classes)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.constant_(m.weight, 1)
                nn.init.constant_(m.bias, 0)

    def _make_layer(self, block, planes: int, n: int, stride: int = 1) -> nn.Sequential:
        downsample = None
        if stride != 1 or self.inplanes != planes * block.expansion:
            downsample = nn.Sequential(_conv1x1(self.inplanes, planes * block.expansion, stride),
                                       nn.BatchNorm2d(planes * block.expansion))
        layers = [block(self.inplanes, planes, stride, downsample)]
        self.inplanes = planes * block.expansion
        layers += [block(self.inplanes, planes) for _ in range(1, n)]
        return nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # ImageNet classifier, unused here
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return self.fc(torch.flatten(self.avgpool(x), 1))


class ResnetEncoder(nn.Module):
    """Monodepth2's ``ResnetEncoder``: input in [0, 1], normalised internally with
    ``(x − 0.45) / 0.225``; returns 5 feature maps at 1/2, 1/4, 1/8, 1/16 and 1/32 of the input
    with ``num_ch_enc`` channels ([64, 64, 128, 256, 512], ×4 for the last four with
    bottleneck blocks).

    ``pretrained``: ``False`` (random init) or the path of a torchvision ImageNet ResNet state dict
    (keys ``conv1.weight`` …) to start training from. Nothing is ever downloaded, so ``True`` is
    an error.
    """

    def __init__(self, num_layers: int = 18, pretrained: bool | str | Path = False):
        super().__init__()
        self.num_layers = int(num_layers)
        self.encoder = ResNet(self.num_layers)
        self.num_ch_enc = [64, 64, 128, 256, 512]
        if RESNET_SPECS[self.num_layers][1] == "bottleneck":
            self.num_ch_enc = [64] + [c * 4 for c in self.num_ch_enc[1:]]
        if pretrained is True:
            raise ModelLoadError("ResnetEncoder(pretrained=True): nothing is downloaded at run "
                                 "time; pass the path of a torchvision ImageNet state dict")
        if pretrained:
            load_torchvision_resnet(self, pretrained)

    num_stages = 5  # stem, layer1 (after the max-pool), layer2, layer3, layer4: one tap each
    level_stages = (1, 2, 3, 4, 5)  # stages run to produce each of the 5 feature maps

    def stage_modules(self, index: int) -> list[nn.Module]:
        e = self.encoder
        return [[e.conv1, e.bn1], [e.layer1], [e.layer2], [e.layer3], [e.layer4]][index]

    def forward_stages(self, x: torch.Tensor, start: int, stop: int,
                       features: list[torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Run stages ``start`` … ``stop − 1`` (see :attr:`num_stages`) on ``x`` (the [0, 1]
        image when ``start`` is 0), appending each stage's output to a copy of ``features``
        (the staged-encoder protocol of :mod:`sfm_ttr_ros.core.refinement.encoder`)."""
        e = self.encoder
        out = list(features)
        for i in range(start, stop):
            if i == 0:
                x = e.relu(e.bn1(e.conv1((x - 0.45) / 0.225)))
            elif i == 1:
                x = e.layer1(e.maxpool(x))
            else:
                x = (e.layer2, e.layer3, e.layer4)[i - 2](x)
            out.append(x)
        return x, out

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.forward_stages(x, 0, self.num_stages, [])[1]


def load_torchvision_resnet(encoder: ResnetEncoder, path: str | Path) -> None:
    """Load a torchvision ImageNet ResNet state dict file into ``encoder.encoder``."""
    path = Path(path)
    if not path.is_file():
        raise ModelLoadError(f"ImageNet ResNet weights not found: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupted / not a torch file
        raise ModelLoadError(f"cannot read ImageNet ResNet weights {path}: {exc}") from exc
    if not isinstance(state, dict):
        raise ModelLoadError(f"{path} does not hold a state dict (got {type(state).__name__})")
    own = encoder.encoder.state_dict()
    missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
    bad = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or bad:
        raise ModelLoadError(
            f"{path} is not a ResNet-{encoder.num_layers} torchvision state dict: "
            f"missing {missing[:5]}, shape mismatch {bad[:5]}")
    encoder.encoder.load_state_dict({k: v for k, v in state.items() if k in own}, strict=False)
