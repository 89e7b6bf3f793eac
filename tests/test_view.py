"""``codecsplat view`` without a browser: every bad input is refused with its own error before a server starts, the
viewer's cameras are the scene's (the page opens at the first context camera, upright; a saved camera renders the
same frame through ``codecsplat render``'s path), the splats are the Gaussians, the port check, and the background
thread's latest-request queue. The page itself, in Chromium: tests/test_view_browser.py."""

from __future__ import annotations

import json
import math
import pathlib
import socket
import threading
import time

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from conftest import tiny_coding_model
from plyfile import PlyData, PlyElement

from codecsplat_warp.cli import EXIT_USER, _context_views, main
from codecsplat_warp.data import ProceduralConfig, load_scene, procedural_scene
from codecsplat_warp.errors import DataError, InputError, PortInUseError, ViewerError
from codecsplat_warp.export.ply import write_ply
from codecsplat_warp.gaussians import SH_C0, SH_C1, Gaussians
from codecsplat_warp.model.prune import prune_gaussians

pytest.importorskip("viser", reason="viser is not installed (the README's install has it; a bare kit, such as the GPU "
                                    "machines', may not)")
from codecsplat_warp.view import inputs as view_inputs  # noqa: E402
from codecsplat_warp.view import serve as view_serve  # noqa: E402
from codecsplat_warp.view.app import Viewer  # noqa: E402
from codecsplat_warp.view.geometry import (REFERENCE_WXYZ, browser_camera, framing_camera,  # noqa: E402
                                           splat_arrays, viewer_frame)
from codecsplat_warp.view.inputs import (ENCODE_PHASES, encode_source, input_kind, read_bitstream,  # noqa: E402
                                         read_gaussians, scene_source)
from codecsplat_warp.view.ports import choose_port  # noqa: E402
from codecsplat_warp.view.worker import LatestWork  # noqa: E402

WIDTH, HEIGHT = 48, 32


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict:
    """A tiny random model with its codec, a procedural scene folder (6 views) and that model's bitstream of two of
    its views."""
    root = tmp_path_factory.mktemp("view")
    model = tiny_coding_model(0)
    scene = procedural_scene(3, ProceduralConfig(width=WIDTH, height=HEIGHT, num_views=6, texture_size=16))
    (root / "scene" / "images").mkdir(parents=True)
    frames = []
    for i in range(scene.num_views):
        iio.imwrite(root / "scene" / "images" / f"{i}.png", scene.images[i].permute(1, 2, 0).numpy())
        K, c2w = scene.cameras.K[i].double(), scene.cameras.c2w[i].double()
        frames.append({"file": f"images/{i}.png", "w": WIDTH, "h": HEIGHT, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
                       "cx": float(K[0, 2]), "cy": float(K[1, 2]), "c2w": c2w.tolist()})
    (root / "scene" / "cameras.json").write_text(json.dumps({
        "format": "codecsplat-scene-v1", "frames": frames, "near": float(scene.cameras.near.min()),
        "far": float(scene.cameras.far.max())}))
    views = [0, 3]
    data = model.encode(scene.images[views].float() / 255.0, scene.cameras.select(views).to(dtype=torch.float32), 64.0)
    (root / "tiny.csplat").write_bytes(data)
    return {"root": root, "model": model, "bitstream": root / "tiny.csplat", "scene": root / "scene"}


# --------------------------------------------------------------------------------------------------
# Bad inputs: one error each, and no server
@pytest.fixture
def no_server(monkeypatch):
    """Fails the test if ``codecsplat view`` constructs its viser server."""
    def refuse(*args, **kwargs):
        raise AssertionError("a server was started")

    monkeypatch.setattr(view_serve.viser, "ViserServer", refuse)


def _view_error(capsys, *argv: str) -> str:
    """``codecsplat view ARGV --device cpu``'s stderr (``--port 0`` unless ARGV gives a port, so that a server on
    the default port does not answer first); its exit code must be the user-error code."""
    port = [] if "--port" in argv else ["--port", "0"]
    assert main(["view", *argv, *port, "--device", "cpu"]) == EXIT_USER
    err = capsys.readouterr().err
    assert err.startswith("codecsplat: error: ") and err.count("\n") == 1, err
    return err


def test_a_missing_input_is_refused(tmp_path, capsys, no_server):
    assert "does not exist" in _view_error(capsys, str(tmp_path / "scene.csplat"))


def test_a_corrupt_bitstream_is_refused(tmp_path, capsys, no_server):
    (tmp_path / "scene.csplat").write_bytes(b"these are not the bytes of a bitstream")
    assert "not a CodecSplat bitstream" in _view_error(capsys, str(tmp_path / "scene.csplat"))


