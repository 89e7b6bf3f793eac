"""The viewer behind ``codecsplat view``: one scene served to any number of browsers by viser.

Each browser gets its own copy of the scene (the Gaussians as splats that its WebGL draws, the context cameras as
frustums) and its own panel. The panel's renderer choice switches that browser to frames rendered on the server by
the package's rasterizer (:meth:`~codecsplat_warp.model.CodecSplat.render`, on ``--device``) at its camera and
streamed to it as lossless PNG: what the codec decodes, pixel for pixel, as ``codecsplat render`` renders it. One
background thread renders the frames (the newest camera of each browser), another encodes a scene folder again
when a browser moves the λ slider or picks another preset; neither stops the server when it fails or a browser
leaves mid-frame.
"""

from __future__ import annotations

import json
import math
import pathlib
import threading
import time
import warnings
from dataclasses import dataclass

import imageio.v3 as iio
import numpy as np
import torch
import viser

from ..choices import RDO_PRESETS
from ..codec import LAMBDA_MAX, LAMBDA_MIN
from ..errors import CodecSplatError
from ..export.ply import encode_ply
from ..export.video import to_uint8_frames
from ..gaussians import rotmat_to_quat
from ..model.rdo import preset_steps
from .geometry import NEAR_FRACTION, REFERENCE_WXYZ, ViewCamera, browser_camera, splat_arrays, viewer_frame
from .inputs import ENCODE_PHASES, SceneSource, ViewScene, encode_source
from .worker import LatestWork

SERVER_RENDERING = "Render on the server"
"""The label of the panel's checkbox that switches a browser from its WebGL splats to the server's frames."""

CONTEXT_CAMERAS = "Context cameras"
"""The label of the panel's checkbox that shows or hides the context cameras' frustums."""

PHOTOGRAPHS = "Their photographs"
"""The label of the panel's checkbox that puts the context views' photographs on their frustums. Off at first: from
a context camera's own pose its photograph fills the view (ticking it there compares photograph and decoded scene)."""

FRUSTUM_COLOUR = (230, 120, 20)
"""RGB of the context cameras' frustums."""

FAR_FACTOR = 100.0
"""The browser camera's far plane, in units of the scene's size (focus distance + radius)."""

FRUSTUM_SCALE = 0.15
"""Size of a context camera's frustum, as a fraction of the reference camera's focus distance."""

FRUSTUM_THICKNESS = 2.0
"""Line thickness of a frustum on the screen (pixels)."""

STOP_WAIT_S = 5.0
"""Seconds the viewer waits for a running frame or encode to end when it stops."""

TICK_S = 1.0
"""How often the panel's encoding line counts the seconds of a running encode."""

BLACK = np.zeros((1, 1, 3), dtype=np.uint8)
"""The browser's background behind its splats: black, as the rasterizer composites the decoded scene (white, viser's
default, would show through the many faint Gaussians the model makes and lighten the whole scene)."""

CLOSED_CONNECTION_WARNING = r"Queued a \w+ on a closed connection"
"""viser's warning for a message to a browser that has just left (a frame finished after its browser closed)."""


@dataclass(frozen=True)
class EncodeStatus:
    """What the panel says about encoding again: the progress bar's value (0-100), whether it moves, and a line."""

    value: float = 100.0
    busy: bool = False
    line: str = ""


@dataclass(frozen=True)
class EncodePanel:
    """The parts of a browser's panel that show :class:`EncodeStatus`."""

    progress: viser.GuiProgressBarHandle
    line: viser.GuiMarkdownHandle

    def show(self, status: EncodeStatus) -> None:
        self.progress.value = status.value
        self.progress.animated = status.busy
        self.line.content = status.line


@dataclass
class ClientView:
    """One browser's handles: its splats, its panel's parts that change, and how many frames it got."""

    client: viser.ClientHandle
    splats: viser.GaussianSplatHandle
    server_frames: viser.GuiCheckboxHandle
    frame_text: viser.GuiMarkdownHandle
    scene_text: viser.GuiMarkdownHandle
    encode_panel: EncodePanel | None = None
    frames: int = 0


