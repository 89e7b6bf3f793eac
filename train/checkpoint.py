"""Resumable training checkpoints: safetensors shards (<= 16 MB a file) plus a small trainer-state file.

Layout of ``<run>/checkpoints/``::

    step-00001000/model-00000.safetensors ...   model weights (tensors larger than a shard are split)
    step-00001000/optim-00000.safetensors ...   optimizer tensors (AdamW exp_avg, exp_avg_sq, step)
    step-00001000/ema-00000.safetensors ...     weight average of the trainable parameters (float32; runs with
                                                --ema-decay > 0; its update count is in checkpoint.json)
    step-00001000/trainer.pt                    param groups, scheduler, RNG states, step, config (small)
    step-00001000/checkpoint.json               index: files, split tensors, step; written last
    latest                                      name of the newest complete checkpoint

Every file is written to a temporary name and moved into place with ``os.replace``; the checkpoint
folder is assembled under a temporary name and renamed when complete, and ``latest`` is replaced last,
so a run killed at any moment resumes from the last complete checkpoint.

Resuming (:func:`load_checkpoint`) reads the raw weights; everything that uses a run's weights (validation,
export, warm starts) reads :func:`weights_for_use`, the weight average where the checkpoint has one.
"""

from __future__ import annotations

import json
import os
import pathlib
import random
import shutil

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.nn.config import ModelConfig

from .weight_average import WeightAverage

MAX_FILE_BYTES = 16 * 1024 * 1024
"""Largest checkpoint file (so checkpoints move between machines in small pieces)."""

FORMAT = "codecsplat-stage1-checkpoint-v1"

HEADER_BYTES_PER_TENSOR = 128
"""Budget for one tensor's safetensors header entry (JSON dtype, shape, offsets, padding) beyond its key."""


