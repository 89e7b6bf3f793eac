"""LPIPS v0.1 (Zhang et al. 2018) in plain torch, with VGG16 or AlexNet trunks.

Weights come from safetensors files ``lpips_vgg.safetensors`` / ``lpips_alex.safetensors`` whose keys are
torchvision ``features.N.{weight,bias}`` (conv index N of ``torchvision.models.vgg16`` / ``alexnet``,
OIHW) and ``lin{i}.weight`` [1,C_i,1,1] (the LPIPS linear layers). The directory is an argument or the
environment variable ``CODECSPLAT_LPIPS_WEIGHTS``.

distance(x, y) = sum over the 5 trunk stages l of mean_{h,w} sum_c w_{l,c} (n(f_l(x)) - n(f_l(y)))^2_c,
with n the unit-normalisation along channels and f_l the ReLU outputs (relu1_2 ... relu5_3 for VGG,
relu1 ... relu5 for AlexNet) of inputs in [-1,1] passed through LPIPS' scaling layer.
"""

from __future__ import annotations

import os
import pathlib
from collections import OrderedDict

import torch
from safetensors.torch import load_file
from torch import nn

from ..checks import check_tensor, common_device
from ..errors import InputError
from ..nn.layers import copy_weights, torchvision_features, vgg16_trunk

WEIGHTS_ENV = "CODECSPLAT_LPIPS_WEIGHTS"
"""Environment variable naming the directory that holds the LPIPS safetensors files."""

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
"""LPIPS scaling layer: (x - SHIFT) / SCALE for x in [-1,1] (equals ImageNet mean/std normalisation of [0,1])."""

_ALEX_LAYERS = (
    # (conv index, in, out, kernel, stride, padding) per stage; a 3x3 stride-2 max-pool precedes stages 2 and 3.
    ((0, 3, 64, 11, 4, 2),),
    ((3, 64, 192, 5, 1, 2),),
    ((6, 192, 384, 3, 1, 1),),
    ((8, 384, 256, 3, 1, 1),),
    ((10, 256, 256, 3, 1, 1),),
)

_FILES = {"vgg": "lpips_vgg.safetensors", "alex": "lpips_alex.safetensors"}


def _alex_trunk() -> nn.ModuleList:
    stages = []
    for i, convs in enumerate(_ALEX_LAYERS):
        layers: dict[str, nn.Module] = {}
        if i in (1, 2):
            layers["pool"] = nn.MaxPool2d(3, 2)
        for index, c_in, c_out, k, stride, pad in convs:
            layers[str(index)] = nn.Conv2d(c_in, c_out, k, stride=stride, padding=pad)
            layers[f"relu{index}"] = nn.ReLU()
        stages.append(nn.Sequential(OrderedDict(layers)))
    return nn.ModuleList(stages)


def resolve_weights_dir(weights_dir: str | os.PathLike | None = None) -> pathlib.Path:
    """The LPIPS weights directory: the argument, else ``$CODECSPLAT_LPIPS_WEIGHTS``; InputError if neither."""
    path = weights_dir if weights_dir is not None else os.environ.get(WEIGHTS_ENV)
    if not path:
        raise InputError(f"LPIPS weights directory not given: pass weights_dir or set {WEIGHTS_ENV} "
                         "(e.g. ../shared/weights)")
    return pathlib.Path(path)


def weights_file(net: str, weights_dir: str | os.PathLike | None = None) -> pathlib.Path:
    """The weights file of LPIPS ``net`` (``"vgg"`` or ``"alex"``) in :func:`resolve_weights_dir`'s directory.

    Raises:
        InputError: unknown net, no directory, or no such file.
    """
    if net not in _FILES:
        raise InputError(f"LPIPS net must be one of {', '.join(_FILES)}, got {net!r}")
    file = resolve_weights_dir(weights_dir) / _FILES[net]
    if not file.is_file():
        raise InputError(f"LPIPS weights file {file} does not exist")
    return file


