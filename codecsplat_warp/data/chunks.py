"""RE10K / ACID / DL3DV ``.torch`` chunks as pixelSplat, MVSplat and DepthSplat store them: reader and writer.

A chunk file is a list of scene dicts::

    {"key": str, "url": str, "timestamps": int64 [N],
     "cameras": float32 [N,18],   # fx/W, fy/H, cx/W, cy/H, 0, 0, then w2c[:3,:4] row-major (OpenCV axes)
     "images": [uint8 [bytes] JPEG, ...]}   # N encoded images

and ``index.json`` next to the chunks maps each key to its chunk file name. Files are read with
``torch.load(..., weights_only=True)``, so a chunk cannot run pickled code. The format has no depth bounds:
near/far come from the dataset configuration (:mod:`~codecsplat_warp.data.preprocess`).
"""

from __future__ import annotations

import io
import json
import pathlib
import pickle
from typing import Iterable

import torch
from PIL import Image
from tqdm.auto import tqdm

from ..cameras import Cameras
from ..errors import DataError
from .scene import EncodedImages, Scene, make_cameras, read_image_size, require_file

CHUNK_KEYS = ("key", "url", "timestamps", "cameras", "images")
DEFAULT_MAX_CHUNK_BYTES = 100 * 2**20
"""Writer default: start a new chunk once the current one holds this many image bytes (pixelSplat uses ~100 MB)."""
DEFAULT_JPEG_QUALITY = 95


def read_chunk(file, near: float = 0.5, far: float = 100.0) -> list[Scene]:
    """Every scene of one ``.torch`` chunk, images kept encoded (decoded on access).

    Args:
        file: the chunk path.
        near, far: depth range given to every camera (DepthSplat's RE10K config is 0.5 / 100).

    Raises:
        DataError: not a loadable weights-only file, wrong structure, count mismatch or bad cameras,
            naming the file, the scene key and the frame.
    """
    file = pathlib.Path(file)
    return [_scene_from_record(file, index, record, near, far) for index, record in enumerate(_load_records(file))]


def load_index(root) -> dict[str, pathlib.Path]:
    """``index.json`` of a chunk folder as key -> chunk path.

    Raises:
        DataError: missing or malformed index, or an entry naming a chunk that does not exist.
    """
    root = pathlib.Path(root)
    file = require_file(root / "index.json")
    try:
        entries = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{file}: not valid JSON: {exc}") from None
    if not isinstance(entries, dict) or not all(isinstance(v, str) for v in entries.values()):
        raise DataError(f"{file}: expected an object mapping scene keys to chunk file names")
    index = {key: root / name for key, name in entries.items()}
    for key, path in index.items():
        if not path.is_file():
            raise DataError(f"{file}: scene {key!r} points to {path}, which does not exist")
    return index


def load_chunk_scene(root, key: str, near: float = 0.5, far: float = 100.0) -> Scene:
    """The scene ``key`` of a chunk folder, found through its ``index.json``."""
    index = load_index(root)
    if key not in index:
        raise DataError(f"{pathlib.Path(root) / 'index.json'}: no scene with key {key!r}")
    for scene in read_chunk(index[key], near, far):
        if scene.key == key:
            return scene
    raise DataError(f"{index[key]}: index.json says it holds scene {key!r}, but it does not")


def write_chunks(scenes: Iterable[Scene], out_dir, max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES,
                 jpeg_quality: int = DEFAULT_JPEG_QUALITY, progress: bool = True) -> dict[str, str]:
    """Package scenes as ``.torch`` chunks plus ``index.json`` in ``out_dir``; returns the index.

    JPEG files are stored byte for byte; other images (PNG files, decoded tensors) are encoded as JPEG
    with ``jpeg_quality``. ``Scene.metadata`` may give ``url`` and ``timestamps`` (default ``""`` and
    0..V-1). Scene keys must be unique.
    """
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    index: dict[str, str] = {}
    chunk: list[dict] = []
    chunk_bytes = 0

    def flush() -> None:
        nonlocal chunk, chunk_bytes
        name = f"{len(set(index.values())):06d}.torch"
        torch.save(chunk, out_dir / name)
        index.update({record["key"]: name for record in chunk})
        chunk, chunk_bytes = [], 0

    for scene in tqdm(scenes, desc="writing chunks", unit="scene", disable=not progress):
        if scene.key in index or any(r["key"] == scene.key for r in chunk):
            raise DataError(f"{scene.source}: scene key {scene.key!r} is used twice")
        record = scene_to_record(scene, jpeg_quality)
        chunk.append(record)
        chunk_bytes += sum(int(im.numel()) for im in record["images"])
        if chunk_bytes >= max_chunk_bytes:
            flush()
    if chunk:
        flush()
    (out_dir / "index.json").write_text(json.dumps(index, indent=1))
    return index


