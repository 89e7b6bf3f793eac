"""Pretrained CodecSplat files: writing, reading and the shipped default.

A pretrained file is ONE safetensors file: every weight in float32, or in float16 when written with
``save_pretrained(half=True)`` (weights first rounded to float16 values by :func:`round_to_half`), and in its
metadata the format name, the :class:`~codecsplat_warp.nn.config.ModelConfig` as JSON, the SHA-256 of the
weights (checked on load) and the model identifier. Loading gives a float32 model either way. The re10k/dl3dv
presets hold about 4.1 M parameters, i.e. 15.7 MiB in float32 (7.9 MiB in float16), within the 16 MiB a file
may have. The shipped default at :data:`DEFAULT_CHECKPOINT` (three latent levels, 4.1 M parameters) is stored in
float16 (``python -m train.export ... --half``, 7.9 MiB; a codec grown by a fourth latent level holds 4.2 M, a
model with the VGG16 mono prior about 5.9 M parameters, 11.3 MiB in float16, which would not fit in float32).

The model identifier (:func:`~codecsplat_warp.model.codecsplat.model_id`)
hashes the weights as float32 values, so a float16 file and the float32 model it loads into share it.
"""

from __future__ import annotations

import json
import os
import pathlib

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from ..device import resolve_device
from ..errors import DataError, InputError
from ..nn.config import ModelConfig
from .codecsplat import CodecSplat, model_id, weights_digest
from .releases import DEFAULT_FILE

DEFAULT_CHECKPOINT = pathlib.Path(__file__).resolve().parents[1] / DEFAULT_FILE
"""The checkpoint shipped with the package (``load_pretrained()`` with no path)."""

FORMAT = "codecsplat-pretrained-v1"


def round_to_half(model: torch.nn.Module) -> torch.nn.Module:
    """Round every floating weight of ``model`` to float16 precision in place (kept in its dtype), so that it can
    be stored by :func:`save_pretrained` with ``half=True`` at half the size; returns the model."""
    with torch.no_grad():
        for tensor in model.state_dict().values():
            if tensor.is_floating_point():
                tensor.copy_(tensor.half())
    return model


def save_pretrained(model: torch.nn.Module, path, half: bool = False) -> pathlib.Path:
    """Write ``model`` (a :class:`CodecSplat` with its codec) as one safetensors file, atomically.

    Args:
        half: store the weights as float16 (half the file size); they must already be float16 values
            (:func:`round_to_half`), so loading gives back exactly the model that was saved (same model id).
    Returns:
        the path written.
    Raises:
        InputError: the model has no codec (a stage-1 model cannot encode or decode bitstreams), or ``half``
            with weights that float16 does not represent exactly.
    """
    if getattr(model, "codec", None) is None:
        raise InputError("only a CodecSplat with its codec (codec=True, stage 2) can be saved as a pretrained model")
    path = pathlib.Path(path)
    storage = torch.float16 if half else torch.float32
    tensors = {name: t.detach().to("cpu", storage).contiguous() for name, t in model.state_dict().items()}
    if half and any(not torch.equal(tensors[n].float(), t.detach().cpu().float()) for n, t in model.state_dict().items()):
        raise InputError("half=True needs weights that are float16 values: call round_to_half(model) first")
    metadata = {"format": FORMAT, "config": json.dumps(model.config.to_dict()), "weights_sha256": weights_digest(model),
                "model_id": model_id(model)}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=metadata)
    os.replace(tmp, path)
    return path


def load_pretrained(path=None, device=None):
    """A :class:`CodecSplat` (with codec, eval mode) from a file written by :func:`save_pretrained`.

    Args:
        path: the safetensors file; None for the shipped :data:`DEFAULT_CHECKPOINT`.
        device: cpu, cuda, cuda:N, auto or None (auto: CUDA when available).
    Raises:
        DataError: the file is missing, unreadable, of another format, or its weights do not match their hash.
    """
    path = pathlib.Path(path) if path is not None else DEFAULT_CHECKPOINT
    if not path.is_file():
        hint = (" (the shipped default model is not part of this installation yet: train one with train.stage2 "
                "and write it with save_pretrained, or pass a path)") if path == DEFAULT_CHECKPOINT else ""
        raise DataError(f"pretrained model file {path} not found{hint}")
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError) as exc:
        raise DataError(f"{path} is not a readable safetensors file: {exc}") from None
    if metadata.get("format") != FORMAT:
        raise DataError(f"{path}: not a CodecSplat pretrained file (format {metadata.get('format')!r}, "
                        f"expected {FORMAT})")
    try:
        config = ModelConfig.from_dict(json.loads(metadata["config"]))
        model = CodecSplat(config, codec=True)
        model.load_state_dict(tensors)
    except (KeyError, ValueError, RuntimeError) as exc:
        raise DataError(f"{path}: config and weights do not fit together: {exc}") from None
    model = model.to(resolve_device(device)).eval()
    if weights_digest(model) != metadata.get("weights_sha256"):
        raise DataError(f"{path}: the weights do not match their SHA-256 (corrupt file)")
    return model
