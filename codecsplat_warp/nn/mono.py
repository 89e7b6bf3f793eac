"""Pretrained monocular backbones for MVEnc's mono slot (paper §3.2 uses a pretrained monocular ViT).

No ViT can be had offline here, so the shipped prior is the ImageNet-trained VGG16 trunk of the LPIPS
weights (torchvision keys ``features.N.*``), cut after relu3_3: 256 channels at 1/4 of the image
resolution, which is exactly MVEnc's matching grid. It is frozen (ImageNet statistics, no fine-tuning) and
its weights are part of the model's state dict, so a saved model file carries them and a user needs no
other file. :data:`MONO_BACKBONES` maps the names ``ModelConfig.mono`` may take to their builders.
"""

from __future__ import annotations

import pathlib

import torch
from safetensors.torch import load_file
from torch import nn

from ..errors import InputError
from .layers import IMAGENET_MEAN, IMAGENET_STD, copy_weights, torchvision_features, vgg16_trunk

VGG_MONO_STAGES = 3
"""relu1_2, relu2_2, relu3_3: the last one is at stride 4 (MVEnc's matching grid)."""


class VGGMono(nn.Module):
    """Frozen VGG16 up to relu3_3: images [V,3,H,W] in [0,1] -> features [V,256,H/4,W/4] (H, W multiples of 4).

    Built with random weights (a saved model's state dict fills them); :meth:`load_imagenet` reads the
    ImageNet weights from an LPIPS-style safetensors file.
    """

    out_channels = 256

    def __init__(self):
        super().__init__()
        self.trunk = vgg16_trunk(VGG_MONO_STAGES)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).reshape(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).reshape(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)

    def load_imagenet(self, file) -> "VGGMono":
        """Copy the trunk's weights from a safetensors file with torchvision keys (e.g.
        ``lpips_vgg.safetensors``; other keys are ignored). Returns self.

        Raises:
            InputError: the file is missing, or lacks a key or holds a wrong shape (naming it).
        """
        file = pathlib.Path(file)
        if not file.is_file():
            raise InputError(f"VGG16 weights file {file} does not exist")
        copy_weights(torchvision_features(self.trunk), load_file(str(file)), f"VGG16 {file}")
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = (images - self.mean.to(images.dtype)) / self.std.to(images.dtype)
        for stage in self.trunk:
            x = stage(x)
        return x


MONO_BACKBONES = {"vgg16": VGGMono}
"""``ModelConfig.mono`` names (besides ``"none"``) and the module each builds."""


def build_mono_backbone(name: str) -> nn.Module | None:
    """The backbone ``ModelConfig.mono`` names (random weights, frozen), or None for ``"none"``."""
    if name == "none":
        return None
    try:
        return MONO_BACKBONES[name]()
    except KeyError:
        raise InputError(f"unknown mono backbone {name!r}; choose none or {', '.join(MONO_BACKBONES)}") from None
