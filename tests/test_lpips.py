"""LPIPS against an independent flat torchvision-layout reference built from the same safetensors files."""

from __future__ import annotations


import pytest
from conftest import LPIPS_WEIGHTS as WEIGHTS
from conftest import needs_lpips
import torch
from safetensors.torch import load_file
from torch import nn

from codecsplat_warp.errors import InputError
from codecsplat_warp.metrics import LPIPS

pytestmark = needs_lpips

# torchvision `features` Sequentials (conv/relu/pool by index) and LPIPS' taps (ReLU outputs).
VGG = ["c3-64", "r", "c64-64", "r", "p2", "c64-128", "r", "c128-128", "r", "p2", "c128-256", "r", "c256-256", "r",
       "c256-256", "r", "p2", "c256-512", "r", "c512-512", "r", "c512-512", "r", "p2", "c512-512", "r", "c512-512", "r",
       "c512-512", "r"]
VGG_TAPS = [3, 8, 15, 22, 29]
ALEX = ["a3-64-11-4-2", "r", "p3", "a64-192-5-1-2", "r", "p3", "a192-384-3-1-1", "r", "a384-256-3-1-1", "r",
        "a256-256-3-1-1", "r"]
ALEX_TAPS = [1, 4, 7, 9, 11]


def build(spec):
    layers = []
    for item in spec:
        if item == "r":
            layers.append(nn.ReLU())
        elif item.startswith("p"):
            k = int(item[1:])
            layers.append(nn.MaxPool2d(k, 2))
        elif item.startswith("c"):
            i, o = map(int, item[1:].split("-"))
            layers.append(nn.Conv2d(i, o, 3, padding=1))
        else:
            i, o, k, s, p = map(int, item[1:].split("-"))
            layers.append(nn.Conv2d(i, o, k, stride=s, padding=p))
    return nn.Sequential(*layers)


def reference_lpips(net: str, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Textbook LPIPS v0.1: scaling layer, taps, unit-normalise, squared difference, lin, spatial mean, sum."""
    tensors = load_file(str(WEIGHTS / f"lpips_{net}.safetensors"))
    features = build(VGG if net == "vgg" else ALEX)
    features.load_state_dict({k[len("features."):]: v for k, v in tensors.items() if k.startswith("features.")})
    taps = VGG_TAPS if net == "vgg" else ALEX_TAPS
    shift = torch.tensor([-0.030, -0.088, -0.188]).reshape(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).reshape(1, 3, 1, 1)

    def activations(img):
        h, out = (img * 2 - 1 - shift) / scale, []
        for i, layer in enumerate(features):
            h = layer(h)
            if i in taps:
                out.append(h)
        return out

    total = 0
    for i, (a, b) in enumerate(zip(activations(x), activations(y))):
        a = a / (a.norm(dim=1, keepdim=True) + 1e-10)
        b = b / (b.norm(dim=1, keepdim=True) + 1e-10)
        total = total + (tensors[f"lin{i}.weight"] * (a - b) ** 2).sum(1).mean(dim=(1, 2))
    return total


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_matches_reference_and_basic_properties(net):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 64, 64, generator=g)
    y = (x + 0.1 * torch.randn(2, 3, 64, 64, generator=g)).clamp(0, 1)
    metric = LPIPS(net, WEIGHTS)
    with torch.no_grad():
        d = metric(x, y)
        torch.testing.assert_close(d, reference_lpips(net, x, y), rtol=1e-4, atol=1e-6)
        assert torch.equal(metric(x, x), torch.zeros(2))
        noise = metric(x, torch.rand(2, 3, 64, 64, generator=g))
    assert bool((d > 0).all()) and bool((noise > d).all())
    assert not any(p.requires_grad for p in metric.parameters())


def test_gradient_is_finite_even_for_identical_and_black_images():
    metric = LPIPS("vgg", WEIGHTS)
    x = torch.zeros(1, 3, 32, 32, requires_grad=True)
    metric(x, torch.zeros(1, 3, 32, 32)).sum().backward()
    assert bool(torch.isfinite(x.grad).all())


def test_missing_weights_and_bad_inputs(tmp_path, monkeypatch):
    monkeypatch.delenv("CODECSPLAT_LPIPS_WEIGHTS", raising=False)
    with pytest.raises(InputError, match="CODECSPLAT_LPIPS_WEIGHTS"):
        LPIPS("vgg")
    with pytest.raises(InputError, match="does not exist"):
        LPIPS("vgg", tmp_path)
    with pytest.raises(InputError, match="net"):
        LPIPS("squeeze", WEIGHTS)
    monkeypatch.setenv("CODECSPLAT_LPIPS_WEIGHTS", str(WEIGHTS))
    metric = LPIPS("alex")
    with pytest.raises(InputError, match="y"):
        metric(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 16))