class LPIPS(nn.Module):
    """Learned perceptual image distance; frozen, eval-mode.

    Args:
        net: ``"vgg"`` (VGG16, used for training losses) or ``"alex"`` (AlexNet, the usual evaluation metric).
        weights_dir: directory holding ``lpips_vgg.safetensors`` / ``lpips_alex.safetensors``
            (default ``$CODECSPLAT_LPIPS_WEIGHTS``).

    Raises:
        InputError: unknown net, no directory, missing file, or keys/shapes that do not match.
    """

    def __init__(self, net: str = "vgg", weights_dir: str | os.PathLike | None = None):
        super().__init__()
        file = weights_file(net, weights_dir)
        self.net = net
        self.stages = vgg16_trunk() if net == "vgg" else _alex_trunk()
        channels = [stage[-2].out_channels for stage in self.stages]
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in channels)
        self.register_buffer("shift", torch.tensor(SHIFT).reshape(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).reshape(1, 3, 1, 1), persistent=False)
        self._load(file)
        self.requires_grad_(False)
        self.eval()

    def _load(self, file: pathlib.Path) -> None:
        tensors = load_file(str(file))
        expected = torchvision_features(self.stages)
        for i, lin in enumerate(self.lins):
            expected[f"lin{i}.weight"] = lin.weight
        unexpected = sorted(set(tensors) - set(expected))
        if unexpected:
            raise InputError(f"LPIPS weights {file} do not match the {self.net} layout: unexpected {unexpected}")
        copy_weights(expected, tensors, f"LPIPS {file}")

    def train(self, mode: bool = True) -> "LPIPS":
        """Always stays in eval mode (the trunk is frozen)."""
        return super().train(False)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Per-image distance [B] between images x, y [B,3,H,W] in [0,1] (differentiable w.r.t. both).

        Computed in float32 whatever the input dtype or autocast state.
        """
        x, y = self.check_images(x, y)
        return self.distance(self.unit_features(x), self.unit_features(y))

    def check_images(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x, y`` checked as :meth:`forward` takes them (InputError / DeviceMismatchError otherwise)."""
        dims: dict[str, int] = {}
        x = check_tensor("x", x, ("B", 3, "H", "W"), (torch.float32, torch.float64, torch.bfloat16, torch.float16), dims)
        y = check_tensor("y", y, ("B", 3, "H", "W"), (torch.float32, torch.float64, torch.bfloat16, torch.float16), dims)
        common_device(x=x, y=y, weights=self.shift)
        return x, y

    def unit_features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """The unit-normalised features of every trunk stage of ``images`` [B,3,H,W] in [0,1] (float32, autocast
        off): one side of :meth:`distance`, which a caller comparing many images with one target computes once."""
        with torch.autocast(images.device.type, enabled=False):
            features, units = self._normalize(images), []
            for stage in self.stages:
                features = stage(features)
                units.append(_unit(features))
        return units

    def distance(self, x_units: list[torch.Tensor], y_units: list[torch.Tensor]) -> torch.Tensor:
        """Per-image distance [B] between two images' :meth:`unit_features`."""
        total = torch.zeros(x_units[0].shape[0], device=x_units[0].device, dtype=torch.float32)
        with torch.autocast(x_units[0].device.type, enabled=False):
            for lin, fx, fy in zip(self.lins, x_units, y_units):
                total = total + lin((fx - fy) ** 2).mean(dim=(1, 2, 3))
        return total

    def _normalize(self, images: torch.Tensor) -> torch.Tensor:
        return ((images.float() * 2.0 - 1.0) - self.shift) / self.scale


def _unit(features: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """Features divided by their L2 norm over channels (LPIPS' normalize_tensor).

    The squared norm is clamped at 1e-20 before the square root so all-zero feature vectors (dead ReLUs)
    get a zero gradient instead of NaN; their value is 0 either way.
    """
    norm = torch.sqrt((features**2).sum(dim=1, keepdim=True).clamp_min(1e-20))
    return features / (norm + eps)
