"""codecsplat-warp: CodecSplat (feed-forward 3DGS with a learned scene bitstream) on NVIDIA Warp kernels.

Public entry points live in submodules: :mod:`codecsplat_warp.cameras` (conventions),
:mod:`codecsplat_warp.ops` (differentiable Warp ops), :mod:`codecsplat_warp.device` (torch/Warp glue).
"""

__version__ = "0.1.0"
