"""DeepLabV3 (dilated ResNet + ASPP + 1x1 classifier, bilinear upsampling) in plain PyTorch.

Written by hand because torchvision cannot be installed beside the CPU torch of these machines
(PyPI's torchvision fails to import beside torch 2.13.0 CPU). Two sizes: ``r18-os16`` (BasicBlock
ResNet-18 layout, output stride 16, ASPP rates 6/12/18; the CPU default) and ``r50-os8`` (Bottleneck
ResNet-50 layout, output stride 8, ASPP rates 12/24/36, as the paper's torchvision model). ``torchvision-r50`` builds torchvision's own
deeplabv3_resnet50 when torchvision is importable. No weights are downloaded: pretrained weights
come only from a path the user gives (``load_backbone_weights``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .config import ModelConfig


class BasicBlock(nn.Module):
    """ResNet's two-convolution residual block (ResNet-18/34), with stride and dilation."""

    expansion = 1

    def __init__(self, cin, cout, stride=1, dilation=1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, dilation, dilation, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, dilation, dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.down = None if stride == 1 and cin == cout else nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        """x [B, cin, H, W] -> [B, cout, H / stride, W / stride]."""
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + (x if self.down is None else self.down(x)))


class Bottleneck(nn.Module):
    """ResNet's 1x1-3x3-1x1 residual block (ResNet-50), output channels 4 x ``planes``, with stride and
    dilation."""

    expansion = 4

    def __init__(self, cin, planes, stride=1, dilation=1):
        super().__init__()
        cout = planes * 4
        self.conv1 = nn.Conv2d(cin, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride, dilation, dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, cout, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(cout)
        self.down = None if stride == 1 and cin == cout else nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        """x [B, cin, H, W] -> [B, 4 planes, H / stride, W / stride]."""
        y = F.relu(self.bn1(self.conv1(x)))
        y = F.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return F.relu(y + (x if self.down is None else self.down(x)))


class DilatedResNet(nn.Module):
    """ResNet trunk whose last stages trade stride for dilation (output stride 8 or 16)."""

    def __init__(self, block, layers, width, output_stride):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3, width, 7, 2, 3, bias=False), nn.BatchNorm2d(width), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, 1))
        dilate = {16: (False, False, True), 8: (False, True, True)}[output_stride]
        cin, dilation, stages = width, 1, []
        for i, blocks in enumerate(layers):
            planes = width * 2**i
            stride = 1 if i == 0 else 2
            if i > 0 and dilate[i - 1]:
                dilation, stride = dilation * 2, 1
            stage = [block(cin, planes, stride, dilation)]
            cin = planes * block.expansion
            stage += [block(cin, planes, 1, dilation) for _ in range(blocks - 1)]
            stages.append(nn.Sequential(*stage))
        self.layer1, self.layer2, self.layer3, self.layer4 = stages
        self.out_channels = cin

    def forward(self, x):
        """Images [B, 3, H, W] -> features [B, C, H / os, W / os] (os: the output stride)."""
        return self.layer4(self.layer3(self.layer2(self.layer1(self.stem(x)))))


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling: a 1x1 branch, a 3x3 branch per dilation rate and an image-pooling
    branch, concatenated and projected to ``cout`` channels."""

    def __init__(self, cin, cout, rates):
        super().__init__()
        branch = lambda k, r: nn.Sequential(nn.Conv2d(cin, cout, k, padding=0 if k == 1 else r, dilation=r, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))  # noqa: E731
        self.branches = nn.ModuleList([branch(1, 1)] + [branch(3, r) for r in rates])
        self.pool = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))
        self.project = nn.Sequential(nn.Conv2d(cout * (len(rates) + 2), cout, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True), nn.Dropout(0.1))

    def forward(self, x):
        """Features [B, cin, h, w] -> [B, cout, h, w]."""
        pooled = F.interpolate(self.pool(x), size=x.shape[-2:], mode="bilinear", align_corners=False)
        return self.project(torch.cat([b(x) for b in self.branches] + [pooled], dim=1))


class DeepLabV3(nn.Module):
    """logits [B, K, H, W] at the input resolution."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        if config.arch == "r18-os16":
            self.backbone = DilatedResNet(BasicBlock, (2, 2, 2, 2), config.width, 16)
            rates = (6, 12, 18)
        elif config.arch == "r50-os8":
            self.backbone = DilatedResNet(Bottleneck, (3, 4, 6, 3), config.width, 8)
            rates = (12, 24, 36)
        else:
            raise ValueError(f"model arch must be r18-os16, r50-os8 or torchvision-r50, got {config.arch!r}")
        c = config.aspp_channels
        self.head = nn.Sequential(ASPP(self.backbone.out_channels, c, rates), nn.Conv2d(c, c, 3, padding=1, bias=False),
                                  nn.BatchNorm2d(c), nn.ReLU(inplace=True), nn.Conv2d(c, config.num_classes, 1))

    def forward(self, x):
        """Images [B, 3, H, W] (normalised) -> logits [B, K, H, W]."""
        return F.interpolate(self.head(self.backbone(x)), size=x.shape[-2:], mode="bilinear", align_corners=False)


class _TorchvisionDeepLab(nn.Module):
    def __init__(self, config: ModelConfig):
        super().__init__()
        from torchvision.models.segmentation import deeplabv3_resnet50

        self.net = deeplabv3_resnet50(weights=None, weights_backbone=None, num_classes=config.num_classes, aux_loss=False)

    def forward(self, x):
        return self.net(x)["out"]


def build_model(config: ModelConfig) -> nn.Module:
    """The network ``config`` describes (randomly initialised). Raises ValueError for ``torchvision-r50``
    without an importable torchvision."""
    if config.arch == "torchvision-r50":
        try:
            return _TorchvisionDeepLab(config)
        except (ImportError, RuntimeError) as exc:
            raise ValueError(f"model arch torchvision-r50 needs an importable torchvision ({exc})") from None
    return DeepLabV3(config)


def load_backbone_weights(model: nn.Module, path) -> None:
    """Fill the backbone from a state dict file (weights_only); every backbone tensor must load."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such weights file") from None
    except Exception as exc:  # torch raises many types for files that are not state dicts
        raise ValueError(f"{path}: not a readable state dict ({type(exc).__name__}: {exc})") from None
    if not isinstance(state, dict):
        raise ValueError(f"{path}: expected a state dict (name -> tensor), got {type(state).__name__}")
    state = state.get("state_dict", state)
    backbone = model.backbone if hasattr(model, "backbone") else model.net.backbone
    own = backbone.state_dict()
    matched = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    missing = sorted(set(own) - set(matched))
    if missing:
        raise ValueError(f"{path}: {len(missing)} backbone tensors missing or of another shape, e.g. {missing[:3]}")
    backbone.load_state_dict(matched)