def test_a_truncated_bitstream_is_refused(tiny, tmp_path, capsys, no_server):
    data = tiny["bitstream"].read_bytes()
    (tmp_path / "cut.csplat").write_bytes(data[: len(data) - 3])
    assert "truncated" in _view_error(capsys, str(tmp_path / "cut.csplat"))


def test_a_ply_without_gaussian_fields_is_refused(tmp_path, capsys, no_server):
    points = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    PlyData([PlyElement.describe(points, "vertex")]).write(str(tmp_path / "points.ply"))
    assert "lacks the 3DGS properties" in _view_error(capsys, str(tmp_path / "points.ply"))


def test_a_bitstream_of_another_model_is_refused(tiny, capsys, no_server):
    # the tiny random model wrote it; the command decodes with the shipped model
    assert "was written by model" in _view_error(capsys, str(tiny["bitstream"]))


def test_a_port_in_use_is_refused(tiny, capsys, no_server):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        err = _view_error(capsys, str(tiny["bitstream"]), "--port", str(port))
    assert f"port {port} on 127.0.0.1 is in use: pass --port 0" in err


@pytest.mark.parametrize(("argv", "message"), [
    (["--lambda", "64"], "--lambda encode a scene folder, but"),
    (["--views", "0,1", "--size", "32x32"], "--views, --size encode a scene folder"),
    (["--cameras", "cameras.json"], "--cameras places the views of a PLY file"),
    (["--port", "70000"], "--port must be in 0-65535"),
    (["--max-frame-side", "8"], "--max-frame-side must be at least 16"),
])
def test_options_that_do_not_fit_the_input_are_refused(tiny, capsys, no_server, argv, message):
    assert message in _view_error(capsys, str(tiny["bitstream"]), *argv)


def test_a_lambda_out_of_range_is_refused(tiny, capsys, no_server):
    assert "lambda must be in [16, 1024]" in _view_error(capsys, str(tiny["scene"]), "--lambda", "2000")


# --------------------------------------------------------------------------------------------------
# Inputs
def test_input_kinds(tiny, tmp_path):
    (tmp_path / "scene.bin").write_bytes(tiny["bitstream"].read_bytes())
    (tmp_path / "cloud.txt").write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    assert input_kind(str(tiny["bitstream"])) == "bitstream"
    assert input_kind(str(tmp_path / "scene.bin")) == "bitstream"  # by its magic bytes
    assert input_kind(str(tmp_path / "cloud.txt")) == "ply"
    assert input_kind(str(tiny["scene"])) == "scene"
    assert input_kind(str(tiny["scene"] / "cameras.json")) == "scene"
    with pytest.raises(DataError, match="does not exist"):
        input_kind(str(tmp_path / "nothing"))


def test_a_ply_with_cameras_opens_at_its_first_view_with_photographs(tiny, tmp_path):
    decoded = tiny["model"].decode_scene(tiny["bitstream"].read_bytes())
    write_ply(tmp_path / "scene.ply", decoded.gaussians)
    shown = read_gaussians(str(tmp_path / "scene.ply"), str(tiny["scene"] / "cameras.json"), torch.device("cpu"))
    scene = load_scene(tiny["scene"])
    assert shown.kind == "ply" and len(shown.gaussians) == len(decoded.gaussians) and shown.bitstream is None
    assert torch.equal(shown.reference.w2c, scene.cameras.w2c[:1]) and shown.context.num_views == scene.num_views
    assert shown.photographs.shape == (scene.num_views, HEIGHT, WIDTH, 3)
    alone = read_gaussians(str(tmp_path / "scene.ply"), None, torch.device("cpu"))
    assert alone.context is None and alone.photographs is None and alone.reference.num_views == 1


def test_a_ply_s_photographs_are_sent_small(tiny, tmp_path, monkeypatch):
    decoded = tiny["model"].decode_scene(tiny["bitstream"].read_bytes())
    write_ply(tmp_path / "scene.ply", decoded.gaussians)
    monkeypatch.setattr(view_inputs, "PHOTOGRAPH_SIDE", 16)
    shown = read_gaussians(str(tmp_path / "scene.ply"), str(tiny["scene"] / "cameras.json"), torch.device("cpu"))
    assert shown.photographs.shape == (6, 11, 16, 3) and shown.photographs.dtype == np.uint8


def test_a_scene_folder_is_encoded_as_codecsplat_encode_encodes_it(tiny):
    model = tiny["model"]
    source = scene_source(str(tiny["scene"]), "0,3", None, model, _context_views)
    phases = []
    shown = encode_source(model, source, 64.0, "fast", on_phase=phases.append)
    assert phases == list(ENCODE_PHASES) and shown.kind == "scene" and shown.name == "scene"
    scene = load_scene(tiny["scene"])
    context = scene.cameras.select([0, 3]).to(dtype=torch.float32)
    expected = model.encode(scene.images[[0, 3]].float() / 255.0, context, 64.0)
    assert shown.bitstream == expected and shown.lam == 64.0 and shown.preset == "fast"
    assert shown.parts["total"] == len(expected) and len(shown.context_psnr) == 2
    torch.testing.assert_close(shown.reference.w2c, scene.cameras.w2c[:1], rtol=0, atol=1e-6)  # float32 at encode
    assert shown.photographs.shape == (2, HEIGHT, WIDTH, 3)
    with pytest.raises(InputError, match="lambda must be in"):
        encode_source(model, source, 2000.0, "fast")


