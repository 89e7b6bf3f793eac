"""Render path of ``codecsplat render``: orbit cameras and frame / GIF / MP4 output."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from codecsplat_warp.cameras import Cameras, intrinsics_matrix
from codecsplat_warp.data.procedural import look_at
from codecsplat_warp.errors import InputError
from codecsplat_warp.export import video
from codecsplat_warp.export.video import ORBIT_MIN_RADIUS_FRACTION, mp4_plugin, orbit_cameras, to_uint8_frames, write_frames


def _context(eyes: torch.Tensor, target=(0.0, 0.0, 5.0)) -> Cameras:
    V = eyes.shape[0]
    f = torch.full((V,), 40.0, dtype=torch.float64)
    K = intrinsics_matrix(f, f, torch.full((V,), 30.0, dtype=torch.float64), torch.full((V,), 18.0, dtype=torch.float64))
    c2w = look_at(eyes.double(), torch.tensor(target, dtype=torch.float64).expand(V, 3), up=(0.0, -1.0, 0.0))
    return Cameras.from_c2w(K, c2w, torch.full((V,), 0.5), torch.full((V,), 20.0), 64, 40)


def _project(cameras: Cameras, point: torch.Tensor) -> torch.Tensor:
    cam = cameras.w2c[:, :3, :3] @ point + cameras.w2c[:, :3, 3]
    return (cameras.K @ cam[..., None])[..., 0][:, :2] / cam[:, 2:]


def test_orbit_circles_the_context_viewpoint_and_looks_at_the_focus():
    context = _context(torch.tensor([[-0.3, 0.0, 0.0], [0.3, 0.0, 0.0]]))
    depth = torch.full((2, 40, 64), 5.0)
    orbit = orbit_cameras(context, depth, 8)
    assert orbit.num_views == 8 and (orbit.width, orbit.height) == (64, 40) and orbit.dtype == context.dtype
    distances = (orbit.centers - context.centers.mean(0)).norm(dim=-1)
    torch.testing.assert_close(distances, torch.full((8,), 0.3, dtype=torch.float64))
    focus = torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)  # mean centre + median depth along the mean axis
    torch.testing.assert_close(_project(orbit, focus), torch.tensor([[30.0, 18.0]], dtype=torch.float64).expand(8, 2))
    assert bool((orbit.near == 0.5).all() and (orbit.far == 20.0).all())


def test_orbit_of_coincident_context_cameras_uses_the_minimum_radius():
    context = _context(torch.zeros(2, 3))
    orbit = orbit_cameras(context, torch.full((2, 40, 64), 4.0), 3)
    radius = (orbit.centers - torch.zeros(3, dtype=torch.float64)).norm(dim=-1)
    torch.testing.assert_close(radius, torch.full((3,), ORBIT_MIN_RADIUS_FRACTION * 4.0, dtype=torch.float64))
    with pytest.raises(InputError):
        orbit_cameras(context, torch.ones(2, 40, 64), 0)


def _frames(count=3, height=20, width=30) -> np.ndarray:
    rgb = torch.rand(count, 3, height, width, generator=torch.Generator().manual_seed(0)) * 1.2 - 0.1
    frames = to_uint8_frames(rgb)
    assert frames.dtype == np.uint8 and frames.shape == (count, height, width, 3)
    return frames


def test_png_frames_and_gif_round_trip(tmp_path):
    frames = _frames()
    paths = write_frames(tmp_path / "png", frames, "png")
    assert [p.name for p in paths] == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    assert np.array_equal(iio.imread(paths[1]), frames[1])
    (gif,) = write_frames(tmp_path / "gif", frames, "gif", fps=10)
    assert gif.name == "render.gif" and iio.imread(gif, index=None).shape[:3] == (3, 20, 30)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["frame_0000.png", "frame_0001.png", "frame_0002.png",
                                                            "gif", "png", "render.gif"]


def test_bad_format_and_fps_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="unknown frame format"):
        write_frames(tmp_path, _frames(), "avi")
    with pytest.raises(InputError, match="fps"):
        write_frames(tmp_path, _frames(), "gif", fps=0)


def test_mp4_without_plugin_names_the_package(tmp_path, monkeypatch):
    monkeypatch.setattr(video, "MP4_PLUGINS", ())  # as if neither imageio-ffmpeg nor av were installed
    with pytest.raises(InputError, match="pip install imageio-ffmpeg"):
        write_frames(tmp_path, _frames(), "mp4")
    assert list(tmp_path.iterdir()) == []


def _smooth_frames(count=4, height=20, width=30) -> np.ndarray:
    """uint8 [F,H,W,3] ramps (red along x, green along y, blue per frame) that H.264 keeps within a few levels."""
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([np.stack([x * 5, y * 7, np.full_like(x, 60 * i)], -1) for i in range(count)]).astype(np.uint8)


@pytest.mark.skipif(mp4_plugin() is None, reason="no MP4 plugin (imageio-ffmpeg or av) installed")
def test_mp4_round_trips_frames_and_fps(tmp_path):
    frames = _smooth_frames()
    (path,) = write_frames(tmp_path, frames, "mp4", fps=4)
    assert path.name == "render.mp4" and list(tmp_path.iterdir()) == [path]
    decoded = iio.imread(path, index=None, plugin=mp4_plugin())
    assert decoded.shape == frames.shape and decoded.dtype == np.uint8  # sides not multiples of 16 keep their size
    assert np.abs(decoded.astype(np.int16) - frames).mean() < 6  # lossy H.264: a few levels; frames in order
    assert iio.immeta(path, plugin=mp4_plugin())["fps"] == pytest.approx(4.0)
