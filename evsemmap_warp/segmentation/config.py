"""Segmentation model settings, importable without torch (the CLI reads its defaults)."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class ModelConfig:
    """The segmentation network's shape: the architecture, K classes, the channels of the first ResNet stage
    and of the ASPP (what a checkpoint must match to load its weights)."""

    arch: str = "r18-os16"  # r18-os16 | r50-os8 | torchvision-r50
    num_classes: int = 9
    # The CPU-friendly default; the full-size model is arch r50-os8, width 64, aspp_channels 256.
    width: int = 32  # channels of the first ResNet stage (64 = the standard ResNet)
    aspp_channels: int = 64

    def as_dict(self) -> dict:
        """Every field by name (stored in checkpoints)."""
        return asdict(self)
