"""Standard 3DGS PLY files (the layout of the INRIA 3D Gaussian Splatting code, read by common splat viewers).

One binary little-endian ``vertex`` element with float32 properties, in this order:

* ``x, y, z``: centres (world space);
* ``nx, ny, nz``: zeros (3DGS writes them; viewers ignore them);
* ``f_dc_0..2``: the degree-0 SH coefficient of R, G, B;
* ``f_rest_0..3(K-1)-1``: the higher SH coefficients **channel-major**: all K-1 coefficients of R, then of
  G, then of B (3DGS stores ``features_rest`` as [N, 3, K-1] flattened);
* ``opacity``: logit of the opacity;
* ``scale_0..2``: natural log of the standard deviations;
* ``rot_0..3``: the rotation quaternion w, x, y, z (Gaussian frame -> world, unit length).

SH conventions are those of :mod:`codecsplat_warp.gaussians` (3DGS/gsplat basis, +0.5 added by the
renderer), so the file renders the same in 3DGS viewers as with :meth:`CodecSplat.render`.
"""

from __future__ import annotations

import io
import os
import pathlib
import tempfile

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError

from ..errors import DataError
from ..gaussians import Gaussians
from .files import write_bytes

_OPACITY_EPS = 2.0**-24
"""Opacities are clamped to [eps, 1 - eps] before the logit, so float32 sigmoid outputs of exactly 0 or 1 stay finite."""

_SCALE_MIN = float(np.finfo(np.float32).tiny)
"""Scales are clamped to at least this before the log."""


def attribute_names(sh_degree: int) -> list[str]:
    """The vertex property names of a PLY with SH of ``sh_degree``, in file order."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def ply_attributes(gaussians: Gaussians) -> dict[str, np.ndarray]:
    """The PLY columns of ``gaussians`` as {name: float32 [N]}, in :func:`attribute_names` order."""
    g = gaussians.detach()
    n = len(g)
    sh = g.sh.to("cpu", torch.float64)
    opacity = g.opacities.to("cpu", torch.float64).clamp(_OPACITY_EPS, 1.0 - _OPACITY_EPS)
    blocks = [
        g.means.to("cpu", torch.float64),
        torch.zeros(n, 3, dtype=torch.float64),
        sh[:, 0, :],
        sh[:, 1:, :].transpose(1, 2).reshape(n, -1),
        torch.logit(opacity)[:, None],
        g.scales.to("cpu", torch.float64).clamp_min(_SCALE_MIN).log(),
        torch.nn.functional.normalize(g.quats.to("cpu", torch.float64), dim=-1),
    ]
    table = torch.cat(blocks, dim=1).to(torch.float32).numpy()
    return {name: table[:, i] for i, name in enumerate(attribute_names(g.sh_degree))}


def gaussians_from_attributes(columns: dict[str, np.ndarray], device: torch.device | str = "cpu") -> Gaussians:
    """Inverse of :func:`ply_attributes` (normals ignored, quaternions normalised): float32 :class:`Gaussians`.

    Raises:
        DataError: a position, opacity, scale or rotation column is missing, or the ``f_rest_*`` count is
            not 3 ((degree+1)^2 - 1) for a degree 0..3.
    """
    rest = sorted((k for k in columns if k.startswith("f_rest_") and k[7:].isdigit()), key=lambda k: int(k[7:]))
    num_sh = len(rest) // 3 + 1
    degree = round(num_sh**0.5) - 1
    if len(rest) % 3 or (degree + 1) ** 2 != num_sh or degree > 3:
        raise DataError(f"PLY has {len(rest)} f_rest_* properties; 3DGS needs 3((d+1)^2-1) for an SH degree d in 0..3")
    needed = [n for n in attribute_names(degree) if not n.startswith("n")]
    missing = [n for n in needed if n not in columns]
    if missing:
        raise DataError(f"PLY lacks the 3DGS properties {', '.join(missing)}")
    col = lambda *names: torch.from_numpy(np.stack([np.asarray(columns[k], np.float32) for k in names], 1))  # noqa: E731
    n = len(columns["x"])
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :]
    higher = col(*rest).reshape(n, 3, num_sh - 1).transpose(1, 2) if rest else dc[:, :0]
    return Gaussians(
        means=col("x", "y", "z").to(device),
        quats=torch.nn.functional.normalize(col("rot_0", "rot_1", "rot_2", "rot_3"), dim=-1).to(device),
        scales=col("scale_0", "scale_1", "scale_2").exp().to(device),
        opacities=torch.sigmoid(col("opacity")[:, 0]).to(device),
        sh=torch.cat([dc, higher], dim=1).contiguous().to(device),
    )


def encode_ply(gaussians: Gaussians) -> bytes:
    """The bytes of a binary little-endian 3DGS PLY file holding ``gaussians``."""
    columns = ply_attributes(gaussians)
    vertices = np.empty(len(gaussians), dtype=[(name, "<f4") for name in columns])
    for name, values in columns.items():
        vertices[name] = values
    stream = io.BytesIO()
    PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<").write(stream)
    return stream.getvalue()


def decode_ply(data: bytes, device: torch.device | str = "cpu") -> Gaussians:
    """float32 :class:`Gaussians` of 3DGS PLY file bytes (as :func:`encode_ply` or the 3DGS code writes them).

    The bytes pass through a temporary file: plyfile reads binary data fast only from a memory-mapped file.

    Raises:
        DataError: not a PLY, no ``vertex`` element, or missing 3DGS properties.
    """
    with tempfile.NamedTemporaryFile(suffix=".ply") as tmp:
        tmp.write(data)
        tmp.flush()
        return _read_gaussians(tmp.name, device)


def write_ply(path: str | os.PathLike, gaussians: Gaussians) -> int:
    """Write ``gaussians`` as a binary 3DGS PLY file (atomically); returns the file size in bytes."""
    data = encode_ply(gaussians)
    write_bytes(path, data)
    return len(data)


def read_ply(path: str | os.PathLike, device: torch.device | str = "cpu") -> Gaussians:
    """Read a 3DGS PLY file (as :func:`write_ply` or the 3DGS code writes them) into float32 :class:`Gaussians`.

    Raises:
        DataError: missing file, not a PLY, no ``vertex`` element, or missing 3DGS properties (naming the file).
    """
    if not pathlib.Path(path).is_file():
        raise DataError(f"{path} does not exist")
    try:
        return _read_gaussians(str(path), device)
    except DataError as exc:
        raise DataError(f"{path}: {exc}") from None


def _read_gaussians(path: str, device: torch.device | str) -> Gaussians:
    """Gaussians of the PLY file at ``path`` (memory-mapped, copied before the file is closed)."""
    try:
        ply = PlyData.read(path)
    except (PlyParseError, ValueError, EOFError) as exc:
        raise DataError(f"not a readable PLY file: {exc}") from None
    if "vertex" not in ply:
        raise DataError("PLY file has no 'vertex' element")
    vertices = ply["vertex"].data
    return gaussians_from_attributes({name: np.array(vertices[name]) for name in vertices.dtype.names}, device)

