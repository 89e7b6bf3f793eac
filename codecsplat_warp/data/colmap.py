"""Reader of COLMAP sparse models, text (``cameras.txt``, ``images.txt``, ``points3D.txt``) and binary (``*.bin``).

Images: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` (world-to-camera quaternion and translation,
OpenCV axes) then one line of 2D points ``X Y POINT3D_ID ...``. Cameras: ``CAMERA_ID MODEL WIDTH HEIGHT
PARAMS``; COLMAP's pixel centres are at +0.5 like ours. Perspective models are read as pinhole (their
distortion terms are ignored and kept in ``Scene.metadata["distortion"]``); fisheye models are rejected.
Frames are ordered by image name (natural order). near/far follow the ``llff_bounds`` rule on the
points each image observes (0.1 / 99.9 depth percentiles, then 0.9 x min / 1.1 x max); a model without
points falls back to :func:`~codecsplat_warp.data.scene.bounds_from_focus`.
"""

from __future__ import annotations

import pathlib
import struct
from dataclasses import dataclass

import numpy as np

from ..errors import DataError
from .scene import EncodedImages, Scene, bounds_from_focus, cameras_from_arrays, check_pose_values, natural_key

CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
}
"""COLMAP model id -> (name, number of parameters)."""

MODEL_IDS = {name: (model_id, count) for model_id, (name, count) in CAMERA_MODELS.items()}
SINGLE_FOCAL_MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
"""Models whose parameters start f, cx, cy; the other perspective models start fx, fy, cx, cy."""
PERSPECTIVE_MODELS = SINGLE_FOCAL_MODELS + ("PINHOLE", "OPENCV", "FULL_OPENCV", "FOV")
NEAR_PERCENTILE, FAR_PERCENTILE = 0.1, 99.9
NEAR_FACTOR, FAR_FACTOR = 0.9, 1.1


@dataclass
class ColmapCamera:
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    point3d_ids: np.ndarray


@dataclass
class ColmapModel:
    """A parsed sparse model: cameras by id, images (file order), points by id ([3] float64 each)."""

    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points: dict[int, np.ndarray]


def is_colmap_model(folder: pathlib.Path) -> bool:
    """Whether ``folder`` holds a text or binary COLMAP model."""
    return all((folder / f"{n}.txt").is_file() for n in ("cameras", "images")) or all(
        (folder / f"{n}.bin").is_file() for n in ("cameras", "images"))


def read_model(folder) -> ColmapModel:
    """Parse the model in ``folder`` (text preferred when both exist; points3D optional).

    Raises:
        DataError: missing or malformed files, naming the file and the line / record.
    """
    folder = pathlib.Path(folder)
    if all((folder / f"{n}.txt").is_file() for n in ("cameras", "images")):
        points_file = folder / "points3D.txt"
        return ColmapModel(_read_cameras_text(folder / "cameras.txt"), _read_images_text(folder / "images.txt"),
                           _read_points_text(points_file) if points_file.is_file() else {})
    if all((folder / f"{n}.bin").is_file() for n in ("cameras", "images")):
        points_file = folder / "points3D.bin"
        return ColmapModel(_read_cameras_binary(folder / "cameras.bin"), _read_images_binary(folder / "images.bin"),
                           _read_points_binary(points_file) if points_file.is_file() else {})
    raise DataError(f"{folder}: no COLMAP model (cameras.txt + images.txt or cameras.bin + images.bin)")


