"""Reader of NeuS / IDR ``cameras_sphere.npz`` scenes (DTU and BlendedMVS as NeuS ships them).

For the i-th sorted image, ``world_mat_i`` holds P = K [R|t] (world -> pixels, rows 0-2) and
``scale_mat_i`` maps the normalised frame (object inside the unit sphere) to that world. The cameras are
P @ scale_mat decomposed by RQ into K and [R|t], i.e. expressed in the normalised frame, as NeuS does.
The tiny skew of the decomposed K is dropped. near/far follow the ``unit_sphere`` rule:
min |c| - 1 and max |c| + 1 over the camera centres c.
"""

from __future__ import annotations

import pathlib
import zipfile

import numpy as np

from ..errors import DataError
from .scene import (EncodedImages, Scene, cameras_from_arrays, check_pose_values, list_images, read_image_size,
                    require_file)

MIN_NEAR_FRACTION = 1e-2
"""When a camera sits inside the unit sphere, near is clamped to this fraction of far."""


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 projection P ~ K [R|t] into K (3x3, K[2,2] = 1, positive focals) and w2c (4x4).

    Uses the RQ decomposition of P[:, :3]; the overall sign of P is chosen so that R is a proper rotation.
    """
    M = P[:, :3]
    flip = np.flipud(np.eye(3))
    Q, R = np.linalg.qr((flip @ M).T)
    K, rotation = flip @ R.T @ flip, flip @ Q.T
    signs = np.diag(np.sign(np.diag(K)))
    K, rotation = K @ signs, signs @ rotation
    if np.linalg.det(rotation) < 0:
        K, rotation = -K, -rotation
    centre = -np.linalg.solve(M, P[:, 3])
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ centre
    return K / K[2, 2], w2c


def load_neus(file, image_folder: str | None = None) -> Scene:
    """Scene from ``cameras_sphere.npz`` with images in ``images/`` (or ``image/``, NeuS's default).

    Raises:
        DataError: unreadable file, missing matrices, count mismatch, non-finite or degenerate
            matrices, invalid cameras (naming the file and frame).
    """
    file = pathlib.Path(file)
    folder = file.parent
    if image_folder is None:
        image_folder = "images" if (folder / "images").is_dir() else "image"
    names = list_images(folder / image_folder, natural=True)
    matrices = _read_matrices(file, len(names))
    Ks, w2cs = [], []
    for frame, (world_mat, scale_mat) in enumerate(matrices):
        check_pose_values(file, frame, f"world_mat_{frame}/scale_mat_{frame}", [world_mat, scale_mat])
        P = (world_mat @ scale_mat)[:3, :4]
        if abs(np.linalg.det(P[:, :3])) < 1e-300:
            raise DataError(f"{file}: frame {frame}: world_mat_{frame} @ scale_mat_{frame} is singular")
        K, w2c = decompose_projection(P)
        Ks.append(K)
        w2cs.append(w2c)
    K, w2c = np.stack(Ks), np.stack(w2cs)
    c2w = np.linalg.inv(w2c)
    distances = np.linalg.norm(c2w[:, :3, 3], axis=1)
    far = float(distances.max()) + 1.0
    near = max(float(distances.min()) - 1.0, MIN_NEAR_FRACTION * far)
    width, height = read_image_size(folder / image_folder / names[0], f"{file}: frame 0")
    cameras = cameras_from_arrays(file, K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], c2w, near, far, width, height)
    frame_names = [f"{image_folder}/{n}" for n in names]
    return Scene(
        images=EncodedImages([folder / n for n in frame_names], width, height),
        cameras=cameras,
        key=folder.name,
        source=f"neus:{file}",
        frame_names=frame_names,
    )


def _read_matrices(file: pathlib.Path, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    require_file(file)
    try:
        with np.load(file, allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k], dtype=np.float64) for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise DataError(f"{file}: not a readable .npz archive: {exc}") from None
    n_world = sum(1 for k in arrays if k.startswith("world_mat_") and not k.startswith("world_mat_inv"))
    if n_world != count:
        raise DataError(f"{file}: {n_world} world_mat_i matrices but {count} images")
    matrices = []
    for frame in range(count):
        world, scale = arrays.get(f"world_mat_{frame}"), arrays.get(f"scale_mat_{frame}", np.eye(4))
        if world is None:
            raise DataError(f"{file}: frame {frame}: world_mat_{frame} is missing")
        if world.shape != (4, 4) or scale.shape != (4, 4):
            raise DataError(f"{file}: frame {frame}: world_mat/scale_mat must be 4x4")
        matrices.append((world, scale))
    return matrices

