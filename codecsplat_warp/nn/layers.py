"""Small convolutional building blocks shared by the CodecSplat modules (NCHW float tensors)."""

from __future__ import annotations

import math
from collections import OrderedDict

import torch
from torch import nn
from torch.nn import functional as F

from ..errors import InputError


class _GroupNormByChannelScale(torch.autograd.Function):
    """Group norm whose forward takes each group's moments with ``torch.var_mean`` and applies them as one
    per-(sample, channel) scale and shift; the backward is ATen's own group-norm backward.

    Why: ATen's CUDA group norm reduces each (sample, group) in a single thread block, so the model's
    few-group, full-resolution maps (2 views x 8 groups = 16 blocks of 8 x 256 x 256 values each) leave most of
    a GPU idle; ``var_mean`` splits such a reduction over the whole GPU. Under CUDA autocast it runs in
    float32, as ATen's group norm does.
    """

    @staticmethod
    @torch.amp.custom_fwd(device_type="cuda", cast_inputs=torch.float32)
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, groups: int,
                eps: float) -> torch.Tensor:
        x = x.contiguous()
        n, c = x.shape[:2]
        var, mean = torch.var_mean(x.view(n, groups, -1), dim=2, correction=0)  # [n, groups] each
        rstd = torch.rsqrt(var + eps)
        per_group = c // groups
        scale = rstd.repeat_interleave(per_group, dim=1) * weight  # [n, c]
        shift = bias - mean.repeat_interleave(per_group, dim=1) * scale
        trailing = (1,) * (x.dim() - 2)
        ctx.save_for_backward(x, weight, mean, rstd)
        ctx.groups = groups
        return torch.addcmul(shift.view(n, c, *trailing), x, scale.view(n, c, *trailing))

    @staticmethod
    @torch.amp.custom_bwd(device_type="cuda")
    def backward(ctx, grad: torch.Tensor):
        x, weight, mean, rstd = ctx.saved_tensors
        n, c = x.shape[:2]
        grad_x, grad_weight, grad_bias = torch.ops.aten.native_group_norm_backward(
            grad.contiguous(), x, mean, rstd, weight, n, c, x[0, 0].numel(), ctx.groups,
            [bool(flag) for flag in ctx.needs_input_grad[:3]])
        return grad_x, grad_weight, grad_bias, None, None


def group_norm_by_channel_scale(x: torch.Tensor, groups: int, weight: torch.Tensor, bias: torch.Tensor,
                                eps: float = 1e-5) -> torch.Tensor:
    """``F.group_norm(x, groups, weight, bias, eps)`` for x ``[N, C, ...]`` (float32 or float64, C divisible by
    ``groups``; weight and bias ``[C]``), computed as :class:`_GroupNormByChannelScale` does; same values to
    rounding, same gradients (first order)."""
    if x.dim() < 3 or x.shape[1] % groups or weight.shape != (x.shape[1],) or bias.shape != (x.shape[1],):
        raise InputError(f"group norm of {tuple(x.shape)} into {groups} groups needs [N, C, ...] with C divisible "
                         f"by the groups and weight, bias [C]; got {tuple(weight.shape)}, {tuple(bias.shape)}")
    return _GroupNormByChannelScale.apply(x, weight, bias, groups, eps)


