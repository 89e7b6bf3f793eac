"""Reader of NeRF / instant-ngp / nerfstudio ``transforms*.json`` scenes.

``transform_matrix`` is camera-to-world in OpenGL camera axes (x right, y up, z backward). Intrinsics
``w``, ``h``, ``fl_x``, ``fl_y``, ``cx``, ``cy`` are pixels, at the top level and/or per frame (a frame's
own value wins). Some writers give a 3x3 pinhole matrix ``K`` (pixels, ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``)
instead, again at the top level and/or per frame; it stands for the ``fl_x``/``fl_y``/``cx``/``cy`` keys its
level lacks. Blender-style files give only ``camera_angle_x`` (and maybe ``camera_angle_y``); the
image size is then read from the first image header and the principal point is the image centre.
Distortion terms are ignored (pinhole). ``file_path`` is relative to the json; a path without an
extension gets ``.png`` (Blender scenes). near/far come from the json's ``near``/``far`` when present,
else from :func:`~codecsplat_warp.data.scene.bounds_from_focus`.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np

from ..cameras import OPENGL_TO_OPENCV
from ..errors import DataError
from .scene import (EncodedImages, Scene, bounds_from_focus, cameras_from_arrays, check_pose_values,
                    read_image_size, single_image_size)
from .scene_json import read_json


def load_nerf(file, near: float | None = None, far: float | None = None) -> Scene:
    """Scene from a ``transforms*.json``; ``near``/``far`` override the file's (or the heuristic) bounds.

    Raises:
        DataError: bad JSON, missing keys or images, non-finite matrices, mixed sizes, invalid cameras
            (naming the file and the frame).
    """
    file = pathlib.Path(file)
    data = read_json(file)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{file}: 'frames' must be a non-empty list")
    folder = file.parent.resolve()
    paths = [_frame_path(file, i, f) for i, f in enumerate(frames)]
    shared = _with_matrix_keys(file, "top level", data)
    intrinsics = [_frame_intrinsics(file, i, shared, f, paths[i]) for i, f in enumerate(frames)]
    width, height = single_image_size(file, [(w, h) for w, h, *_ in intrinsics])
    c2w = np.stack([_frame_matrix(file, i, f) for i, f in enumerate(frames)]) @ OPENGL_TO_OPENCV.numpy()
    near, far = _depth_range(file, data, c2w, near, far)
    fx, fy, cx, cy = (np.array([k[j] for k in intrinsics]) for j in range(2, 6))
    cameras = cameras_from_arrays(file, fx, fy, cx, cy, c2w, near, far, width, height)
    return Scene(
        images=EncodedImages(paths, width, height),
        cameras=cameras,
        key=folder.name,
        source=f"nerf:{file}",
        frame_names=[p.relative_to(folder).as_posix() if p.is_relative_to(folder) else str(p) for p in paths],
    )


def _frame_path(file: pathlib.Path, index: int, frame) -> pathlib.Path:
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
        raise DataError(f"{file}: frame {index} lacks a 'file_path' string")
    path = (file.parent / frame["file_path"]).resolve()
    if not path.suffix and not path.exists():
        path = path.with_name(path.name + ".png")
    return path


def _frame_matrix(file: pathlib.Path, index: int, frame: dict) -> np.ndarray:
    try:
        matrix = np.array(frame["transform_matrix"], dtype=np.float64)
    except KeyError:
        raise DataError(f"{file}: frame {index} ({frame['file_path']}) lacks 'transform_matrix'") from None
    except (TypeError, ValueError):
        raise DataError(f"{file}: frame {index} ({frame['file_path']}): transform_matrix must be numbers") from None
    if matrix.shape == (3, 4):
        matrix = np.concatenate([matrix, [[0.0, 0.0, 0.0, 1.0]]])
    if matrix.shape != (4, 4):
        raise DataError(f"{file}: frame {index} ({frame['file_path']}): transform_matrix must be 4x4, got {matrix.shape}")
    check_pose_values(file, index, f"({frame['file_path']}) transform_matrix", matrix)
    return matrix


def _frame_intrinsics(file: pathlib.Path, index: int, top: dict, frame: dict, path: pathlib.Path) -> tuple:
    """(w, h, fx, fy, cx, cy) of one frame: its own keys (``K`` filling in) first, then the top-level ones.

    ``top`` is the top-level object already passed through :func:`_with_matrix_keys`.
    """
    where = f"frame {index} ({frame['file_path']})"
    own = _with_matrix_keys(file, where, frame)
    get = lambda key: own.get(key, top.get(key))  # noqa: E731
    width, height = get("w"), get("h")
    if width is None or height is None:
        width, height = read_image_size(path, f"{file}: frame {index} (no 'w'/'h' given)")
    fx, fy = get("fl_x"), get("fl_y")
    angle_x, angle_y = get("camera_angle_x"), get("camera_angle_y")
    if fx is None and angle_x is not None:
        fx = 0.5 * width / math.tan(0.5 * angle_x)
    if fy is None:
        fy = 0.5 * height / math.tan(0.5 * angle_y) if angle_y is not None else fx
    values = (width, height, fx, fy, get("cx") if get("cx") is not None else width / 2,
              get("cy") if get("cy") is not None else height / 2)
    if any(v is None for v in values):
        raise DataError(f"{file}: {where}: no focal length (fl_x, K or camera_angle_x)")
    check_pose_values(file, index, f"({frame['file_path']}) intrinsics", values)
    return values


def _with_matrix_keys(file: pathlib.Path, where: str, entry: dict) -> dict:
    """``entry`` (top level or one frame) with ``fl_x``, ``fl_y``, ``cx``, ``cy`` taken from its 3x3 ``K``
    where it lacks them (its own keys win); ``entry`` itself when it has no ``K``."""
    if "K" not in entry:
        return entry
    return {**_pinhole_keys(file, where, entry["K"]), **entry}


def _pinhole_keys(file: pathlib.Path, where: str, matrix) -> dict[str, float]:
    """``fl_x``, ``fl_y``, ``cx``, ``cy`` in pixels from a 3x3 pinhole matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.

    Raises:
        DataError: not a 3x3 matrix of numbers, NaN or Inf, a skew term or a last row other than [0, 0, 1]
            (naming the file and ``where``).
    """
    try:
        K = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{file}: {where}: 'K' must be a 3x3 matrix of numbers") from None
    if K.shape != (3, 3):
        raise DataError(f"{file}: {where}: 'K' must be 3x3, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise DataError(f"{file}: {where}: 'K' holds NaN or Inf")
    if K[0, 1] != 0 or K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise DataError(f"{file}: {where}: 'K' must be a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "
                        f"got {K.tolist()}")
    return {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}


def _depth_range(file: pathlib.Path, data: dict, c2w: np.ndarray, near, far) -> tuple[float, float]:
    if near is None or far is None:
        guess_near, guess_far = bounds_from_focus(c2w)
        near = data.get("near", guess_near) if near is None else near
        far = data.get("far", guess_far) if far is None else far
    if not all(isinstance(v, (int, float)) for v in (near, far)):
        raise DataError(f"{file}: 'near'/'far' must be numbers, got {near!r}, {far!r}")
    return float(near), float(far)