class Viewer:
    """The scene, the browsers that show it and the threads that render and encode for them.

    Args:
        model: the :class:`~codecsplat_warp.model.CodecSplat` that decoded (or encoded) the scene; it renders the
            server's frames.
        scene: what to show first.
        source: the context views of a scene folder (the panel then encodes them again), else None.
        max_side: long side of a server frame, at most (pixels).
    """

    def __init__(self, model, scene: ViewScene, source: SceneSource | None, max_side: int):
        self._model = model
        self._source = source
        self._max_side = max_side
        self._device = scene.gaussians.means.device
        self._frame = viewer_frame(scene.reference, scene.splats.means)
        self._eye = scene.reference.centers[0].numpy()
        self._lock = threading.Lock()
        self._render_lock = threading.Lock()
        self._scene = scene
        self._splats = splat_arrays(scene.splats, self._eye)
        self._views: dict[int, ClientView] = {}
        self._status = EncodeStatus(line=_encoded_line(scene))
        self._frames = LatestWork("frame streamer", self._stream_frame)
        self._encoder = LatestWork("encoder", self._encode) if source is not None else None

    @property
    def scene(self) -> ViewScene:
        """The scene shown now."""
        return self._scene

    def render(self, camera: ViewCamera) -> tuple[np.ndarray, float]:
        """(uint8 [H,W,3] frame, seconds) of the scene's splats rendered at ``camera`` on the model's device by
        :meth:`~codecsplat_warp.model.CodecSplat.render`, as ``codecsplat render`` renders a pose file of it (which
        leaves out the Gaussians the camera cannot see first: the same image,
        :mod:`~codecsplat_warp.model.prune`)."""
        cameras = camera.cameras().to(self._device, torch.float32)
        with self._render_lock, torch.no_grad():
            start = time.perf_counter()
            rgb = self._model.render(self._scene.splats, cameras)["rgb"]
            frame = to_uint8_frames(rgb)[0]
            return frame, time.perf_counter() - start

    def opening_camera(self, width: int, height: int) -> ViewCamera:
        """The camera the page opens at (the reference camera's pose and vertical field of view) for a canvas of
        ``width`` x ``height`` pixels."""
        frame = self._frame
        return browser_camera(frame, REFERENCE_WXYZ, frame.reference_position, frame.fov, width, height,
                              self._max_side)

    # ----------------------------------------------------------------------------------------------
    # Serving
    def attach(self, server: viser.ViserServer) -> None:
        """Show the scene to every browser that connects to ``server``, and start the threads."""
        warnings.filterwarnings("ignore", message=CLOSED_CONNECTION_WARNING)
        frame = self._frame
        server.initial_camera.position = frame.reference_position
        server.initial_camera.look_at = (0.0, 0.0, 0.0)
        server.initial_camera.up = (0.0, 0.0, 1.0)
        server.initial_camera.fov = frame.fov
        server.initial_camera.near = NEAR_FRACTION * frame.distance
        server.initial_camera.far = FAR_FACTOR * (frame.distance + frame.radius)
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)
        self._frames.start()
        if self._encoder is not None:
            self._encoder.start()

    def stop(self) -> None:
        """Stop the threads (a running frame or encode gets :data:`STOP_WAIT_S` seconds to end)."""
        self._frames.stop(STOP_WAIT_S)
        if self._encoder is not None:
            self._encoder.stop(STOP_WAIT_S)

    def _connect(self, client: viser.ClientHandle) -> None:
        """Give a new browser the scene and its panel."""
        with self._lock:
            self._views[client.client_id] = self._add_view(client)
        client.camera.on_update(lambda _: self._camera_moved(client.client_id))

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            self._views.pop(client.client_id, None)
        self._frames.forget(client.client_id)

    def _camera_moved(self, client_id: int) -> None:
        view = self._views.get(client_id)
        if view is not None and view.server_frames.value:
            self._frames.request(client_id)

    # ----------------------------------------------------------------------------------------------
    # One browser's scene and panel
    def _add_view(self, client: viser.ClientHandle) -> ClientView:
        """The scene nodes and the panel of a new browser."""
        gui = client.gui
        gui.set_panel_label("codecsplat view")
        frame = self._frame
        client.scene.add_frame("/scene", show_axes=False, wxyz=frame.wxyz, position=frame.position)
        client.scene.set_background_image(BLACK, format="png")
        with gui.add_folder("Scene"):
            scene_text = gui.add_markdown(_scene_markdown(self._scene))
        with gui.add_folder("View"):
            server_frames = gui.add_checkbox(SERVER_RENDERING, initial_value=False,
                                             hint=f"frames of the codecsplat rasterizer on {self._device.type}, "
                                             "streamed to this page, instead of the browser's splats")
            frame_text = gui.add_markdown(self._browser_frame_line())
            if self._scene.context is not None:
                self._add_camera_controls(client)
            save_view = gui.add_button("Save this view (PNG)", hint="the server's render of this camera")
            save_camera = gui.add_button("Save this camera (pose file)",
                                         hint="a cameras.json that codecsplat render --cameras takes")
        view = ClientView(client=client, splats=self._add_splats(client, visible=True), server_frames=server_frames,
                          frame_text=frame_text, scene_text=scene_text)
        if self._source is not None:
            view.encode_panel = self._add_encode_controls(client)
        with gui.add_folder("Download"):
            if self._scene.bitstream is not None:
                gui.add_button("Bitstream (.csplat)").on_click(lambda event: self._send_bitstream(event.client))
            gui.add_button("Gaussians (3DGS .ply)").on_click(lambda event: self._send_ply(event.client))
        server_frames.on_update(lambda event: self._switch_renderer(event.client.client_id))
        save_view.on_click(lambda event: self._send_view(event.client))
        save_camera.on_click(lambda event: self._send_camera(event.client))
        return view

    def _add_camera_controls(self, client: viser.ClientHandle) -> None:
        """The context cameras' frustums in ``client``'s scene and the panel's checkboxes for them (and for their
        photographs, when the input had some)."""
        node, frustums = self._add_frustums(client)
        cameras = client.gui.add_checkbox(CONTEXT_CAMERAS, initial_value=True,
                                          hint="the context cameras as frustums")
        cameras.on_update(lambda _: setattr(node, "visible", cameras.value))
        photographs = self._scene.photographs
        if photographs is not None:
            shown = client.gui.add_checkbox(PHOTOGRAPHS, initial_value=False,
                                            hint="the context views' photographs on their frustums; from a context "
                                            "camera's own pose its photograph fills the view")
            shown.on_update(lambda _: _show_photographs(frustums, photographs if shown.value else None))

    def _add_frustums(self, client: viser.ClientHandle) -> tuple[viser.FrameHandle, list[viser.CameraFrustumHandle]]:
        """The context cameras' frustums (without photographs) under one node of ``client``'s scene: (that node,
        the frustums)."""
        frame, context = self._frame, self._scene.context
        node = client.scene.add_frame("/scene/context", show_axes=False)
        c2w, K = context.c2w.numpy(), context.K.numpy()
        frustums = [client.scene.add_camera_frustum(
            f"/scene/context/{v}", fov=2.0 * math.atan(context.height / (2.0 * K[v, 1, 1])),
            aspect=context.width / context.height, scale=FRUSTUM_SCALE * frame.distance,
            thickness=FRUSTUM_THICKNESS, thickness_units="screen", color=FRUSTUM_COLOUR,
            wxyz=tuple(rotmat_to_quat(torch.from_numpy(c2w[v, :3, :3].copy())).tolist()),
            position=tuple(c2w[v, :3, 3].tolist())) for v in range(context.num_views)]
        return node, frustums

    def _add_splats(self, client: viser.ClientHandle, visible: bool):
        """(Re)place ``client``'s splats with the scene's; returns the handle."""
        return client.scene.add_gaussian_splats("/scene/splats", visible=visible, **self._splats)

    def _add_encode_controls(self, client: viser.ClientHandle) -> EncodePanel:
        """The λ slider, the preset choice, the progress bar and the status line of a scene folder's panel."""
        gui = client.gui
        scene = self._scene
        with gui.add_folder("Encode"):
            lam = gui.add_slider("λ", min=int(LAMBDA_MIN), max=int(LAMBDA_MAX), step=1,
                                 initial_value=int(round(scene.lam)),
                                 marks=((16, "16"), (256, "256"), (512, "512"), (1024, "1024")),
                                 hint="rate trade-off: larger is more bytes and more detail")
            preset = gui.add_dropdown("Preset", tuple(RDO_PRESETS), initial_value=scene.preset,
                                      hint="encoder rate-distortion optimisation (codecsplat encode --preset)")
            panel = EncodePanel(gui.add_progress_bar(self._status.value, animated=self._status.busy),
                                gui.add_markdown(self._status.line))
        request = lambda _: self._encoder.request("encode", (float(lam.value), str(preset.value)))  # noqa: E731
        lam.on_update(request)
        preset.on_update(request)
        return panel

    def _switch_renderer(self, client_id: int) -> None:
        view = self._views.get(client_id)
        if view is None:
            return
        if view.server_frames.value:
            view.splats.visible = False
            view.frame_text.content = "rendering on the server…"
            self._frames.request(client_id)
        else:
            view.client.scene.set_background_image(BLACK, format="png")
            view.splats.visible = True
            view.frame_text.content = self._browser_frame_line()

    def _browser_frame_line(self) -> str:
        return (f"{len(self._scene.splats):,d} splats drawn by this browser (frame time: Dev Settings → "
                "WebGL Stats)")

    # ----------------------------------------------------------------------------------------------
    # Frames
    def _camera_of(self, client: viser.ClientHandle) -> ViewCamera | None:
        """The :class:`ViewCamera` of ``client``'s camera now, None before the browser has sent one."""
        camera = client.camera
        if camera.image_width < 1 or camera.image_height < 1:
            return None
        return browser_camera(self._frame, camera.wxyz, camera.position, camera.fov, camera.image_width,
                              camera.image_height, self._max_side)

    def _stream_frame(self, client_id: int, _) -> None:
        """Render the newest camera of a browser in server mode and send it the frame (the frame streamer's work)."""
        view = self._views.get(client_id)
        camera = self._camera_of(view.client) if view is not None else None
        if camera is None or not view.server_frames.value:
            return
        start = time.perf_counter()
        frame, render_s = self.render(camera)
        if client_id not in self._views or not view.server_frames.value:  # left or switched back meanwhile
            return
        view.client.scene.set_background_image(frame, format="png")
        view.frames += 1
        view.frame_text.content = (f"frame {view.frames}: {camera.width}x{camera.height} px, "
                                   f"{len(self._scene.splats):,d} splats, rendered in {1000 * render_s:.0f} ms on "
                                   f"{self._device.type}, {1000 * (time.perf_counter() - start):.0f} ms with "
                                   "sending")

    # ----------------------------------------------------------------------------------------------
    # Files
    def _stem(self) -> str:
        return pathlib.Path(self._scene.name).stem or "scene"

    def _view_name(self, camera: ViewCamera) -> str:
        """The file name (no suffix) of a saved view and its camera: the input's name and the camera's key."""
        return f"{self._stem()}-view-{camera.key}"

    def _send_view(self, client: viser.ClientHandle) -> None:
        """Send ``client`` the server's render of its camera as a PNG file."""
        camera = self._camera_of(client)
        if camera is not None:
            frame, _ = self.render(camera)
            client.send_file_download(f"{self._view_name(camera)}.png",
                                      iio.imwrite("<bytes>", frame, extension=".png"), save_immediately=True)

    def _send_camera(self, client: viser.ClientHandle) -> None:
        """Send ``client`` its camera as a one-view ``cameras.json`` (its frame: the PNG of "Save this view")."""
        camera = self._camera_of(client)
        if camera is not None:
            source = {"tool": "codecsplat view", "input": self._scene.name}
            pose = camera.pose_file(f"{self._view_name(camera)}.png", source)
            client.send_file_download(f"{self._view_name(camera)}.json", json.dumps(pose, indent=1).encode(),
                                      save_immediately=True)

    def _send_bitstream(self, client: viser.ClientHandle) -> None:
        scene = self._scene
        client.send_file_download(f"{self._stem()}-lambda{scene.lam:g}.csplat", scene.bitstream, save_immediately=True)

    def _send_ply(self, client: viser.ClientHandle) -> None:
        client.send_file_download(f"{self._stem()}.ply", encode_ply(self._scene.gaussians), save_immediately=True)

    # ----------------------------------------------------------------------------------------------
    # Encoding again (a scene folder)
    def _encode(self, _, settings: tuple[float, str]) -> None:
        """Encode the scene folder at ``settings`` (λ, preset) and show the result (the encoder's work)."""
        lam, preset = settings
        if (float(np.float32(lam)), preset) == (self._scene.lam, self._scene.preset):
            return
        steps = preset_steps(preset, self._source.cameras.num_views)
        label = f"λ={lam:g}, {preset}" + (f" ({steps} optimisation steps)" if steps else "")
        started = time.perf_counter()
        try:
            scene = self._encode_showing_progress(lam, preset, label)
        except CodecSplatError as exc:
            self._show_status(EncodeStatus(100.0, False, f"{label} failed: {exc}"))
            return
        self._show_scene(scene)
        self._show_status(EncodeStatus(100.0, False, f"{_encoded_line(scene)} (in "
                                                     f"{time.perf_counter() - started:.1f} s)"))

    def _encode_showing_progress(self, lam: float, preset: str, label: str) -> ViewScene:
        """:func:`~.inputs.encode_source`, the panels showing its phase and seconds (every :data:`TICK_S`)."""
        started, phase, finished = time.perf_counter(), [ENCODE_PHASES[0]], threading.Event()

        def show() -> None:
            done = ENCODE_PHASES.index(phase[0]) / len(ENCODE_PHASES)
            self._show_status(EncodeStatus(100.0 * done, True, f"{label}: {phase[0]}… "
                                           f"{time.perf_counter() - started:.0f} s"))

        def on_phase(name: str) -> None:
            phase[0] = name
            show()

        def tick() -> None:
            while not finished.wait(TICK_S):
                show()

        ticker = threading.Thread(target=tick, name="encode ticker", daemon=True)
        ticker.start()
        try:
            return encode_source(self._model, self._source, lam, preset, on_phase)
        finally:
            finished.set()
            ticker.join()

    def _show_scene(self, scene: ViewScene) -> None:
        """Show a newly encoded scene in every browser: its splats, its description and, in server mode, a frame."""
        with self._lock:
            self._scene = scene
            self._splats = splat_arrays(scene.splats, self._eye)
            views = list(self._views.values())
        for view in views:
            view.splats = self._add_splats(view.client, visible=not view.server_frames.value)
            view.scene_text.content = _scene_markdown(scene)
            if view.server_frames.value:
                self._frames.request(view.client.client_id)
            else:
                view.frame_text.content = self._browser_frame_line()

    def _show_status(self, status: EncodeStatus) -> None:
        """Show the encoding status in every panel."""
        with self._lock:
            self._status = status
            views = list(self._views.values())
        for view in views:
            view.encode_panel.show(status)