def load_colmap(folder, image_folder=None) -> Scene:
    """Scene from a COLMAP model folder (e.g. ``scene/sparse/0``); images in ``image_folder``.

    ``image_folder`` defaults to the first ``images/`` folder found in the model folder or up to three
    levels above it; the scene key is that folder's parent name.

    Raises:
        DataError: see :func:`read_model`; also unknown camera ids, fisheye models, mixed image sizes,
            non-finite poses and invalid cameras, naming the file and frame.
    """
    folder = pathlib.Path(folder)
    model = read_model(folder)
    image_dir = _find_image_folder(folder) if image_folder is None else pathlib.Path(image_folder)
    images = sorted(model.images, key=lambda im: natural_key(im.name))
    if not images:
        raise DataError(f"{folder}: the model has no image")
    intrinsics, sizes, distortion = [], [], []
    for frame, image in enumerate(images):
        camera = model.cameras.get(image.camera_id)
        if camera is None:
            raise DataError(f"{folder}: frame {frame} ({image.name}) uses camera {image.camera_id}, which is not defined")
        intrinsics.append(_pinhole(folder, frame, image.name, camera))
        sizes.append((camera.width, camera.height))
        distortion.append(camera.params[3 if camera.model in SINGLE_FOCAL_MODELS else 4:].tolist())
    for frame, (w, h) in enumerate(sizes):
        if (w, h) != sizes[0]:
            raise DataError(f"{folder}: frame {frame} ({images[frame].name}) is {w}x{h}, frame 0 is "
                            f"{sizes[0][0]}x{sizes[0][1]}; a scene must have one image size")
    w2c = np.stack([_w2c(folder, frame, image) for frame, image in enumerate(images)])
    near, far = _depth_range(model, images, w2c)
    fx, fy, cx, cy = np.array(intrinsics).T
    width, height = sizes[0]
    cameras = cameras_from_arrays(folder, fx, fy, cx, cy, np.linalg.inv(w2c), near, far, width, height)
    return Scene(
        images=EncodedImages([image_dir / im.name for im in images], width, height),
        cameras=cameras,
        key=image_dir.parent.name,
        source=f"colmap:{folder}",
        frame_names=[_relative_name(image_dir, im.name) for im in images],
        metadata={"distortion": distortion},
    )


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """3x3 rotation of the quaternion (qw, qx, qy, qz) (normalised first)."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


# --------------------------------------------------------------------------------------------------
def _find_image_folder(model_folder: pathlib.Path) -> pathlib.Path:
    for candidate in [model_folder, *list(model_folder.resolve().parents)[:3]]:
        if (candidate / "images").is_dir():
            return candidate / "images"
    raise DataError(f"{model_folder}: no images/ folder in the model folder or up to three levels above it")


def _relative_name(image_dir: pathlib.Path, name: str) -> str:
    return f"{image_dir.name}/{name}"


def _pinhole(folder: pathlib.Path, frame: int, name: str, camera: ColmapCamera) -> tuple[float, float, float, float]:
    if camera.model not in PERSPECTIVE_MODELS:
        raise DataError(f"{folder}: frame {frame} ({name}): camera model {camera.model} is not supported "
                        f"(perspective models only: {', '.join(PERSPECTIVE_MODELS)})")
    p = camera.params
    check_pose_values(folder, frame, f"({name}) camera parameters", p)
    if camera.model in SINGLE_FOCAL_MODELS:
        return float(p[0]), float(p[0]), float(p[1]), float(p[2])
    return float(p[0]), float(p[1]), float(p[2]), float(p[3])


def _w2c(folder: pathlib.Path, frame: int, image: ColmapImage) -> np.ndarray:
    check_pose_values(folder, frame, f"({image.name}) qvec/tvec", np.concatenate([image.qvec, image.tvec]))
    if np.linalg.norm(image.qvec) < 1e-12:
        raise DataError(f"{folder}: frame {frame} ({image.name}): zero quaternion")
    w2c = np.eye(4)
    w2c[:3, :3] = quaternion_to_rotation(image.qvec)
    w2c[:3, 3] = image.tvec
    return w2c


def _depth_range(model: ColmapModel, images: list[ColmapImage], w2c: np.ndarray) -> tuple[float, float]:
    if not model.points:
        return bounds_from_focus(np.linalg.inv(w2c))
    all_ids = np.array(list(model.points.keys()))
    all_xyz = np.stack(list(model.points.values()))
    lows, highs = [], []
    for image, pose in zip(images, w2c):
        seen = image.point3d_ids[np.isin(image.point3d_ids, all_ids)]
        xyz = np.stack([model.points[int(i)] for i in seen]) if len(seen) else all_xyz
        depth = xyz @ pose[2, :3] + pose[2, 3]
        depth = depth[depth > 0]
        if len(depth):
            lows.append(np.percentile(depth, NEAR_PERCENTILE))
            highs.append(np.percentile(depth, FAR_PERCENTILE))
    if not lows:
        return bounds_from_focus(np.linalg.inv(w2c))
    return NEAR_FACTOR * float(min(lows)), FAR_FACTOR * float(max(highs))


# --------------------------------------------------------------------------------------------------
# Text files
def _data_lines(file: pathlib.Path) -> list[tuple[int, str]]:
    """(line number, text) of every line that is not a comment; blank lines kept (images.txt needs them)."""
    try:
        text = file.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{file}: cannot read: {exc}") from None
    return [(n + 1, line.strip()) for n, line in enumerate(text.splitlines()) if not line.lstrip().startswith("#")]


def _numbers(file: pathlib.Path, line_no: int, fields: list[str], kind=float) -> list:
    try:
        return [kind(x) for x in fields]
    except ValueError:
        raise DataError(f"{file}: line {line_no}: expected numbers, got {' '.join(fields)!r}") from None


def _read_cameras_text(file: pathlib.Path) -> dict[int, ColmapCamera]:
    cameras = {}
    for line_no, line in _data_lines(file):
        if not line:
            continue
        fields = line.split()
        if len(fields) < 4 or fields[1] not in MODEL_IDS:
            raise DataError(f"{file}: line {line_no}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS', got {line!r}")
        count = MODEL_IDS[fields[1]][1]
        if len(fields) != 4 + count:
            raise DataError(f"{file}: line {line_no}: model {fields[1]} needs {count} parameters, got {len(fields) - 4}")
        camera_id, width, height = _numbers(file, line_no, [fields[0], fields[2], fields[3]], int)
        cameras[camera_id] = ColmapCamera(fields[1], width, height, np.array(_numbers(file, line_no, fields[4:])))
    return cameras


def _read_images_text(file: pathlib.Path) -> list[ColmapImage]:
    lines = _data_lines(file)
    images, cursor = [], 0
    while cursor < len(lines):
        line_no, line = lines[cursor]
        cursor += 1
        if not line:
            continue
        fields = line.split()
        if len(fields) < 10:
            raise DataError(f"{file}: line {line_no}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {line!r}")
        values = _numbers(file, line_no, fields[1:8])
        image_id, camera_id = _numbers(file, line_no, [fields[0], fields[8]], int)
        points_line = lines[cursor][1].split() if cursor < len(lines) else []
        cursor += 1
        if len(points_line) % 3:
            raise DataError(f"{file}: line {line_no + 1}: POINTS2D must be triples X Y POINT3D_ID")
        ids = np.array(_numbers(file, line_no + 1, points_line[2::3], int), dtype=np.int64)
        images.append(ColmapImage(image_id, np.array(values[:4]), np.array(values[4:7]), camera_id,
                                  " ".join(fields[9:]), ids[ids >= 0]))
    return images


def _read_points_text(file: pathlib.Path) -> dict[int, np.ndarray]:
    points = {}
    for line_no, line in _data_lines(file):
        if not line:
            continue
        fields = line.split()
        if len(fields) < 8:
            raise DataError(f"{file}: line {line_no}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK[]', got {line!r}")
        points[int(_numbers(file, line_no, fields[:1], int)[0])] = np.array(_numbers(file, line_no, fields[1:4]))
    return points


# --------------------------------------------------------------------------------------------------
# Binary files (little-endian, as COLMAP writes them)
class _BinaryReader:
    def __init__(self, file: pathlib.Path):
        self.file = file
        try:
            self.data = file.read_bytes()
        except OSError as exc:
            raise DataError(f"{file}: cannot read: {exc}") from None
        self.offset = 0

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.offset + size > len(self.data):
            raise DataError(f"{self.file}: truncated at byte {self.offset} (needs {size} more bytes)")
        values = struct.unpack_from("<" + fmt, self.data, self.offset)
        self.offset += size
        return values

    def read_name(self) -> str:
        end = self.data.find(b"\x00", self.offset)
        if end < 0:
            raise DataError(f"{self.file}: truncated image name at byte {self.offset}")
        name = self.data[self.offset:end].decode("utf-8", errors="replace")
        self.offset = end + 1
        return name


def _read_cameras_binary(file: pathlib.Path) -> dict[int, ColmapCamera]:
    reader, cameras = _BinaryReader(file), {}
    (count,) = reader.read("Q")
    for record in range(count):
        camera_id, model_id, width, height = reader.read("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise DataError(f"{file}: camera record {record}: unknown model id {model_id}")
        name, n_params = CAMERA_MODELS[model_id]
        cameras[camera_id] = ColmapCamera(name, width, height, np.array(reader.read(f"{n_params}d")))
    return cameras


def _read_images_binary(file: pathlib.Path) -> list[ColmapImage]:
    reader, images = _BinaryReader(file), []
    (count,) = reader.read("Q")
    for _ in range(count):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.read("i7di")
        name = reader.read_name()
        (n_points,) = reader.read("Q")
        ids = np.array(reader.read("ddq" * n_points)[2::3], dtype=np.int64)
        images.append(ColmapImage(image_id, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), camera_id, name,
                                  ids[ids >= 0]))
    return images


def _read_points_binary(file: pathlib.Path) -> dict[int, np.ndarray]:
    reader, points = _BinaryReader(file), {}
    (count,) = reader.read("Q")
    for _ in range(count):
        point_id, x, y, z, _r, _g, _b, _error, track_length = reader.read("Q3d3BdQ")
        reader.read("ii" * track_length)
        points[point_id] = np.array([x, y, z])
    return points