def _atomic_write(path: pathlib.Path, write) -> None:
    """Call ``write(tmp_path)`` then move the result to ``path`` atomically."""
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def split_tensors(tensors: dict[str, torch.Tensor], max_bytes: int) -> tuple[list[dict[str, torch.Tensor]], dict]:
    """Group CPU tensors into shards whose files stay within ``max_bytes`` (data plus header estimate);
    tensors larger than half of that are cut into flat pieces ``name::part{i}``.
    Returns (shards, {name: shape} of the cut tensors)."""
    shards: list[dict[str, torch.Tensor]] = [{}]
    sizes = [0]
    cut: dict[str, list[int]] = {}
    for name, tensor in tensors.items():
        tensor = tensor.detach().to("cpu").contiguous()
        pieces = {name: tensor}
        if tensor.numel() * tensor.element_size() > max_bytes // 2:
            cut[name] = list(tensor.shape)
            per_piece = max(1, (max_bytes // 2) // tensor.element_size())
            pieces = {f"{name}::part{i}": p.clone() for i, p in enumerate(tensor.reshape(-1).split(per_piece))}
        for key, piece in pieces.items():
            nbytes = piece.numel() * piece.element_size() + len(key) + HEADER_BYTES_PER_TENSOR
            if sizes[-1] + nbytes > max_bytes and shards[-1]:
                shards.append({})
                sizes.append(0)
            shards[-1][key] = piece
            sizes[-1] += nbytes
    return shards, cut


def join_tensors(stored: dict[str, torch.Tensor], cut: dict[str, list[int]]) -> dict[str, torch.Tensor]:
    """Inverse of :func:`split_tensors` on the union of the shards."""
    out = {k: v for k, v in stored.items() if "::part" not in k}
    for name, shape in cut.items():
        parts = sorted((k for k in stored if k.startswith(name + "::part")), key=lambda k: int(k.rsplit("part", 1)[1]))
        out[name] = torch.cat([stored[k] for k in parts]).reshape(shape)
    return out


def _flatten_optimizer(state_dict: dict) -> tuple[dict[str, torch.Tensor], dict]:
    """Optimizer state dict -> (tensors keyed ``state.{param}.{name}``, JSON-able rest)."""
    tensors, plain = {}, {"param_groups": state_dict["param_groups"], "state": {}}
    for index, values in state_dict["state"].items():
        for name, value in values.items():
            if isinstance(value, torch.Tensor):
                tensors[f"state.{index}.{name}"] = value
            else:
                plain["state"].setdefault(str(index), {})[name] = value
    return tensors, plain


def _unflatten_optimizer(tensors: dict[str, torch.Tensor], plain: dict) -> dict:
    state: dict[int, dict] = {int(k): dict(v) for k, v in plain["state"].items()}
    for key, value in tensors.items():
        _, index, name = key.split(".", 2)
        state.setdefault(int(index), {})[name] = value
    return {"state": state, "param_groups": plain["param_groups"]}


def _rng_state() -> dict:
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    if torch.cuda.is_available() and state["cuda"]:
        torch.cuda.set_rng_state_all(state["cuda"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def _write_shards(folder: pathlib.Path, prefix: str, tensors: dict[str, torch.Tensor], max_bytes: int) -> dict:
    shards, cut = split_tensors(tensors, max_bytes)
    files = []
    for i, shard in enumerate(shards):
        name = f"{prefix}-{i:05d}.safetensors"
        _atomic_write(folder / name, lambda tmp, shard=shard: save_file(shard, str(tmp)))
        files.append(name)
    return {"files": files, "cut": cut}


def _read_shards(folder: pathlib.Path, index: dict) -> dict[str, torch.Tensor]:
    stored: dict[str, torch.Tensor] = {}
    for name in index["files"]:
        stored.update(load_file(str(folder / name)))
    return join_tensors(stored, index["cut"])


def save_checkpoint(run_dir, step: int, model: torch.nn.Module, optimizer, scheduler, extra: dict,
                    keep: int = 2, max_bytes: int = MAX_FILE_BYTES,
                    average: WeightAverage | None = None) -> pathlib.Path:
    """Write the checkpoint of ``step`` under ``run_dir/checkpoints`` and keep the newest ``keep``.

    Args:
        model: the bare module (not the DDP wrapper).
        extra: JSON-able values stored with it (e.g. the configs).
        average: the run's weight average, if it keeps one.
    Returns:
        the checkpoint folder.
    """
    root = pathlib.Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    final = root / f"step-{step:08d}"
    tmp = root / f"step-{step:08d}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    optim_tensors, optim_plain = _flatten_optimizer(optimizer.state_dict())
    index = {
        "format": FORMAT,
        "step": step,
        "model": _write_shards(tmp, "model", model.state_dict(), max_bytes),
        "optim": _write_shards(tmp, "optim", optim_tensors, max_bytes),
        "extra": extra,
    }
    if average is not None:
        index["ema"] = {**_write_shards(tmp, "ema", average.averages, max_bytes), "updates": average.updates}
    trainer = {"optimizer": optim_plain, "scheduler": scheduler.state_dict(), "rng": _rng_state()}
    _atomic_write(tmp / "trainer.pt", lambda p: torch.save(trainer, p))
    _atomic_write(tmp / "checkpoint.json", lambda p: p.write_text(json.dumps(index, indent=1)))
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    _atomic_write(root / "latest", lambda p: p.write_text(final.name))
    others = sorted(p for p in root.glob("step-*") if p.is_dir() and p != final)
    for old in others[: max(0, len(others) - (keep - 1))]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def latest_checkpoint(run_dir) -> pathlib.Path | None:
    """The newest complete checkpoint folder of ``run_dir`` (None when there is none)."""
    root = pathlib.Path(run_dir) / "checkpoints"
    pointer = root / "latest"
    if pointer.is_file():
        folder = root / pointer.read_text().strip()
        if (folder / "checkpoint.json").is_file():
            return folder
    complete = sorted(p for p in root.glob("step-*") if (p / "checkpoint.json").is_file() and not p.name.endswith(".tmp"))
    return complete[-1] if complete else None


def load_model_weights(folder, model: torch.nn.Module) -> dict:
    """Load a checkpoint's weights into ``model`` (strict); returns its index (``step``, ``extra``)."""
    folder = pathlib.Path(folder)
    index = _read_index(folder)
    model.load_state_dict(_read_shards(folder, index["model"]))
    return index


def load_checkpoint(folder, model: torch.nn.Module, optimizer, scheduler, average: WeightAverage | None = None) -> int:
    """Restore model, optimizer, scheduler and RNG states, and ``average`` (when given) from the checkpoint's
    weight average, or from its raw weights when it has none (written without one, e.g. before --ema-decay);
    returns the step the checkpoint was taken after."""
    folder = pathlib.Path(folder)
    index = load_model_weights(folder, model)
    if average is not None and "ema" in index:
        average.load(_read_shards(folder, index["ema"]), int(index["ema"]["updates"]))
    elif average is not None:
        average.restart(model)
        print(f"{folder}: no weight average in this checkpoint; it starts from the checkpoint's weights")
    trainer = torch.load(folder / "trainer.pt", weights_only=False)
    optimizer.load_state_dict(_unflatten_optimizer(_read_shards(folder, index["optim"]), trainer["optimizer"]))
    scheduler.load_state_dict(trainer["scheduler"])
    _set_rng_state(trainer["rng"])
    return int(index["step"])


def _read_index(folder: pathlib.Path) -> dict:
    file = folder / "checkpoint.json"
    if not file.is_file():
        raise DataError(f"{folder} is not a complete checkpoint (no checkpoint.json)")
    index = json.loads(file.read_text())
    if index.get("format") != FORMAT:
        raise DataError(f"{file}: unknown checkpoint format {index.get('format')!r}")
    return index


def weights_for_use(folder) -> dict[str, torch.Tensor]:
    """A checkpoint's weights for use rather than for resuming (CPU tensors, by state-dict name): the raw
    weights with the weight average's float32 values in place of the parameters it holds, when it has one."""
    folder = pathlib.Path(folder)
    index = _read_index(folder)
    weights = _read_shards(folder, index["model"])
    if "ema" in index:
        weights.update(_read_shards(folder, index["ema"]))
    return weights


def read_weights(source) -> dict[str, torch.Tensor]:
    """Model weights (float32, CPU) from a checkpoint folder, a run folder's newest checkpoint (both as
    :func:`weights_for_use`) or a pretrained model file (:func:`codecsplat_warp.model.pretrained.save_pretrained`,
    e.g. the shipped default).

    Raises:
        DataError: ``source`` is neither a checkpoint, a run with one nor a readable safetensors file.
    """
    source = pathlib.Path(source)
    if source.is_dir():
        folder = source if (source / "checkpoint.json").is_file() else latest_checkpoint(source)
        if folder is None:
            raise DataError(f"{source}: no checkpoint there (expected a run folder with checkpoints/)")
        tensors = weights_for_use(folder)
    elif source.is_file():
        try:
            tensors = load_file(str(source))
        except Exception as exc:  # safetensors raises its own error types for a bad header
            raise DataError(f"{source} is not a readable safetensors file: {exc}") from None
    else:
        raise DataError(f"{source} is neither a run folder nor a model file")
    return {name: t.float() if t.is_floating_point() else t for name, t in tensors.items()}


def load_matching_weights(model: torch.nn.Module, tensors: dict[str, torch.Tensor]) -> tuple[list[str], list[str]]:
    """Copy every tensor whose name and shape ``model`` has (a warm start across architecture changes).

    Returns:
        (names of the model's tensors left at their initialisation, names of ``tensors`` not used).
    """
    state = model.state_dict()
    used = {name: t for name, t in tensors.items() if name in state and state[name].shape == t.shape}
    with torch.no_grad():
        for name, tensor in used.items():
            state[name].copy_(tensor)
    return sorted(set(state) - set(used)), sorted(set(tensors) - set(used))


def model_file_config(path, option: str) -> ModelConfig:
    """The network sizes stored in the metadata of the model file ``path`` (a CodecSplat safetensors file), named
    as the command-line ``option`` (e.g. ``--init``) in the errors: InputError when the file is missing, DataError
    when it is not a CodecSplat model file."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise InputError(f"{option} must name a model file, got {str(path)!r}")
    try:
        with safe_open(str(path), "pt") as f:
            metadata = f.metadata() or {}
        return ModelConfig.from_dict(json.loads(metadata["config"]))
    except Exception as exc:  # safetensors raises its own error types for a bad header
        raise DataError(f"{option} {path}: not a CodecSplat model file ({exc})") from None
