"""ResNet-18 (He et al. 2016) as a frozen feature extractor, for Merola et al.'s ``obs=frames_resnet``.

Merola et al. feed ImageNet-trained ResNet-18 features of RGB frames to their Double DQN. ImageNet weights cannot be
downloaded on the machines this project targets, and torchvision is not a dependency, so this module defines the
network itself with torchvision's parameter names: a user who has ``resnet18-f37072fd.pth`` (torchvision's
ImageNet checkpoint) or any state dict with those names gives its path as ``agent.merola.resnet_weights``, and
``load_resnet18`` refuses clearly when none is given, rather than extracting features with random weights.

Our camera gives class maps, not RGB: they are coloured with the CARLA palette (``envs.camera.colorize``) and
normalised with ImageNet's statistics before the network sees them. At 64×64 the last stage's map is 2×2×512.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + (x if self.downsample is None else self.downsample(x)))


class ResNet18Features(nn.Module):
    """ResNet-18 up to its last convolutional stage: ``(B, 3, H, W)`` normalised RGB -> ``(B, 512, H/32, W/32)``."""

    def __init__(self):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        widths = (64, 128, 256, 512)
        cin = 64
        for k, w in enumerate(widths, start=1):
            stride = 1 if k == 1 else 2
            setattr(self, f"layer{k}", nn.Sequential(BasicBlock(cin, w, stride), BasicBlock(w, w)))
            cin = w

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))


def load_resnet18(path: str | None) -> ResNet18Features:
    """The feature extractor with the weights in ``path`` (torchvision's names; the classifier ``fc.*`` is
    ignored), frozen and in eval mode. Refuses a missing ``path``: features of random weights are not ImageNet's."""
    from ..common import StageError

    if not path:
        raise StageError(
            "obs=frames_resnet needs ImageNet ResNet-18 weights, and they cannot be downloaded here: give a local "
            "file with agent.merola.resnet_weights=/path/to/resnet18-f37072fd.pth (torchvision's checkpoint), or use "
            "the default obs=frames_vae"
        )
    p = Path(path)
    if not p.is_file():
        raise StageError(f"agent.merola.resnet_weights={path}: no such file; give the path of a ResNet-18 state dict")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as err:  # a truncated or foreign file
        raise StageError(f"{p} is not a readable torch state dict ({err}); give a ResNet-18 checkpoint") from None
    net = ResNet18Features()
    state = {k: v for k, v in state.items() if not k.startswith("fc.")}
    try:
        missing, unexpected = net.load_state_dict(state, strict=False)
    except RuntimeError as err:  # a tensor of the wrong shape under a ResNet name
        missing, unexpected = [str(err).splitlines()[-1].strip()], []
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]  # absent from older checkpoints
    if missing or unexpected:
        raise StageError(
            f"{p} is not a ResNet-18 state dict with torchvision's names: missing {missing[:3]}..., unexpected "
            f"{unexpected[:3]}...; give torchvision's resnet18 checkpoint"
        )
    for param in net.parameters():
        param.requires_grad_(False)
    return net.eval()
