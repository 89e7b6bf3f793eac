"""Reader of ``cameras.json`` in format ``codecsplat-scene-v1`` (OpenCV c2w, pixels at stored size).

Layout (see ``../shared/data/scenes/README.md``)::

    {"format": "codecsplat-scene-v1",
     "frames": [{"file": "images/x.jpg", "w": 512, "h": 384, "fx":, "fy":, "cx":, "cy":, "c2w": 4x4}, ...],
     "near": float, "far": float, "source": {...}}
"""

from __future__ import annotations

import json
import pathlib

import numpy as np

from ..errors import DataError
from .scene import EncodedImages, Scene, cameras_from_arrays, check_pose_values, require_file, single_image_size

FORMAT_NAME = "codecsplat-scene-v1"
FRAME_KEYS = ("file", "w", "h", "fx", "fy", "cx", "cy", "c2w")


def read_json(file: pathlib.Path) -> dict:
    """Parsed JSON object of ``file``; DataError naming it when missing, malformed or not an object."""
    require_file(file)
    try:
        with open(file, encoding="utf-8") as handle:
            data = json.load(handle)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{file}: not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise DataError(f"{file}: expected a JSON object at the top level, got {type(data).__name__}")
    return data


def is_scene_json(file: pathlib.Path) -> bool:
    """Whether ``file`` is a readable JSON object declaring ``format: codecsplat-scene-v1``."""
    try:
        return read_json(file).get("format") == FORMAT_NAME
    except DataError:
        return False


def load_scene_json(file) -> Scene:
    """Scene from a ``cameras.json`` file; frame files are relative to its folder.

    Raises:
        DataError: wrong format tag, missing keys, non-finite values, mixed image sizes or invalid
            cameras, naming the file and the frame.
    """
    file = pathlib.Path(file)
    data = read_json(file)
    if data.get("format") != FORMAT_NAME:
        raise DataError(f"{file}: format is {data.get('format')!r}, expected {FORMAT_NAME!r}")
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{file}: 'frames' must be a non-empty list")
    for key in ("near", "far"):
        if not isinstance(data.get(key), (int, float)):
            raise DataError(f"{file}: '{key}' must be a number, got {data.get(key)!r}")
    for index, frame in enumerate(frames):
        _check_frame(file, index, frame)
    width, height = single_image_size(file, [(f["w"], f["h"]) for f in frames])
    column = lambda key: np.array([f[key] for f in frames], dtype=np.float64)  # noqa: E731
    c2w = np.array([f["c2w"] for f in frames], dtype=np.float64)
    cameras = cameras_from_arrays(
        file, column("fx"), column("fy"), column("cx"), column("cy"), c2w, data["near"], data["far"], width, height
    )
    folder = file.parent
    names = [f["file"] for f in frames]
    return Scene(
        images=EncodedImages([folder / n for n in names], width, height),
        cameras=cameras,
        key=folder.name,
        source=f"scene-json:{file}",
        frame_names=names,
        metadata={"source": data.get("source", {})},
    )


def _check_frame(file: pathlib.Path, index: int, frame) -> None:
    if not isinstance(frame, dict):
        raise DataError(f"{file}: frame {index} must be an object, got {type(frame).__name__}")
    missing = [k for k in FRAME_KEYS if k not in frame]
    if missing:
        raise DataError(f"{file}: frame {index} lacks {', '.join(missing)}")
    if not isinstance(frame["file"], str):
        raise DataError(f"{file}: frame {index}: 'file' must be a string")
    try:
        c2w = np.array(frame["c2w"], dtype=np.float64)
        numbers = np.array([frame[k] for k in ("w", "h", "fx", "fy", "cx", "cy")], dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{file}: frame {index} ({frame['file']}): w, h, fx, fy, cx, cy, c2w must be numbers") from None
    if c2w.shape != (4, 4):
        raise DataError(f"{file}: frame {index} ({frame['file']}): c2w must be 4x4, got shape {c2w.shape}")
    check_pose_values(file, index, f"({frame['file']}) c2w", c2w)
    check_pose_values(file, index, f"({frame['file']}) intrinsics", numbers)
