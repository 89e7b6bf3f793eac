"""Geometry between the scene and the browser viewer: the viewer's world frame, the browser's camera as the
package's :class:`~codecsplat_warp.cameras.Cameras` (and as a ``cameras.json`` pose file), and Gaussians as the
arrays viser's splat renderer draws.

viser's world is z-up and its orbit controls keep z up. The scene's world (OpenCV, as every camera of the package)
has no up direction, so the viewer puts the scene under one rigid transform, :class:`ViewerFrame`: viser's x is the
reference camera's right, y its viewing direction and z its up (-y of the OpenCV camera), and viser's origin is the
point the reference camera looks at (its focus, at the median depth of the Gaussians in front of it). The reference
camera is the first context camera of the input, so the page opens upright at that camera's view.

A browser camera (viser: OpenCV axes too, a vertical field of view, the canvas size in device pixels) becomes a
:class:`ViewCamera`: a pinhole camera in the scene's world, centred principal point, square pixels. Its
:meth:`ViewCamera.cameras` go through the same constructor as a loaded ``cameras.json``
(:func:`~codecsplat_warp.data.scene.cameras_from_arrays`, float64), so that ``codecsplat render --cameras`` of its
:meth:`ViewCamera.pose_file` renders the same frame.
"""

from __future__ import annotations

import hashlib
import json
import math
import pathlib
from dataclasses import dataclass

import numpy as np
import torch

from ..cameras import Cameras
from ..data.scene import cameras_from_arrays
from ..data.scene_json import FORMAT_NAME
from ..gaussians import Gaussians, quat_to_rotmat, rotmat_to_quat, sh_basis

NEAR_FRACTION = 0.01
"""The near bound of a browser camera, as a fraction of the reference camera's focus distance (the renderer culls
Gaussians nearer than half of it)."""

DEFAULT_FOV = math.radians(50.0)
"""Vertical field of view of the reference camera of an input without cameras (a PLY alone), radians."""

DEFAULT_FRAMING_PERCENTILE = 90.0
"""An input without cameras is framed so that this percentile of the Gaussians' distances from their median centre
fills the default field of view."""

DEFAULT_REFERENCE_SIZE = 512
"""Image side (pixels) of the reference camera made up for an input without cameras."""

REFERENCE_WXYZ = (math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0)
"""The reference camera's orientation in viser's world (w, x, y, z): looking along +y with z up."""

POSE_CONVENTION = "opencv c2w, pixels at stored size, pixel centers at +0.5"
"""The ``convention`` note of the pose files the viewer writes (as the package's scene folders carry it)."""


@dataclass(frozen=True)
class ViewerFrame:
    """The rigid map between the scene's world and viser's (see the module docstring).

    Attributes:
        rotation: [3,3] float64: its columns are viser's x, y and z axes in scene coordinates.
        focus: [3] float64: the scene point at viser's origin.
        distance: the reference camera's distance to the focus (scene units, > 0).
        fov: the reference camera's vertical field of view (radians).
        radius: the largest distance of a Gaussian centre from the focus (scene units).
    """

    rotation: np.ndarray
    focus: np.ndarray
    distance: float
    fov: float
    radius: float

    @property
    def reference_position(self) -> tuple[float, float, float]:
        """The reference camera's centre in viser's world: on the -y axis, at its focus distance."""
        return (0.0, -self.distance, 0.0)

    @property
    def wxyz(self) -> tuple[float, float, float, float]:
        """The quaternion (w, x, y, z) of the scene -> viser rotation (the frame node's orientation in viser)."""
        return tuple(rotmat_to_quat(torch.from_numpy(self.rotation.T.copy())).tolist())

    @property
    def position(self) -> tuple[float, float, float]:
        """Where the scene's origin lies in viser's world (the frame node's position)."""
        return tuple((-self.rotation.T @ self.focus).tolist())

    def scene_c2w(self, wxyz, position) -> np.ndarray:
        """[4,4] float64 camera-to-world in the scene of a viser camera (orientation ``wxyz``, centre ``position``,
        both in viser's world, OpenCV axes)."""
        R_viser = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz, dtype=np.float64))).numpy()
        c2w = np.eye(4)
        c2w[:3, :3] = self.rotation @ R_viser
        c2w[:3, 3] = self.rotation @ np.asarray(position, dtype=np.float64) + self.focus
        return c2w


@dataclass(frozen=True)
class ViewCamera:
    """One pinhole camera of the viewer in the scene's world (OpenCV axes, pixel centres at +0.5).

    Attributes:
        c2w: [4,4] float64 camera-to-world.
        fx, fy, cx, cy: intrinsics in pixels.
        width, height: image size in pixels.
        near, far: the depth range (scene units) the renderer culls with (half of near, twice far).
    """

    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float
    far: float

    @property
    def key(self) -> str:
        """Eight hex digits that name this camera (the same camera, the same key): a saved view and its pose file
        share it, and the files of two cameras do not overwrite each other."""
        values = [self.c2w.tolist(), self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.near, self.far]
        return hashlib.sha256(json.dumps(values).encode()).hexdigest()[:8]

    def cameras(self) -> Cameras:
        """float64 :class:`Cameras` of this camera, made as ``load_scene`` makes those of :meth:`pose_file`."""
        return cameras_from_arrays(pathlib.Path("codecsplat view"), [self.fx], [self.fy], [self.cx], [self.cy],
                                   self.c2w[None], self.near, self.far, self.width, self.height)

    def pose_file(self, image: str, source: dict) -> dict:
        """This camera as a one-frame ``cameras.json`` (codecsplat-scene-v1) whose frame is the file ``image``;
        ``source`` says where it came from. ``load_scene`` of it gives :meth:`cameras` exactly (JSON keeps every
        float64 digit)."""
        frame = {"file": image, "w": self.width, "h": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                 "cy": self.cy, "c2w": self.c2w.tolist()}
        return {"format": FORMAT_NAME, "convention": POSE_CONVENTION, "frames": [frame], "near": self.near,
                "far": self.far, "source": source}