def _show_photographs(frustums: list[viser.CameraFrustumHandle], photographs: np.ndarray | None) -> None:
    """Put the photographs uint8 [V,H,W,3] on the V frustums, or take them off (None)."""
    for v, frustum in enumerate(frustums):
        frustum.image = photographs[v] if photographs is not None else None


def _scene_markdown(scene: ViewScene) -> str:
    """The panel's description of ``scene``: its input, model, λ, bytes per part and splat count."""
    kinds = {"bitstream": "scene bitstream", "ply": "3DGS PLY", "scene": "scene folder, encoded here"}
    lines = [f"**{scene.name}** ({kinds[scene.kind]})", ""]
    if scene.model is not None:
        lines += [f"model `{scene.model}`, λ = {scene.lam:g}" + (f", preset {scene.preset}" if scene.preset else ""),
                  "", "| part | bytes |", "|---|---:|"]
        lines += [f"| {name} | {count:,d} |" for name, count in scene.parts.items() if name != "total"]
        lines += [f"| **total** | **{scene.parts['total']:,d}** |", ""]
    if scene.context_psnr is not None:
        lines += ["context views: " + ", ".join(f"{value:.2f}" for value in scene.context_psnr) + " dB PSNR", ""]
    hidden = len(scene.gaussians) - len(scene.splats)
    lines.append(f"{len(scene.splats):,d} splats ({hidden:,d} of {len(scene.gaussians):,d} Gaussians have an opacity "
                 "below 1/255 and draw nothing)")
    return "\n".join(lines)


def _encoded_line(scene: ViewScene) -> str:
    """One line on an encoded scene: λ, preset, bytes and the context views' PSNR (empty for other inputs)."""
    if scene.context_psnr is None:
        return ""
    scores = ", ".join(f"{value:.2f}" for value in scene.context_psnr)
    return f"λ={scene.lam:g}, {scene.preset}: {len(scene.bitstream):,d} B, context views {scores} dB"