# --------------------------------------------------------------------------------------------------
# Cameras
@pytest.fixture(scope="module")
def viewer(tiny) -> Viewer:
    scene = read_bitstream(tiny["model"], str(tiny["bitstream"]))
    return Viewer(tiny["model"], scene, None, max_side=960)


def test_the_page_opens_at_the_first_context_camera(tiny, viewer):
    context = viewer.scene.context
    camera = viewer.opening_camera(context.width, context.height)
    opening = camera.cameras()
    # the bitstream stores float32 cameras: their rotations are orthonormal to float32 rounding
    torch.testing.assert_close(opening.w2c, context.w2c[:1], rtol=0, atol=1e-6)
    torch.testing.assert_close(opening.K, context.K[:1], rtol=0, atol=1e-9)
    frame, _ = viewer.render(camera)
    with torch.no_grad():
        reference = tiny["model"].render(viewer.scene.splats, context.select([0]).to(dtype=torch.float32))["rgb"]
    expected = (reference[0].permute(1, 2, 0).clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    assert frame.std() > 5 and np.abs(frame.astype(int) - expected).max() <= 1


def test_the_viewer_world_is_upright_and_rigid(viewer):
    frame = viewer._frame
    context = viewer.scene.context
    reference = frame.scene_c2w(REFERENCE_WXYZ, frame.reference_position)
    np.testing.assert_allclose(reference, context.c2w[0].numpy(), atol=1e-6)
    up = -context.c2w[0, :3, 1].numpy()
    np.testing.assert_allclose(frame.rotation[:, 2], up, atol=1e-12)  # viser's z (its orbit's up) is the camera's up
    # turning the browser's camera about viser's z turns the scene camera about the reference camera's up
    angle = 0.3
    turn = (math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2))
    wxyz = _quat_multiply(turn, REFERENCE_WXYZ)
    position = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]]) @ \
        np.array(frame.reference_position)
    turned = frame.scene_c2w(wxyz, position)
    assert abs(float(turned[:3, 1] @ reference[:3, 1]) - 1.0) < 1e-6  # the down axis stays (no roll)
    np.testing.assert_allclose(np.linalg.norm(turned[:3, 3] - frame.focus), frame.distance, rtol=1e-6)
    assert math.isclose(math.acos(np.clip(turned[:3, 2] @ reference[:3, 2], -1, 1)), angle, rel_tol=1e-6)