def viewer_frame(reference: Cameras, means: torch.Tensor) -> ViewerFrame:
    """The :class:`ViewerFrame` of the first camera of ``reference``, focused at the median depth of the Gaussian
    centres ``means`` [N,3] in front of it (at a unit distance when none is)."""
    c2w = reference.c2w[0].detach().to("cpu", torch.float64).numpy()
    fy = float(reference.K[0, 1, 1])
    points = means.detach().to("cpu", torch.float64).numpy()
    depth = (points - c2w[:3, 3]) @ c2w[:3, 2]
    ahead = depth[depth > 0]
    distance = float(np.median(ahead)) if ahead.size else 1.0
    focus = c2w[:3, 3] + distance * c2w[:3, 2]
    rotation = np.stack([c2w[:3, 0], c2w[:3, 2], -c2w[:3, 1]], axis=1)
    radius = float(np.linalg.norm(points - focus, axis=1).max()) if points.size else distance
    return ViewerFrame(rotation=rotation, focus=focus, distance=distance,
                       fov=2.0 * math.atan(reference.height / (2.0 * fy)), radius=radius)


def framing_camera(means: torch.Tensor) -> Cameras:
    """A reference camera for Gaussians without cameras (a PLY alone): the scene's axes (looking along +z, y down),
    :data:`DEFAULT_FOV`, placed so that the :data:`DEFAULT_FRAMING_PERCENTILE` percentile of the centres' distances
    from their median fills the view. float64, :data:`DEFAULT_REFERENCE_SIZE` pixels square."""
    points = means.detach().to("cpu", torch.float64)
    centre = points.median(dim=0).values
    spread = float(torch.quantile((points - centre).norm(dim=1), DEFAULT_FRAMING_PERCENTILE / 100.0)) or 1.0
    distance = spread / math.tan(DEFAULT_FOV / 2.0) + spread
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 3] = centre - distance * torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    f = DEFAULT_REFERENCE_SIZE / (2.0 * math.tan(DEFAULT_FOV / 2.0))
    half = DEFAULT_REFERENCE_SIZE / 2.0
    return cameras_from_arrays(pathlib.Path("codecsplat view"), [f], [f], [half], [half], c2w[None].numpy(),
                               NEAR_FRACTION * distance, distance + 2.0 * spread, DEFAULT_REFERENCE_SIZE,
                               DEFAULT_REFERENCE_SIZE)


def browser_camera(frame: ViewerFrame, wxyz, position, fov: float, width: int, height: int,
                   max_side: int) -> ViewCamera:
    """The :class:`ViewCamera` of a browser camera: orientation ``wxyz`` and centre ``position`` in viser's world,
    vertical field of view ``fov`` (radians), a canvas of ``width`` x ``height`` device pixels, scaled down to at
    most ``max_side`` pixels on its long side (the browser stretches the frame over its canvas). Its depth range
    holds every Gaussian: near :data:`NEAR_FRACTION` of the focus distance, far the camera's distance to the focus
    plus the scene's radius."""
    scale = min(1.0, max_side / max(width, height))
    w, h = max(1, round(width * scale)), max(1, round(height * scale))
    f = h / (2.0 * math.tan(fov / 2.0))
    c2w = frame.scene_c2w(wxyz, position)
    near = NEAR_FRACTION * frame.distance
    far = max(float(np.linalg.norm(c2w[:3, 3] - frame.focus)) + frame.radius, 2.0 * near)
    return ViewCamera(c2w=c2w, fx=f, fy=f, cx=w / 2.0, cy=h / 2.0, width=w, height=h, near=near, far=far)


def splat_arrays(gaussians: Gaussians, eye: np.ndarray) -> dict[str, np.ndarray]:
    """The arguments of viser's ``add_gaussian_splats`` for ``gaussians`` (scene coordinates): ``centers`` [N,3],
    ``covariances`` [N,3,3] (R diag(scale²) Rᵀ), ``rgbs`` [N,3] in [0,1] and ``opacities`` [N,1], float32. viser
    draws one colour per Gaussian: the spherical harmonics are evaluated once, towards the viewpoint ``eye`` [3]
    (scene coordinates), as the renderer colours them from there."""
    g = gaussians.detach()
    means = g.means.to("cpu", torch.float64)
    rotation = quat_to_rotmat(g.quats.to("cpu", torch.float64))
    covariances = rotation @ torch.diag_embed(g.scales.to("cpu", torch.float64) ** 2) @ rotation.transpose(1, 2)
    directions = torch.nn.functional.normalize(means - torch.as_tensor(eye, dtype=torch.float64), dim=-1)
    basis = sh_basis(g.sh_degree, directions)
    rgbs = ((basis[:, :, None] * g.sh.to("cpu", torch.float64)).sum(1) + 0.5).clamp(0.0, 1.0)
    as_numpy = lambda t: t.to(torch.float32).numpy()  # noqa: E731
    return {"centers": as_numpy(means), "covariances": as_numpy(covariances), "rgbs": as_numpy(rgbs),
            "opacities": as_numpy(g.opacities.to("cpu")[:, None])}
