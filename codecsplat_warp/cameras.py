"""Pinhole cameras: the only place where camera conventions are defined.

Conventions (used by every kernel, op, loader and the bitstream):

* **Axes**: OpenCV camera axes: x right, y down, z forward (viewing direction). A point in front of the
  camera has z > 0.
* **Extrinsics**: stored world-to-camera, ``w2c`` [V,4,4] (``X_cam = w2c @ X_world``); the camera-to-world
  matrix ``c2w`` is derived (its column 3 is the camera centre in world space).
* **Intrinsics**: ``K`` [V,3,3] in pixels at the camera's ``width`` x ``height``; a camera point
  (x, y, z) projects to column ``u = fx*x/z + cx`` and row ``v = fy*y/z + cy``. **Pixel centres are at
  +0.5**: the image covers [0, width] x [0, height] and pixel (i, j) (column i, row j) has its centre at
  (i + 0.5, j + 0.5); a centred principal point is cx = width / 2. Skew is not modelled.
* **Depth** is the z coordinate in the camera frame (not the ray length); ``near`` / ``far`` [V] bound it.
* Rescaling an image by (sx, sy) multiplies fx, cx by sx and fy, cy by sy exactly (pixel-edge convention),
  which is how feature grids smaller than the image get their intrinsics (:meth:`Cameras.rescaled`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

from .checks import FLOAT_DTYPES, check_same_dtype, check_tensor, common_device
from .errors import CameraError

ROTATION_TOLERANCE = 1e-4
"""Largest |R Rᵀ − I| entry accepted for an extrinsic rotation (float32 round-trips sit near 1e-6)."""

SKEW_TOLERANCE = 1e-3
"""Largest |K[0,1]| / fx accepted: skew is not modelled, so it must be negligible."""

MEMO_ENTRIES = 8
"""Values :meth:`Cameras.memoized` keeps per cameras object (oldest dropped first)."""

OPENGL_TO_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
"""Right-multiply an OpenGL/NeRF camera-to-world matrix (x right, y up, z backward) by this to get OpenCV axes."""


@dataclass(frozen=True)
class Cameras:
    """A batch of V pinhole cameras sharing one image size (see the module docstring for conventions).

    Attributes:
        K: [V,3,3] intrinsics in pixels, pixel centres at +0.5; float32 or float64.
        w2c: [V,4,4] world-to-camera rigid transforms, OpenCV axes; same dtype/device as ``K``.
        near: [V] nearest scene depth (camera z), > 0.
        far: [V] farthest scene depth, > near.
        width: image width in pixels (>= 1).
        height: image height in pixels (>= 1).

    Construction validates every value and raises :class:`CameraError` naming the first bad view.
    """

    K: torch.Tensor
    w2c: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        try:
            for name, shape in (("K", ("V", 3, 3)), ("w2c", ("V", 4, 4)), ("near", ("V",)), ("far", ("V",))):
                object.__setattr__(self, name, check_tensor(name, getattr(self, name), shape, FLOAT_DTYPES, dims))
            common_device(K=self.K, w2c=self.w2c, near=self.near, far=self.far)
            check_same_dtype(K=self.K, w2c=self.w2c, near=self.near, far=self.far)
        except ValueError as exc:
            raise CameraError(str(exc)) from None
        if int(self.width) != self.width or int(self.height) != self.height or self.width < 1 or self.height < 1:
            raise CameraError(f"image size must be positive integers, got width={self.width}, height={self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        _validate_values(self.K, self.w2c, self.near, self.far)

    # ----------------------------------------------------------------------------------------------
    # Constructors
    @classmethod
    def from_c2w(cls, K, c2w, near, far, width: int, height: int) -> "Cameras":
        """Cameras from OpenCV-axes camera-to-world matrices ``c2w`` [V,4,4] (or [V,3,4])."""
        c2w = _homogeneous(torch.as_tensor(c2w))
        return cls(K=_as_like(K, c2w), w2c=rigid_inverse(c2w), near=_as_like(near, c2w).reshape(-1),
                   far=_as_like(far, c2w).reshape(-1), width=width, height=height)

    @classmethod
    def from_opengl_c2w(cls, K, c2w_opengl, near, far, width: int, height: int) -> "Cameras":
        """Cameras from OpenGL/NeRF camera-to-world matrices (x right, y up, z backward) [V,4,4] or [V,3,4]."""
        c2w_opengl = _homogeneous(torch.as_tensor(c2w_opengl))
        flip = OPENGL_TO_OPENCV.to(c2w_opengl)
        return cls.from_c2w(K, c2w_opengl @ flip, near, far, width, height)

    @classmethod
    def from_normalized_intrinsics(cls, intrinsics, w2c, near, far, width: int, height: int) -> "Cameras":
        """Cameras from RE10K-style normalised intrinsics.

        Args:
            intrinsics: [V,4] (fx/width, fy/height, cx/width, cy/height) or [V,3,3] normalised matrices.
            w2c: [V,4,4] or [V,3,4] world-to-camera, OpenCV axes.
            near, far: [V] or scalars.
            width, height: the pixel size to scale the intrinsics to.
        """
        w2c = _homogeneous(torch.as_tensor(w2c))
        intr = _as_like(intrinsics, w2c)
        if intr.dim() == 3:
            intr = torch.stack([intr[:, 0, 0], intr[:, 1, 1], intr[:, 0, 2], intr[:, 1, 2]], dim=-1)
        K = intrinsics_matrix(intr[:, 0] * width, intr[:, 1] * height, intr[:, 2] * width, intr[:, 3] * height)
        V = w2c.shape[0]
        return cls(K=K, w2c=w2c, near=_as_like(near, w2c).expand(V).clone(), far=_as_like(far, w2c).expand(V).clone(),
                   width=width, height=height)

    # ----------------------------------------------------------------------------------------------
    # Derived quantities
    def __len__(self) -> int:
        return self.K.shape[0]

    @property
    def num_views(self) -> int:
        """Number of cameras V."""
        return self.K.shape[0]

    @property
    def device(self) -> torch.device:
        return self.K.device

    @property
    def dtype(self) -> torch.dtype:
        return self.K.dtype

    @property
    def c2w(self) -> torch.Tensor:
        """[V,4,4] camera-to-world (OpenCV axes), the rigid inverse of ``w2c``."""
        return rigid_inverse(self.w2c)

    @property
    def centers(self) -> torch.Tensor:
        """[V,3] camera centres in world space."""
        return self.c2w[:, :3, 3]

    def normalized_intrinsics(self) -> torch.Tensor:
        """[V,4] (fx/width, fy/height, cx/width, cy/height), the RE10K chunk layout."""
        K = self.K
        return torch.stack([K[:, 0, 0] / self.width, K[:, 1, 1] / self.height,
                            K[:, 0, 2] / self.width, K[:, 1, 2] / self.height], dim=-1)

    def pixel_intrinsics(self) -> torch.Tensor:
        """[V,4] (fx, fy, cx, cy) in pixels, the form the Warp kernels take."""
        K = self.K
        return torch.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]], dim=-1)

    def relative_transforms(self, neighbours: torch.Tensor) -> torch.Tensor:
        """[V,M,4,4] transforms from reference camera r to source camera ``neighbours[r, m]``.

        ``T[r, m] = w2c[s] @ c2w[r]`` maps a point in camera r's frame to camera s's frame without a
        round trip through world coordinates (so large world offsets do not cost float32 precision).
        """
        c2w = self.c2w
        return self.w2c[neighbours.long()] @ c2w[:, None]

    # ----------------------------------------------------------------------------------------------
    # Transformations (each returns new, validated Cameras)
    def to(self, device=None, dtype: torch.dtype | None = None) -> "Cameras":
        """Copy to another device and/or float dtype (no copy when nothing changes)."""
        if (device is None or torch.device(device) == self.device) and (dtype is None or dtype == self.dtype):
            return self
        move = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
        return self._derive(K=move(self.K), w2c=move(self.w2c), near=move(self.near), far=move(self.far))

    def select(self, index) -> "Cameras":
        """The cameras at ``index`` (int list, slice or tensor), as a new batch."""
        if isinstance(index, int):
            index = [index]
        return self._derive(K=self.K[index], w2c=self.w2c[index], near=self.near[index], far=self.far[index])

    @staticmethod
    def concat(batches: "list[Cameras]") -> "Cameras":
        """One batch of the cameras of ``batches`` in order (e.g. several scenes' views in one training batch).

        Raises:
            CameraError: no batches, or batches of different image size, device or dtype.
        """
        if not batches:
            raise CameraError("Cameras.concat needs at least one batch")
        first = batches[0]
        for other in batches[1:]:
            if (other.width, other.height, other.device, other.dtype) != (first.width, first.height, first.device,
                                                                          first.dtype):
                raise CameraError(f"Cameras.concat needs one image size, device and dtype: {first.width}x"
                                  f"{first.height} {first.device} {first.dtype} vs {other.width}x{other.height} "
                                  f"{other.device} {other.dtype}")
        cat = lambda name: torch.cat([getattr(b, name) for b in batches])  # noqa: E731
        return first._derive(K=cat("K"), w2c=cat("w2c"), near=cat("near"), far=cat("far"))

    def rescaled(self, width: int, height: int) -> "Cameras":
        """The same cameras for an image resampled to ``width`` x ``height`` (e.g. a 1/4 feature grid)."""
        if (width, height) == (self.width, self.height):
            return self
        if width < 1 or height < 1:
            raise CameraError(f"image size must be positive, got width={width}, height={height}")
        sx, sy = width / self.width, height / self.height
        scale = torch.tensor([sx, sy, 1.0], dtype=self.dtype, device=self.device)
        return self._derive(K=self.K * scale[None, :, None], width=int(width), height=int(height))

    def cropped(self, left: int, top: int, width: int, height: int) -> "Cameras":
        """The same cameras for the crop [left, left+width) x [top, top+height) of the image."""
        if left < 0 or top < 0 or left + width > self.width or top + height > self.height:
            raise CameraError(f"crop ({left},{top},{width},{height}) leaves the {self.width}x{self.height} image")
        K = self.K.clone()
        K[:, 0, 2] -= left
        K[:, 1, 2] -= top
        return self._derive(K=K, width=int(width), height=int(height))

    def mirrored(self) -> "Cameras":
        """The cameras of the left-right mirrored images (``image.flip(-1)``) of the mirrored world (x -> -x).

        Column u becomes ``width - u`` (cx -> width - cx, fx unchanged) and ``w2c`` becomes S w2c S with
        S = diag(-1, 1, 1, 1): a proper rotation again, so every view of the scene stays consistent (a world point
        x maps to S x, and projects where the mirrored image shows it). Training uses it to double the scenes.
        """
        S = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=self.dtype, device=self.device))
        K = self.K.clone()
        K[:, 0, 2] = self.width - self.K[:, 0, 2]
        return self._derive(K=K, w2c=S @ self.w2c @ S)

    def _derive(self, **changes) -> "Cameras":
        """A copy with ``changes`` applied, skipping validation: only for transformations that keep valid
        cameras valid (device/dtype moves, view selection, rescaling, cropping, mirroring). Saves a host sync per op."""
        new = object.__new__(Cameras)
        for field in fields(self):
            object.__setattr__(new, field.name, changes.get(field.name, getattr(self, field.name)))
        return new

    def memoized(self, key, compute):
        """``compute()`` evaluated once per ``key`` for these cameras (e.g. kernel-ready intrinsics and relative
        transforms that every op call would otherwise rebuild with a dozen small device ops).

        The cache lives on this object only (transformations return new objects with an empty one) and is
        dropped when ``K`` or ``w2c`` are modified in place.
        """
        versions = (self.K._version, self.w2c._version)
        cache = self.__dict__.setdefault("_memo", {})
        if cache.get("versions") != versions:
            cache.clear()
            cache["versions"] = versions
        if key not in cache:
            while len(cache) > MEMO_ENTRIES:  # "versions" plus at most MEMO_ENTRIES values, oldest dropped first
                del cache[next(k for k in cache if k != "versions")]
            cache[key] = compute()
        return cache[key]

    def memo_values(self) -> tuple:
        """The values :meth:`memoized` holds now. Code that captures a CUDA graph over ops on these cameras holds
        them for the graph's life: the graph reads their memory, and the cache may drop them."""
        return tuple(value for key, value in self.__dict__.get("_memo", {}).items() if key != "versions")

    def with_depth_range(self, near, far) -> "Cameras":
        """The same cameras with new near/far bounds ([V] or scalars)."""
        V = self.num_views
        return replace(self, near=_as_like(near, self.K).expand(V).clone(), far=_as_like(far, self.K).expand(V).clone())


# --------------------------------------------------------------------------------------------------
# Free functions on matrices
def intrinsics_matrix(fx, fy, cx, cy) -> torch.Tensor:
    """[V,3,3] pinhole matrices from [V] focal lengths and principal points (pixels)."""
    K = torch.zeros(fx.shape[0], 3, 3, dtype=fx.dtype, device=fx.device)
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = fx, fy, cx, cy, 1.0
    return K


def rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms [...,4,4] as [Rᵀ, −Rᵀt] (exact for rotations, no general inverse)."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def _homogeneous(T: torch.Tensor) -> torch.Tensor:
    if T.dim() == 3 and T.shape[-2:] == (3, 4):
        bottom = torch.zeros(T.shape[0], 1, 4, dtype=T.dtype, device=T.device)
        bottom[..., 3] = 1.0
        return torch.cat([T, bottom], dim=-2)
    if T.dim() != 3 or T.shape[-2:] != (4, 4):
        raise CameraError(f"pose matrices must be [V,4,4] or [V,3,4], got {tuple(T.shape)}")
    return T


def _as_like(x, ref: torch.Tensor) -> torch.Tensor:
    dtype = ref.dtype if ref.dtype in FLOAT_DTYPES else torch.float64
    return torch.as_tensor(x).to(device=ref.device, dtype=dtype)


def _validate_values(K: torch.Tensor, w2c: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> None:
    """Raise CameraError naming the first view with a bad value. Runs on a float64 CPU copy."""
    K, w2c, near, far = (t.detach().to("cpu", torch.float64) for t in (K, w2c, near, far))
    for v in range(K.shape[0]):
        where = f"view {v}"
        for name, t in (("K", K[v]), ("w2c", w2c[v]), ("near", near[v]), ("far", far[v])):
            if not bool(torch.isfinite(t).all()):
                raise CameraError(f"{where}: {name} holds NaN or Inf")
        fx, fy = float(K[v, 0, 0]), float(K[v, 1, 1])
        if fx <= 0 or fy <= 0:
            raise CameraError(f"{where}: focal lengths must be > 0, got fx={fx:g}, fy={fy:g}")
        if abs(float(K[v, 0, 1])) > SKEW_TOLERANCE * fx or not torch.allclose(
            K[v, 1:, :1], torch.zeros(2, 1, dtype=torch.float64)
        ) or not torch.allclose(K[v, 2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)):
            raise CameraError(f"{where}: K must be [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K[v].tolist()}")
        R = w2c[v, :3, :3]
        err = float((R @ R.T - torch.eye(3, dtype=torch.float64)).abs().max())
        if err > ROTATION_TOLERANCE or float(torch.linalg.det(R)) <= 0:
            raise CameraError(f"{where}: w2c rotation is not a proper orthonormal rotation (|RRᵀ−I|={err:.2e})")
        if not torch.allclose(w2c[v, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)):
            raise CameraError(f"{where}: w2c bottom row must be [0,0,0,1], got {w2c[v, 3].tolist()}")
        n, f = float(near[v]), float(far[v])
        if not 0 < n < f:
            raise CameraError(f"{where}: need 0 < near < far, got near={n:g}, far={f:g}")
