"""Reader of Middlebury multi-view stereo ``*_par.txt`` camera files.

First line: the number of views; then one line per view:
``name k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3`` with
x ~ K (R X + t) (OpenCV axes, origin at the top-left corner). Images are looked up as ``images/<name>``
(or ``<name>`` next to the file). The format has no depth bounds: near/far come from the arguments or from
:func:`~codecsplat_warp.data.scene.bounds_from_focus`.
"""

from __future__ import annotations

import pathlib

import numpy as np

from ..errors import DataError
from .scene import (EncodedImages, Scene, cameras_from_arrays, check_pose_values, depth_range, read_image_size,
                    require_file)

VALUES_PER_VIEW = 21


def load_middlebury(file, near: float | None = None, far: float | None = None) -> Scene:
    """Scene from a Middlebury ``*_par.txt``; ``near``/``far`` override the heuristic bounds.

    Raises:
        DataError: bad counts, unparsable or non-finite numbers, invalid cameras (naming file and frame).
    """
    file = pathlib.Path(file)
    names, values = _parse(file)
    folder = file.parent
    image_folder = "images/" if (folder / "images").is_dir() else ""
    frame_names = [image_folder + n for n in names]
    K = values[:, :9].reshape(-1, 3, 3)
    w2c = np.tile(np.eye(4), (len(names), 1, 1))
    w2c[:, :3, :3] = values[:, 9:18].reshape(-1, 3, 3)
    w2c[:, :3, 3] = values[:, 18:21]
    c2w = np.linalg.inv(w2c)
    width, height = read_image_size(folder / frame_names[0], f"{file}: frame 0")
    near, far = depth_range(c2w, near, far)
    cameras = cameras_from_arrays(file, K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], c2w, near, far, width, height)
    return Scene(
        images=EncodedImages([folder / n for n in frame_names], width, height),
        cameras=cameras,
        key=folder.name,
        source=f"middlebury:{file}",
        frame_names=frame_names,
    )


def _parse(file: pathlib.Path) -> tuple[list[str], np.ndarray]:
    lines = [line.split() for line in require_file(file).read_text().splitlines() if line.strip()]
    if not lines or len(lines[0]) != 1 or not lines[0][0].isdigit():
        raise DataError(f"{file}: first line must be the number of views")
    count = int(lines[0][0])
    if len(lines) - 1 != count:
        raise DataError(f"{file}: header says {count} views but {len(lines) - 1} view lines follow")
    names, rows = [], []
    for frame, fields in enumerate(lines[1:]):
        if len(fields) != 1 + VALUES_PER_VIEW:
            raise DataError(f"{file}: frame {frame}: expected a name and {VALUES_PER_VIEW} numbers, got {len(fields)} fields")
        try:
            row = np.array([float(x) for x in fields[1:]])
        except ValueError:
            raise DataError(f"{file}: frame {frame} ({fields[0]}): not a number in {fields[1:]}") from None
        check_pose_values(file, frame, f"({fields[0]}) K/R/t", row)
        names.append(fields[0])
        rows.append(row)
    return names, np.stack(rows)