class GroupNorm(nn.GroupNorm):
    """``nn.GroupNorm`` (same parameters, state-dict keys and values) that, while a CUDA graph is being captured
    (the RDO decoder's step), normalises with :func:`group_norm_by_channel_scale`, whose moments use the whole
    GPU; otherwise ATen's group norm.

    Why only in a graph: there a launch costs nothing, and the split moments took an H100's graphed RDO step from
    11.2-11.4 to 10.2-10.3 ms (2 views) and 62.7-63.1 to 60.6-60.9 ms (8 views). Eagerly, the same op sequence
    slowed a stage-2 training step from 91-92 to 109-116 ms (2 views) and 118.5 to 125.1 ms (8 views)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.is_cuda and self.affine and torch.cuda.is_current_stream_capturing():
            return group_norm_by_channel_scale(x, self.num_groups, self.weight, self.bias, self.eps)
        return super().forward(x)


def group_norm(channels: int) -> GroupNorm:
    """GroupNorm with up to 8 groups (batch-size independent: training runs one scene per GPU)."""
    return GroupNorm(math.gcd(8, channels), channels)


def conv3x3(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    """3x3 convolution with 'same' padding (halves H, W when ``stride=2``)."""
    return nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1)


def zero_conv(in_channels: int, out_channels: int, kernel_size: int = 3) -> nn.Conv2d:
    """Convolution initialised to output zeros: a residual branch ending in it starts as the identity."""
    conv = nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2)
    nn.init.zeros_(conv.weight)
    nn.init.zeros_(conv.bias)
    return conv


class ResidualBlock(nn.Module):
    """Pre-activation residual block: x + conv(relu(norm(conv(relu(norm(x)))))). Shape-preserving."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(
            group_norm(channels), nn.ReLU(inplace=False), conv3x3(channels, channels),
            group_norm(channels), nn.ReLU(inplace=False), conv3x3(channels, channels),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


def conv_stack(in_channels: int, channels: int, out_channels: int, blocks: int, zero_init_out: bool = False) -> nn.Sequential:
    """conv3x3(in->channels), ``blocks`` residual blocks, ReLU, conv3x3(channels->out).

    With ``zero_init_out`` the last convolution starts at zero (residual heads).
    """
    out = zero_conv(channels, out_channels) if zero_init_out else conv3x3(channels, out_channels)
    return nn.Sequential(conv3x3(in_channels, channels), *[ResidualBlock(channels) for _ in range(blocks)],
                         nn.ReLU(inplace=False), out)


class _PixelShuffleWithBias(torch.autograd.Function):
    """``F.pixel_shuffle(y + bias[:, None, None], factor)`` in one pass: the bias add writes the shuffled layout."""

    @staticmethod
    def forward(ctx, y: torch.Tensor, bias: torch.Tensor, factor: int) -> torch.Tensor:
        n, c, h, w = y.shape
        channels = c // factor**2
        order = (0, 1, 4, 2, 5, 3)  # [n, channels, row, sub-row, column, sub-column]
        out = y.new_empty(n, channels, h, factor, w, factor)
        torch.add(y.reshape(n, channels, factor, factor, h, w).permute(order),
                  bias.to(y.dtype).view(1, channels, factor, factor, 1, 1).permute(order), out=out)  # fmt: skip
        ctx.factor = factor
        ctx.bias_dtype = bias.dtype
        return out.view(n, channels, h * factor, w * factor)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        grad_y = F.pixel_unshuffle(grad, ctx.factor)
        grad_bias = grad_y.sum(dim=(0, 2, 3)).to(ctx.bias_dtype) if ctx.needs_input_grad[1] else None
        return grad_y, grad_bias, None


def pixel_shuffle_with_bias(y: torch.Tensor, bias: torch.Tensor, factor: int) -> torch.Tensor:
    """``F.pixel_shuffle(y + bias[:, None, None], factor)`` for ``y [N, C, h, w]`` (C divisible by factor^2) and
    ``bias [C]``, with the bias added while the shuffle copies: ``[N, C / factor^2, h * factor, w * factor]``,
    differentiable in both."""
    if y.dim() != 4 or y.shape[1] % factor**2 or bias.shape != (y.shape[1],):
        raise InputError(f"pixel shuffle by {factor} of {tuple(y.shape)} needs [N, C, h, w] with C divisible by "
                         f"{factor**2} and a bias [C]; got {tuple(bias.shape)}")
    return _PixelShuffleWithBias.apply(y, bias, factor)


