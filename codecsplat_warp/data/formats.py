"""One scene folder or pose file -> :class:`~codecsplat_warp.data.scene.Scene`, whatever its format.

:func:`load_scene` reads one scene folder (or pose file, or one scene of a ``.torch`` chunk), detecting its format:

========================  =====================================================================
format                    detected by
========================  =====================================================================
``scene-json``            ``cameras.json`` with ``"format": "codecsplat-scene-v1"`` (default)
``llff``                  ``poses_bounds.npy``
``nerf``                  ``transforms.json`` / ``transforms_train.json`` / ``transforms*.json``
``neus``                  ``cameras_sphere.npz``
``middlebury``            ``*_par.txt``
``colmap``                ``sparse/0/``, ``sparse/`` or the folder itself holding cameras/images .txt/.bin
``kitti``                 ``poses.txt`` next to ``calib.txt`` (KITTI odometry)
``7scenes``               ``camera-intrinsics.txt`` next to ``poses/*.pose.txt`` (Microsoft 7-Scenes)
``strecha``               ``gt_dense_cameras/*.camera`` (Strecha et al. dense multi-view stereo benchmark)
========================  =====================================================================
"""

from __future__ import annotations

import pathlib

from ..errors import DataError
from .chunks import load_chunk_scene, read_chunk
from .colmap import is_colmap_model, load_colmap
from .kitti import load_kitti
from .llff import load_llff
from .middlebury import load_middlebury
from .nerf import load_nerf
from .neus import load_neus
from .scene import Scene, name_list
from .scene_json import is_scene_json, load_scene_json
from .sevenscenes import load_7scenes, pose_files_of
from .strecha import CAMERA_FOLDER, is_strecha_folder, load_strecha

FORMATS = ("scene-json", "llff", "nerf", "neus", "middlebury", "colmap", "kitti", "7scenes", "strecha")
"""Format names accepted by :func:`load_scene`'s ``format`` argument."""

_LOADERS = {
    "scene-json": load_scene_json, "llff": load_llff, "nerf": load_nerf, "neus": load_neus,
    "middlebury": load_middlebury, "colmap": load_colmap, "kitti": load_kitti, "7scenes": load_7scenes,
    "strecha": load_strecha,
}


def load_scene(path, format: str | None = None, prefer_native: bool = False, key: str | None = None) -> Scene:
    """Load one scene from a folder, a pose file or a ``.torch`` chunk, detecting the format.

    Args:
        path: a scene folder, a pose file (``cameras.json``, ``poses_bounds.npy``, ``transforms*.json``,
            ``cameras_sphere.npz``, ``*_par.txt``, KITTI ``poses.txt``, 7-Scenes ``camera-intrinsics.txt``),
            a COLMAP model folder, a Strecha ``gt_dense_cameras`` folder, a ``.torch`` chunk, or a chunk folder
            (``index.json`` + chunks).
        format: force one of :data:`FORMATS` (the pose file is then looked up in the folder).
        prefer_native: in a folder holding both, read the native pose file instead of ``cameras.json``.
        key: the scene of a chunk (may be left out when the chunk holds one scene) or of a chunk folder. Chunks
            store no depth bounds: the cameras get DepthSplat's RE10K range, near 0.5 and far 100 (another
            dataset's: ``scene.cameras.with_depth_range``, or :func:`read_chunk` with ``near`` / ``far``).

    Raises:
        DataError: nothing readable found, unknown format name, a key the chunk does not hold (listing those it
            does), a key for a path that is not a chunk, or any loader error (naming file and frame).
    """
    path = pathlib.Path(path)
    if not path.exists():
        raise DataError(f"{path} does not exist")
    if path.suffix == ".torch" and path.is_file():
        return _chunk_scene(path, key)
    if key is not None:
        if path.is_dir() and (path / "index.json").is_file():
            return load_chunk_scene(path, key)
        raise DataError(f"{path}: key={key!r} selects a scene of a .torch chunk or chunk folder, and this is neither")
    if format is not None and format not in FORMATS:
        raise DataError(f"unknown scene format {format!r}; known: {', '.join(FORMATS)}")
    if path.is_file():
        detected = format or _format_of_file(path)
        return _LOADERS[detected](path)
    candidates = _pose_files(path)
    if format is not None:
        if format not in candidates:
            raise DataError(f"{path}: no {format} pose file found")
        return _LOADERS[format](candidates[format])
    order = [f for f in FORMATS if f != "scene-json"] + ["scene-json"] if prefer_native else list(FORMATS)
    for name in order:
        if name in candidates:
            return _LOADERS[name](candidates[name])
    raise DataError(f"{path}: no supported pose file (cameras.json, poses_bounds.npy, transforms*.json, "
                    "cameras_sphere.npz, *_par.txt, COLMAP sparse model, KITTI poses.txt + calib.txt, "
                    "7-Scenes camera-intrinsics.txt + poses/*.pose.txt, Strecha gt_dense_cameras/*.camera)")


