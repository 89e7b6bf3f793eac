"""The sub-pixel upsampling's shuffle with the convolution's bias added during its copy: the same values and
gradients as the convolution, then torch's pixel shuffle, on every device; typed input errors."""

from __future__ import annotations

import pytest
import torch
from torch.nn import functional as F

from codecsplat_warp.errors import InputError
from codecsplat_warp.nn.layers import conv3x3, pixel_shuffle_conv, pixel_shuffle_with_bias

from conftest import CUDA, DEVICES


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("factor", [2, 3])
def test_the_shuffle_with_bias_gives_torchs_shuffle_of_the_biased_map_in_float64(device, factor):
    y = torch.randn(2, 2 * factor**2, 5, 7, dtype=torch.float64, device=device, requires_grad=True)
    bias = torch.randn(2 * factor**2, dtype=torch.float64, device=device, requires_grad=True)
    ours = pixel_shuffle_with_bias(y, bias, factor)
    assert ours.shape == (2, 2, 5 * factor, 7 * factor) and ours.is_contiguous()
    assert torch.equal(ours, F.pixel_shuffle(y + bias[:, None, None], factor))
    assert torch.autograd.gradcheck(lambda a, b: pixel_shuffle_with_bias(a, b, factor), (y, bias))
    assert torch.autograd.gradcheck(lambda a: pixel_shuffle_with_bias(a, bias.detach(), factor), (y,))


@pytest.mark.parametrize("device", DEVICES)
def test_the_sub_pixel_convolution_gives_the_convolution_then_torchs_shuffle(device):
    conv = conv3x3(6, 4 * 5).to(device)
    x = torch.randn(3, 6, 9, 11, device=device, requires_grad=True)
    x_reference = x.detach().clone().requires_grad_()
    ours = pixel_shuffle_conv(x, conv, 2)
    reference = F.pixel_shuffle(conv(x_reference), 2)
    torch.testing.assert_close(ours, reference)
    grad = torch.randn_like(reference)
    ours_grads = torch.autograd.grad(ours, (x, conv.weight, conv.bias), grad)
    reference_grads = torch.autograd.grad(reference, (x_reference, conv.weight, conv.bias), grad)
    for name, a, b in zip(("input", "weight", "bias"), ours_grads, reference_grads):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5, msg=name)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="no CUDA GPU visible to torch")
def test_under_bfloat16_autocast_the_sub_pixel_convolution_keeps_the_convolutions_dtype_and_values():
    conv = conv3x3(8, 16).cuda()
    x = torch.randn(2, 8, 12, 10, device="cuda")
    with torch.autocast("cuda", dtype=torch.bfloat16):
        ours = pixel_shuffle_conv(x, conv, 2)
        reference = F.pixel_shuffle(conv(x), 2)
    assert ours.dtype == reference.dtype == torch.bfloat16
    torch.testing.assert_close(ours, reference)


@pytest.mark.parametrize("shape, bias_shape", [((2, 6, 4, 4), (6,)), ((2, 8, 4, 4), (4,)), ((8, 4, 4), (8,))])
def test_a_map_the_factor_cannot_shuffle_or_a_wrong_bias_is_an_input_error(shape, bias_shape):
    with pytest.raises(InputError, match="pixel shuffle by 2"):
        pixel_shuffle_with_bias(torch.zeros(shape), torch.zeros(bias_shape), 2)
