"""Scene data: loaders for the formats users have, protocol preprocessing, view selection, procedural
scenes with exact ground truth, and a torch Dataset / DataLoader path.

:func:`load_scene` (:mod:`.formats`) reads one scene folder (or pose file), detecting its format among
:data:`FORMATS`.

RE10K / ACID / DL3DV ``.torch`` chunks hold many scenes: ``load_scene("PATH/000000.torch", key=...)`` (or a chunk
folder with its ``index.json`` and ``key``) reads one, :func:`read_chunk` all of a chunk.
"""

from __future__ import annotations

from ..errors import DataError
from .chunks import load_chunk_scene, load_index, read_chunk, write_chunks
from .colmap import is_colmap_model, load_colmap, read_model
from .depth_maps import DepthMaps, read_depth_maps
from .dataset import ProceduralDataset, SceneDataset, make_dataloader
from .formats import FORMATS, detect_formats, load_scene
from .kitti import load_kitti
from .llff import load_llff
from .middlebury import load_middlebury
from .nerf import load_nerf
from .neus import load_neus
from .preprocess import DATASET_CONFIGS, DatasetConfig, preprocess_scene, resize_and_crop
from .procedural import ProceduralConfig, procedural_scene, render
from .scene import EncodedImages, Scene
from .scene_json import load_scene_json
from .sevenscenes import load_7scenes
from .strecha import load_strecha
from .views import (
    BoundedSamplerConfig, ViewSelection, load_evaluation_index, sample_bounded_views, split_context_targets,
)

__all__ = [
    "BoundedSamplerConfig", "DATASET_CONFIGS", "DataError", "DatasetConfig", "DepthMaps", "EncodedImages", "FORMATS",
    "ProceduralConfig", "ProceduralDataset", "Scene", "SceneDataset", "ViewSelection", "detect_formats",
    "is_colmap_model", "load_7scenes", "load_chunk_scene", "load_colmap", "load_evaluation_index", "load_index",
    "load_kitti", "load_llff", "load_middlebury", "load_nerf", "load_neus", "load_scene", "load_scene_json",
    "load_strecha", "make_dataloader", "preprocess_scene", "procedural_scene", "read_chunk", "read_depth_maps",
    "read_model", "render", "resize_and_crop", "sample_bounded_views", "split_context_targets", "write_chunks",
]