def _chunk_scene(file: pathlib.Path, key: str | None) -> Scene:
    """The scene ``key`` of one chunk file (its only scene when ``key`` is None)."""
    scenes = read_chunk(file)
    keys = [scene.key for scene in scenes]
    if key is None:
        if len(scenes) != 1:
            raise DataError(f"{file} holds {len(scenes)} scenes: choose one with key= ({name_list(keys)})")
        return scenes[0]
    if key not in keys:
        raise DataError(f"{file} holds no scene {key!r}; it holds {name_list(keys)}")
    return scenes[keys.index(key)]


def detect_formats(folder) -> dict[str, pathlib.Path]:
    """Every supported pose file found in a scene folder, as format name -> path."""
    return _pose_files(pathlib.Path(folder))


def _format_of_file(file: pathlib.Path) -> str:
    name = file.name
    if name.endswith(".json"):
        if is_scene_json(file):
            return "scene-json"
        if name.startswith("transforms"):
            return "nerf"
    if name == "poses_bounds.npy":
        return "llff"
    if name == "cameras_sphere.npz":
        return "neus"
    if name.endswith("_par.txt"):
        return "middlebury"
    if name == "poses.txt":
        return "kitti"
    if name == "camera-intrinsics.txt":
        return "7scenes"
    raise DataError(f"{file}: unsupported pose file (expected cameras.json, poses_bounds.npy, transforms*.json, "
                    "cameras_sphere.npz, *_par.txt, poses.txt or camera-intrinsics.txt)")


def _pose_files(folder: pathlib.Path) -> dict[str, pathlib.Path]:
    found: dict[str, pathlib.Path] = {}
    if (folder / "cameras.json").is_file() and is_scene_json(folder / "cameras.json"):
        found["scene-json"] = folder / "cameras.json"
    if (folder / "poses_bounds.npy").is_file():
        found["llff"] = folder / "poses_bounds.npy"
    transforms = sorted(folder.glob("transforms*.json"))
    preferred = [folder / "transforms.json", folder / "transforms_train.json"]
    for file in [p for p in preferred if p.is_file()] + transforms:
        found.setdefault("nerf", file)
    if (folder / "cameras_sphere.npz").is_file():
        found["neus"] = folder / "cameras_sphere.npz"
    par_files = sorted(folder.glob("*_par.txt"))
    if par_files:
        found["middlebury"] = par_files[0]
    for model in (folder / "sparse" / "0", folder / "sparse", folder):
        if is_colmap_model(model):
            found["colmap"] = model
            break
    if (folder / "poses.txt").is_file() and (folder / "calib.txt").is_file():
        found["kitti"] = folder / "poses.txt"
    if (folder / "camera-intrinsics.txt").is_file() and _has_7scenes_poses(folder):
        found["7scenes"] = folder / "camera-intrinsics.txt"
    cameras = folder if folder.name == CAMERA_FOLDER else folder / CAMERA_FOLDER
    if is_strecha_folder(cameras):
        found["strecha"] = cameras
    return found


def _has_7scenes_poses(folder: pathlib.Path) -> bool:
    try:
        return bool(pose_files_of(folder))
    except DataError:
        return False