def _quat_multiply(a, b) -> tuple:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def test_a_saved_camera_renders_the_same_frame_as_codecsplat_render(tiny, viewer, tmp_path):
    frame = viewer._frame
    camera = browser_camera(frame, _quat_multiply((math.cos(0.1), 0.0, math.sin(0.1), 0.0), REFERENCE_WXYZ),
                            (0.2, -frame.distance * 1.3, 0.1), 0.7, 61, 40, max_side=960)
    (tmp_path / "view.json").write_text(json.dumps(camera.pose_file("view.png", {"tool": "test"})))
    loaded = load_scene(tmp_path / "view.json").cameras
    made = camera.cameras()
    assert torch.equal(loaded.K, made.K) and torch.equal(loaded.w2c, made.w2c)
    assert torch.equal(loaded.near, made.near) and torch.equal(loaded.far, made.far)
    # what codecsplat render does with the pose file: prune for its frames, render each
    model = tiny["model"]
    scene = model.decode_scene(tiny["bitstream"].read_bytes())
    cameras = loaded.to("cpu", torch.float32)
    pruned, _ = prune_gaussians(scene.gaussians, cameras)
    with torch.no_grad():
        offline = model.render(pruned, cameras)["rgb"]
    offline = (offline[0].permute(1, 2, 0).clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    streamed, _ = viewer.render(camera)
    assert streamed.shape == (40, 61, 3) and streamed.std() > 5
    assert np.array_equal(streamed, offline)


def test_frames_are_scaled_down_to_the_largest_side(viewer):
    frame = viewer._frame
    full = browser_camera(frame, REFERENCE_WXYZ, frame.reference_position, 0.5, 1920, 1080, max_side=4096)
    small = browser_camera(frame, REFERENCE_WXYZ, frame.reference_position, 0.5, 1920, 1080, max_side=960)
    assert (small.width, small.height) == (960, 540) and (full.width, full.height) == (1920, 1080)
    assert math.isclose(small.fy / small.height, full.fy / full.height) and small.cx == 480 and small.cy == 270
    assert math.isclose(full.fy, 540 / math.tan(0.25))


def test_the_depth_range_holds_every_gaussian(viewer):
    frame = viewer._frame
    far_away = browser_camera(frame, REFERENCE_WXYZ, (0.0, -50 * frame.distance, 0.0), 0.5, 64, 64, 960)
    means = viewer.scene.splats.means.double().numpy()
    depth = (means - far_away.c2w[:3, 3]) @ far_away.c2w[:3, 2]
    assert depth.max() <= far_away.far and far_away.near < 0.5 * depth.min()


def test_splats_are_the_gaussians_covariances_and_their_colours_towards_the_viewpoint():
    half = math.sqrt(0.5)
    sh = torch.zeros(2, 4, 3)
    sh[:, 0] = torch.tensor([0.2, -0.1, 0.4])
    sh[:, 3] = torch.tensor([0.5, 0.0, -0.5])  # the -x basis function: brighter red looking along -x
    gaussians = Gaussians(means=torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]),
                          quats=torch.tensor([[half, 0.0, 0.0, half], [1.0, 0.0, 0.0, 0.0]]),
                          scales=torch.tensor([[1.0, 2.0, 3.0], [0.1, 0.1, 0.1]]),
                          opacities=torch.tensor([0.5, 0.25]), sh=sh)
    arrays = splat_arrays(gaussians, np.zeros(3))
    np.testing.assert_allclose(arrays["covariances"][0], np.diag([4.0, 1.0, 9.0]), atol=1e-6)  # 90 deg about z
    np.testing.assert_allclose(arrays["covariances"][1], np.eye(3) * 0.01, atol=1e-7)
    dc = 0.5 + SH_C0 * sh[0, 0].numpy()
    np.testing.assert_allclose(arrays["rgbs"][0], np.clip(dc - SH_C1 * 1.0 * sh[0, 3].numpy(), 0, 1), atol=1e-6)
    np.testing.assert_allclose(arrays["rgbs"][1], np.clip(dc + SH_C1 * 1.0 * sh[0, 3].numpy(), 0, 1), atol=1e-6)
    np.testing.assert_allclose(arrays["opacities"], [[0.5], [0.25]])
    assert arrays["centers"].dtype == np.float32 and arrays["centers"].shape == (2, 3)


def test_a_ply_alone_opens_at_a_view_that_frames_it():
    points = torch.randn(500, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor([2.0, 1.0, 0.5]) + 10.0
    camera = framing_camera(points)
    frame = viewer_frame(camera, points)
    seen = browser_camera(frame, REFERENCE_WXYZ, frame.reference_position, frame.fov, 400, 400, 960)
    local = (points.double().numpy() - seen.c2w[:3, 3]) @ seen.c2w[:3, :3]
    u = seen.fx * local[:, 0] / local[:, 2] + seen.cx
    v = seen.fy * local[:, 1] / local[:, 2] + seen.cy
    inside = (local[:, 2] > 0) & (u >= 0) & (u < 400) & (v >= 0) & (v < 400)
    assert inside.mean() >= 0.9
    np.testing.assert_allclose(camera.c2w[0, :3, :3].numpy(), np.eye(3))  # the scene's own axes: +z ahead, y down


# --------------------------------------------------------------------------------------------------
# Ports
def test_port_zero_takes_the_first_free_port_and_a_taken_port_is_an_error():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(PortInUseError, match=f"port {port} on 127.0.0.1 is in use"):
            choose_port("127.0.0.1", port, 8080)
        chosen = choose_port("127.0.0.1", 0, port)
    assert chosen > port
    with pytest.raises(ViewerError, match="not a host name or address"):
        choose_port("no such host.invalid", 8080, 8080)


# --------------------------------------------------------------------------------------------------
# The background threads' queue
def test_latest_work_runs_each_key_once_with_its_newest_value_and_survives_a_failure(capsys):
    started, release, done = threading.Event(), threading.Event(), []

    def work(key, value):
        if value == "block":
            started.set()
            release.wait(10)
        if value == "fail":
            raise RuntimeError("a failed frame")
        done.append((key, value))

    queue = LatestWork("test worker", work)
    queue.start()
    queue.request("a", "block")
    assert started.wait(10)
    for value in ("first", "second", "newest"):
        queue.request("b", value)
    queue.request("c", "fail")
    queue.request("d", "gone")
    queue.forget("d")
    release.set()
    queue.request("e", "after the failure")
    deadline = time.monotonic() + 10
    while len(done) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    queue.stop(10)
    assert done == [("a", "block"), ("b", "newest"), ("e", "after the failure")]
    assert "test worker failed" in capsys.readouterr().err
