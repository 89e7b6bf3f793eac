"""3DGS PLY export: layout read back through plyfile, round trip, pruning and errors."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from codecsplat_warp.errors import DataError
from codecsplat_warp.export import attribute_names, read_ply, write_ply
from codecsplat_warp.model.prune import OPACITY_THRESHOLD, prune_transparent
from codecsplat_warp.gaussians import Gaussians


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return Gaussians(
        means=torch.randn(n, 3, generator=g) * 3,
        quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        scales=torch.rand(n, 3, generator=g) * 0.2 + 1e-3,
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        sh=torch.randn(n, k, 3, generator=g) * 0.3,
    )


def test_file_has_the_3dgs_layout(tmp_path):
    gaussians = random_gaussians(40, degree=2)
    k = 9
    gaussians.sh = torch.arange(k * 3, dtype=torch.float32).reshape(1, k, 3).repeat(40, 1, 1)  # sh[n,k,c] = 3k + c
    size = write_ply(tmp_path / "s.ply", gaussians)
    ply = PlyData.read(str(tmp_path / "s.ply"))
    assert size == (tmp_path / "s.ply").stat().st_size and not ply.text and ply.byte_order == "<"
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == attribute_names(2) and len(attribute_names(2)) == 9 + 24 + 8
    assert all(p.val_dtype in ("f4", "float32") for p in vertex.properties)
    v = vertex.data
    assert v["f_dc_0"][0] == 0 and v["f_dc_1"][0] == 1 and v["f_dc_2"][0] == 2
    # channel-major f_rest: R coefficients 1..8, then G, then B
    assert [v[f"f_rest_{i}"][0] for i in range(24)] == [3 * kk + c for c in range(3) for kk in range(1, k)]
    np.testing.assert_allclose(v["opacity"], torch.logit(gaussians.opacities.double()).numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.stack([v[f"scale_{i}"] for i in range(3)], 1), gaussians.scales.log().numpy(), rtol=1e-6)
    np.testing.assert_allclose(np.stack([v[f"rot_{i}"] for i in range(4)], 1), gaussians.quats.numpy(), atol=1e-7)
    assert not any(v[n].any() for n in ("nx", "ny", "nz"))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip(tmp_path, degree):
    gaussians = random_gaussians(64, degree, seed=degree)
    gaussians.opacities[0] = 1.0  # sigmoid saturated in float32: must stay finite in the file
    write_ply(tmp_path / "s.ply", gaussians)
    back = read_ply(tmp_path / "s.ply")
    assert back.sh_degree == degree and len(back) == 64
    for name in ("means", "quats", "scales", "opacities", "sh"):
        torch.testing.assert_close(getattr(back, name), getattr(gaussians, name), rtol=2e-6, atol=2e-7, msg=name)


def test_round_trip_renders_the_same_image(tmp_path):
    from codecsplat_warp.model import CodecSplat
    from codecsplat_warp.nn.config import get_preset
    from codecsplat_warp.model.report import example_inputs

    model = CodecSplat(get_preset("tiny")).eval()
    images, cameras = example_inputs(model.config, torch.device("cpu"))
    with torch.no_grad():
        gaussians = model(images, cameras)["gaussians"]
    write_ply(tmp_path / "s.ply", gaussians)
    before = model.render(gaussians, cameras)["rgb"]
    after = model.render(read_ply(tmp_path / "s.ply"), cameras)["rgb"]
    torch.testing.assert_close(after, before, rtol=0, atol=1e-5)


def test_prune_leaves_out_gaussians_below_one_255th():
    gaussians = random_gaussians(10, degree=1)
    gaussians.opacities[:] = torch.tensor([0.0, 0.5 / 255, 0.999 / 255, 1.0 / 255, 0.01, 0.5, 0.9, 1e-5, 0.2, 1.0])
    kept, removed = prune_transparent(gaussians)
    assert removed == 4 and len(kept) == 6 and bool((kept.opacities >= OPACITY_THRESHOLD).all())
    torch.testing.assert_close(kept.means, gaussians.means[gaussians.opacities >= 1 / 255])


def test_read_errors_are_data_errors(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    with pytest.raises(DataError, match="not a readable PLY"):
        read_ply(tmp_path / "junk.ply")
    points = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    PlyData([PlyElement.describe(points, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(DataError, match="lacks the 3DGS properties"):
        read_ply(tmp_path / "points.ply")
    odd = np.zeros(3, dtype=[(n, "<f4") for n in attribute_names(0)] + [("f_rest_0", "<f4")])
    PlyData([PlyElement.describe(odd, "vertex")]).write(str(tmp_path / "odd.ply"))
    with pytest.raises(DataError, match="f_rest"):
        read_ply(tmp_path / "odd.ply")


def test_an_interrupted_write_leaves_no_file(tmp_path, monkeypatch):
    def half_write(self, data):
        with open(self, "wb") as handle:
            handle.write(data[:10])
        raise KeyboardInterrupt

    monkeypatch.setattr(pathlib.Path, "write_bytes", half_write)
    with pytest.raises(KeyboardInterrupt):
        write_ply(tmp_path / "s.ply", random_gaussians(5, degree=0))
    assert list(tmp_path.iterdir()) == []
