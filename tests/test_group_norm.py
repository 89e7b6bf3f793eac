"""The model's group norm: the same values and gradients as torch's on every device and inside a CUDA graph, typed
input errors."""

from __future__ import annotations

import pytest
import torch
from torch.nn import functional as F

from codecsplat_warp.errors import InputError
from codecsplat_warp.nn.layers import GroupNorm, group_norm, group_norm_by_channel_scale

from conftest import CUDA, DEVICES


@pytest.mark.parametrize("device", DEVICES)
def test_values_and_gradients_match_torch_group_norm_in_float64(device):
    x = torch.randn(2, 8, 5, 6, dtype=torch.float64, device=device, requires_grad=True)
    weight = torch.randn(8, dtype=torch.float64, device=device, requires_grad=True)
    bias = torch.randn(8, dtype=torch.float64, device=device, requires_grad=True)
    ours = group_norm_by_channel_scale(x, 4, weight, bias)
    torch.testing.assert_close(ours, F.group_norm(x, 4, weight, bias), rtol=0, atol=1e-12)
    assert torch.autograd.gradcheck(lambda *a: group_norm_by_channel_scale(a[0], 4, a[1], a[2]), (x, weight, bias))
    frozen = (weight.detach(), bias.detach())  # frozen parameters (the RDO decoder): the input's gradient only
    assert torch.autograd.gradcheck(lambda a: group_norm_by_channel_scale(a, 4, *frozen), (x,))


@pytest.mark.parametrize("device", DEVICES)
def test_the_module_matches_nn_group_norm_in_float32_and_keeps_its_state_dict(device):
    ours = group_norm(32).to(device)
    reference = torch.nn.GroupNorm(8, 32).to(device)
    with torch.no_grad():
        ours.weight.normal_()
        ours.bias.normal_()
    reference.load_state_dict(ours.state_dict())
    assert isinstance(ours, GroupNorm) and ours.num_groups == 8
    x = (3.0 + 2.0 * torch.randn(2, 32, 16, 24, device=device)).requires_grad_()
    x_reference = x.detach().clone().requires_grad_()
    torch.testing.assert_close(ours(x), reference(x_reference), rtol=1e-5, atol=1e-5)
    grad = torch.randn(2, 32, 16, 24, device=device)
    ours(x).backward(grad)
    reference(x_reference).backward(grad)
    torch.testing.assert_close(x.grad, x_reference.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ours.weight.grad, reference.weight.grad, rtol=1e-4, atol=1e-3)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="no CUDA GPU visible to torch")
def test_inside_a_cuda_graph_the_module_gives_torch_group_norm():
    ours = group_norm(32).cuda()
    with torch.no_grad():
        ours.weight.normal_()
        ours.bias.normal_()
    x = 3.0 + 2.0 * torch.randn(2, 32, 64, 48, device="cuda")
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        ours(x)  # warm-up outside the graph, as torch.cuda.graph asks
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        captured = ours(x)
    x.copy_(-1.0 + 0.5 * torch.randn_like(x))
    graph.replay()
    torch.testing.assert_close(captured, F.group_norm(x, 8, ours.weight, ours.bias), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("shape, groups, channels", [((2, 6, 4, 4), 4, 6), ((2, 8), 4, 8), ((2, 8, 4, 4), 4, 6)])
def test_bad_shapes_are_typed_errors(shape, groups, channels):
    with pytest.raises(InputError, match="group norm"):
        group_norm_by_channel_scale(torch.zeros(shape), groups, torch.ones(channels), torch.zeros(channels))
