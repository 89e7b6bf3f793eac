"""Files for other tools: 3DGS PLY export / import, novel-view frames and videos, atomic output."""

from .files import atomic_output, write_bytes, write_text
from .ply import (attribute_names, decode_ply, encode_ply, gaussians_from_attributes,
                  ply_attributes, read_ply, write_ply)
from .video import FORMATS, MP4_MISSING, mp4_plugin, orbit_cameras, to_uint8_frames, write_frames

__all__ = [
    "FORMATS", "MP4_MISSING", "mp4_plugin", "orbit_cameras", "to_uint8_frames", "write_frames",
    "atomic_output", "attribute_names", "decode_ply", "encode_ply",
    "gaussians_from_attributes", "ply_attributes", "read_ply", "write_bytes", "write_ply",
    "write_text",
]