def pixel_shuffle_conv(x: torch.Tensor, conv: nn.Conv2d, factor: int) -> torch.Tensor:
    """``F.pixel_shuffle(conv(x), factor)`` (sub-pixel upsampling). On CUDA the convolution runs without its bias,
    which :func:`pixel_shuffle_with_bias` adds during the shuffle's copy: ATen adds a cuDNN convolution's bias in
    a pass of its own, so this saves one pass over the ``factor^2``-channel map (the same values: the same float
    additions). The CPU's convolutions add the bias themselves, so there the plain path runs."""
    if not x.is_cuda or conv.bias is None or conv.padding_mode != "zeros":
        return F.pixel_shuffle(conv(x), factor)
    y = F.conv2d(x, conv.weight, None, conv.stride, conv.padding, conv.dilation, conv.groups)
    return pixel_shuffle_with_bias(y, conv.bias, factor)


def resize(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bilinear resize of [N,C,h,w] to [N,C,height,width] (identity when the size already matches)."""
    if x.shape[-2:] == (height, width):
        return x
    return F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)


def inverse_depth_to_grid(depth: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Depth [V,H,W] resampled to [V,height,width] by area-averaging inverse depth (exact for planes).

    Averaging 1/depth rather than depth keeps thin foreground structures from being pushed back.
    """
    if depth.shape[-2:] == (height, width):
        return depth
    inverse = F.interpolate((1.0 / depth)[:, None], size=(height, width), mode="area")
    return 1.0 / inverse[:, 0]


VGG16_STAGES = (
    # (torchvision conv index, in, out) per stage; a 2x2 max-pool precedes every stage but the first.
    ((0, 3, 64), (2, 64, 64)),
    ((5, 64, 128), (7, 128, 128)),
    ((10, 128, 256), (12, 256, 256), (14, 256, 256)),
    ((17, 256, 512), (19, 512, 512), (21, 512, 512)),
    ((24, 512, 512), (26, 512, 512), (28, 512, 512)),
)
"""VGG16's convolutions, as ``torchvision.models.vgg16().features`` numbers them (3x3, padding 1, ReLU after each)."""

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
"""Per-channel normalisation of [0,1] RGB images that ImageNet-trained trunks expect."""


def vgg16_trunk(stages: int = len(VGG16_STAGES)) -> nn.ModuleList:
    """The first ``stages`` VGG16 stages (ReLU outputs relu1_2, relu2_2, relu3_3, ... at strides 1, 2, 4, ...),
    one ``nn.Sequential`` each whose convolutions are named by their torchvision index (``"0"``, ``"2"``, ...)."""
    trunk = []
    for i, convs in enumerate(VGG16_STAGES[:stages]):
        layers: dict[str, nn.Module] = {}
        if i > 0:
            layers["pool"] = nn.MaxPool2d(2, 2)
        for index, c_in, c_out in convs:
            layers[str(index)] = nn.Conv2d(c_in, c_out, 3, padding=1)
            layers[f"relu{index}"] = nn.ReLU()
        trunk.append(nn.Sequential(OrderedDict(layers)))
    return nn.ModuleList(trunk)


def torchvision_features(trunk: nn.ModuleList) -> dict[str, nn.Parameter]:
    """The parameters of a trunk under their torchvision keys ``features.N.weight`` / ``features.N.bias``."""
    params = {}
    for stage in trunk:
        for name, module in stage.named_children():
            if isinstance(module, nn.Conv2d):
                params[f"features.{name}.weight"] = module.weight
                params[f"features.{name}.bias"] = module.bias
    return params


def copy_weights(params: dict[str, torch.Tensor], tensors: dict[str, torch.Tensor], source: str) -> None:
    """Copy ``tensors[name]`` into every parameter ``params[name]`` (keys of ``tensors`` that no parameter
    names are ignored). Raises InputError naming ``source`` and the key when one is missing or of another shape."""
    missing = sorted(set(params) - set(tensors))
    if missing:
        raise InputError(f"weights {source} lack {', '.join(missing)}")
    with torch.no_grad():
        for key, param in params.items():
            if tensors[key].shape != param.shape:
                raise InputError(f"weights {source}: {key} has shape {tuple(tensors[key].shape)}, "
                                 f"expected {tuple(param.shape)}")
            param.copy_(tensors[key])