def scene_to_record(scene: Scene, jpeg_quality: int = DEFAULT_JPEG_QUALITY) -> dict:
    """The chunk dict of one scene (see the module docstring)."""
    cameras = scene.cameras.to("cpu", torch.float64)
    V = cameras.num_views
    rows = torch.zeros(V, 18, dtype=torch.float64)
    rows[:, :4] = cameras.normalized_intrinsics()
    rows[:, 6:] = cameras.w2c[:, :3, :4].reshape(V, 12)
    timestamps = torch.as_tensor(scene.metadata.get("timestamps", torch.arange(V)), dtype=torch.int64)
    if timestamps.shape != (V,):
        raise DataError(f"{scene.source}: metadata timestamps have shape {tuple(timestamps.shape)}, expected ({V},)")
    return {
        "key": scene.key,
        "url": str(scene.metadata.get("url", "")),
        "timestamps": timestamps,
        "cameras": rows.to(torch.float32),
        "images": [_encoded_bytes(scene, frame, jpeg_quality) for frame in range(V)],
    }


def _encoded_bytes(scene: Scene, frame: int, jpeg_quality: int) -> torch.Tensor:
    """uint8 [bytes] JPEG of one frame: a JPEG file's own bytes, else a fresh encoding."""
    if isinstance(scene.images, EncodedImages):
        source = scene.images.sources[frame]
        data = source.read_bytes() if isinstance(source, pathlib.Path) else bytes(source)
        if data[:3] == b"\xff\xd8\xff":
            return torch.frombuffer(bytearray(data), dtype=torch.uint8)
    image = scene.decoded_images([frame])[0]
    buffer = io.BytesIO()
    Image.fromarray(image.permute(1, 2, 0).numpy()).save(buffer, format="JPEG", quality=jpeg_quality)
    return torch.frombuffer(bytearray(buffer.getvalue()), dtype=torch.uint8)


def _load_records(file: pathlib.Path) -> list:
    require_file(file)
    try:
        records = torch.load(file, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError) as exc:
        raise DataError(f"{file}: not a weights-only torch chunk: {exc}") from None
    if not isinstance(records, list):
        raise DataError(f"{file}: a chunk must be a list of scene dicts, got {type(records).__name__}")
    return records


def _scene_from_record(file: pathlib.Path, index: int, record, near: float, far: float) -> Scene:
    where = f"{file}: scene {index}"
    if not isinstance(record, dict) or any(k not in record for k in CHUNK_KEYS):
        raise DataError(f"{where}: a scene dict needs the keys {', '.join(CHUNK_KEYS)}")
    key, rows, images = str(record["key"]), record["cameras"], record["images"]
    where = f"{file}: scene {key!r}"
    if not isinstance(rows, torch.Tensor) or rows.dim() != 2 or rows.shape[1] != 18:
        raise DataError(f"{where}: 'cameras' must be an [N,18] tensor")
    V = rows.shape[0]
    if not isinstance(images, (list, tuple)) or len(images) != V:
        raise DataError(f"{where}: {V} camera rows but {len(images) if hasattr(images, '__len__') else '?'} images")
    timestamps = torch.as_tensor(record["timestamps"])
    if timestamps.shape != (V,):
        raise DataError(f"{where}: {V} camera rows but timestamps of shape {tuple(timestamps.shape)}")
    for frame in range(V):
        if not bool(torch.isfinite(rows[frame]).all()):
            raise DataError(f"{where}: frame {frame}: camera row holds NaN or Inf")
        if not isinstance(images[frame], torch.Tensor) or images[frame].dtype != torch.uint8:
            raise DataError(f"{where}: frame {frame}: image must be a uint8 tensor of encoded bytes")
    sources = [images[f].numpy().tobytes() for f in range(V)]
    width, height = read_image_size(io.BytesIO(sources[0]), f"{where}: frame 0")
    w2c = rows[:, 6:].reshape(V, 3, 4).to(torch.float64)
    intrinsics = rows[:, :4].to(torch.float64)
    cameras = make_cameras(where, lambda: Cameras.from_normalized_intrinsics(intrinsics, w2c, near, far, width, height))
    return Scene(
        images=EncodedImages(sources, width, height),
        cameras=cameras,
        key=key,
        source=f"chunk:{file}",
        frame_names=[f"{key}/{int(t)}" for t in timestamps],
        metadata={"url": str(record["url"]), "timestamps": timestamps.clone()},
    )
