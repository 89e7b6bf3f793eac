"""Torch-facing differentiable ops over the Warp kernels (CPU and CUDA, zero-copy)."""
