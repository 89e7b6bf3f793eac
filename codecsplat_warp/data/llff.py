"""Reader of LLFF ``poses_bounds.npy`` scenes.

The file is float [N,17]: per row a row-major 3x5 matrix then two depth bounds. Matrix columns 0-2 are the
camera axes in world coordinates in the order [down, right, backward], column 3 the camera centre and
column 4 ``[H, W, focal]`` in pixels. Row k belongs to the k-th file of ``sorted(os.listdir(images))``
(plain string order, as LLFF loaders sort). The principal point is the image centre and each row's own
focal is used (some captures calibrate one camera per image). near/far = 0.9 x min / 1.1 x max of the
bounds (the ``llff_bounds`` rule).
"""

from __future__ import annotations

import pathlib

import numpy as np

from ..errors import DataError
from .scene import EncodedImages, Scene, cameras_from_arrays, check_pose_values, list_images, require_file

NEAR_FACTOR = 0.9
FAR_FACTOR = 1.1


def load_llff(file, image_folder: str = "images") -> Scene:
    """Scene from ``poses_bounds.npy`` with images in ``<its folder>/<image_folder>``.

    Raises:
        DataError: unreadable file, wrong shape, count mismatch with the images, non-finite rows, mixed
            image sizes or invalid cameras (naming the file and frame).
    """
    file = pathlib.Path(file)
    rows = _read_rows(file)
    folder = file.parent
    names = list_images(folder / image_folder, natural=False)
    if len(names) != len(rows):
        raise DataError(f"{file}: {len(rows)} pose rows but {len(names)} images in {folder / image_folder}")
    frame_names = [f"{image_folder}/{n}" for n in names]
    for frame, row in enumerate(rows):
        check_pose_values(file, frame, f"row ({frame_names[frame]})", row)
    matrices = rows[:, :15].reshape(-1, 3, 5)
    heights, widths, focals = matrices[:, 0, 4], matrices[:, 1, 4], matrices[:, 2, 4]
    width, height = _single_size(file, widths, heights)
    down, right, backward, centre = (matrices[:, :, i] for i in range(4))
    c2w = np.stack([right, down, -backward, centre], axis=-1)
    bounds = rows[:, 15:17]
    near, far = NEAR_FACTOR * float(bounds.min()), FAR_FACTOR * float(bounds.max())
    cameras = cameras_from_arrays(file, focals, focals, widths / 2, heights / 2, c2w, near, far, width, height)
    return Scene(
        images=EncodedImages([folder / n for n in frame_names], width, height),
        cameras=cameras,
        key=folder.name,
        source=f"llff:{file}",
        frame_names=frame_names,
        metadata={"bounds": bounds.copy()},
    )


def _read_rows(file: pathlib.Path) -> np.ndarray:
    require_file(file)
    try:
        rows = np.load(file, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DataError(f"{file}: not a readable .npy array: {exc}") from None
    if rows.ndim != 2 or rows.shape[1] != 17:
        raise DataError(f"{file}: expected an [N,17] LLFF array, got shape {rows.shape}")
    return rows.astype(np.float64)


def _single_size(file: pathlib.Path, widths: np.ndarray, heights: np.ndarray) -> tuple[int, int]:
    for frame in range(len(widths)):
        if widths[frame] != widths[0] or heights[frame] != heights[0]:
            raise DataError(f"{file}: frame {frame} is {widths[frame]:g}x{heights[frame]:g}, frame 0 is "
                            f"{widths[0]:g}x{heights[0]:g}; a scene must have one image size")
    if widths[0] != round(widths[0]) or heights[0] != round(heights[0]):
        raise DataError(f"{file}: frame 0: image size {widths[0]}x{heights[0]} is not whole pixels")
    return int(widths[0]), int(heights[0])
