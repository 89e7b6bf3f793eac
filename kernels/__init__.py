"""Pure Warp kernels of codecsplat-warp (no torch here), one file per kernel family.

Installed as ``codecsplat_warp.kernels``; the torch-facing autograd ops live in ``codecsplat_warp.ops``.
Every kernel is generic over float32/float64 (Warp instantiates the overload on first launch).
"""
