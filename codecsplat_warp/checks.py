"""Argument checks of every op: devices, shapes, dtypes and values, with errors that name the argument.

* An op takes its device from its input tensors (:func:`common_device`); tensors on different devices raise
  :class:`~codecsplat_warp.errors.DeviceMismatchError` naming the arguments.
* Non-contiguous inputs are made contiguous deliberately (a copy only when needed) by :func:`check_tensor`; wrong
  shapes or dtypes raise :class:`~codecsplat_warp.errors.InputError`.
* Finite-value checks (one device-to-host sync each) run unless ``CODECSPLAT_VALIDATE=0`` is set or
  :func:`set_validation` turned them off, e.g. in a training loop whose inputs are known to be good.

Pure torch: no Warp here (the Warp runtime is :mod:`codecsplat_warp.device`).
"""

from __future__ import annotations

import contextlib
import os
from typing import Iterator, Sequence

import torch

from .errors import DeviceMismatchError, InputError

FLOAT_DTYPES: tuple[torch.dtype, ...] = (torch.float32, torch.float64)
"""Floating dtypes the ops take and the Warp kernels are instantiated for (float32: speed, float64: gradchecks)."""

_validate = os.environ.get("CODECSPLAT_VALIDATE", "1") != "0"


def set_validation(enabled: bool) -> None:
    """Turn the finite-value checks of every op on or off (default: on, or ``CODECSPLAT_VALIDATE``)."""
    global _validate
    _validate = bool(enabled)


def validation_enabled() -> bool:
    """Whether ops check their inputs for NaN/Inf (each check costs one device sync)."""
    return _validate


@contextlib.contextmanager
def validation(enabled: bool) -> Iterator[None]:
    """Inside the block, ops check their inputs for NaN/Inf only if ``enabled`` (:func:`set_validation`); the
    setting before it comes back afterwards. Loops over inputs that one check already covered turn it off."""
    saved = _validate
    set_validation(enabled)
    try:
        yield
    finally:
        set_validation(saved)

def common_device(**tensors: torch.Tensor | None) -> torch.device:
    """The device shared by all given tensors (None entries are skipped).

    Raises:
        DeviceMismatchError: naming each argument and its device when they differ.
        InputError: when no tensor is given.
    """
    first = None
    for tensor in tensors.values():
        if tensor is not None:
            if first is None:
                first = tensor.device
            elif tensor.device != first:
                listing = ", ".join(f"{n} on {t.device}" for n, t in tensors.items() if t is not None)
                raise DeviceMismatchError(f"arguments are on different devices: {listing}")
    if first is None:
        raise InputError("no tensor argument to take the device from")
    return first


def check_tensor(
    name: str,
    tensor: object,
    shape: Sequence[int | str | None],
    dtypes: Sequence[torch.dtype] = FLOAT_DTYPES,
    dims: dict[str, int] | None = None,
) -> torch.Tensor:
    """Check one tensor argument and return it contiguous.

    Args:
        name: argument name used in error messages.
        tensor: the value passed by the caller.
        shape: expected shape; an int must match exactly, ``None`` matches anything, and a string is a
            symbol (``"V"``, ``"C"``) that must take the same value in every tensor checked with the same
            ``dims`` dictionary (filled in as symbols are first seen).
        dtypes: allowed dtypes.
        dims: shared symbol table for consistency checks between arguments.

    Raises:
        InputError: not a tensor, wrong rank, wrong size or wrong dtype (message names ``name``).
    """
    if not isinstance(tensor, torch.Tensor):
        raise InputError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
    sizes = tensor.shape
    if len(sizes) != len(shape):
        raise InputError(f"{name} must have shape {_shape_text(shape)}, got {tuple(sizes)}")
    if dims is None:
        dims = {}
    for axis, want in enumerate(shape):
        if want.__class__ is str:
            got = sizes[axis]
            bound = dims.setdefault(want, got)
            if bound != got:
                raise InputError(
                    f"{name} has {want}={got} on axis {axis} but another argument has {want}={bound}"
                )
        elif want is not None and want != sizes[axis]:
            raise InputError(f"{name} must have shape {_shape_text(shape)}, got {tuple(sizes)}")
    if tensor.dtype not in dtypes:
        allowed = ", ".join(str(d).replace("torch.", "") for d in dtypes)
        raise InputError(f"{name} must have dtype {allowed}, got {str(tensor.dtype).replace('torch.', '')}")
    return tensor if tensor.is_contiguous() else tensor.contiguous()


def check_same_dtype(**tensors: torch.Tensor | None) -> torch.dtype:
    """The dtype shared by all given floating tensors; InputError naming them if they differ."""
    present = {n: t for n, t in tensors.items() if t is not None}
    dtypes = {n: t.dtype for n, t in present.items()}
    first = next(iter(dtypes.values()))
    if any(d != first for d in dtypes.values()):
        listing = ", ".join(f"{n}: {str(d).replace('torch.', '')}" for n, d in dtypes.items())
        raise InputError(f"arguments must share one float dtype, got {listing}")
    return first


def check_finite(name: str, tensor: torch.Tensor) -> None:
    """InputError if ``tensor`` holds NaN or Inf (skipped when validation is off; one device sync)."""
    if _validate and tensor.numel() and not bool(torch.isfinite(tensor).all()):
        bad = int((~torch.isfinite(tensor)).sum())
        raise InputError(f"{name} holds {bad} non-finite value(s) (NaN or Inf)")


def check_positive(name: str, tensor: torch.Tensor) -> None:
    """InputError if any value of ``tensor`` is <= 0 or non-finite (skipped when validation is off)."""
    check_finite(name, tensor)
    if _validate and tensor.numel() and not bool((tensor > 0).all()):
        bad = int((tensor <= 0).sum())
        raise InputError(f"{name} must be > 0 everywhere, {bad} value(s) are not")


def check_values(
    finite: dict[str, torch.Tensor] | None = None, positive: dict[str, torch.Tensor] | None = None
) -> None:
    """Finite (and, for ``positive``, > 0) checks of several tensors with ONE device-to-host sync.

    Skipped when validation is off. Raises InputError through :func:`check_finite` / :func:`check_positive`
    (which name the argument and count the bad values) for the first failing tensor.
    """
    if not _validate:
        return
    finite, positive = finite or {}, positive or {}
    # Reductions to scalars, no per-element temporaries: NaN/Inf anywhere make the sum non-finite. A sum that
    # overflows on finite values only sends us to the exact per-element checks below, which then pass.
    flags = [torch.isfinite(t.sum()) for t in finite.values()]
    flags += [torch.isfinite(t.sum()) & (t.min() > 0) for t in positive.values() if t.numel()]
    if not flags or all(torch.stack(flags).tolist()):
        return
    for name, t in finite.items():
        check_finite(name, t)
    for name, t in positive.items():
        check_positive(name, t)


def _shape_text(shape: Sequence[int | str | None]) -> str:
    return "[" + ",".join("*" if s is None else str(s) for s in shape) + "]"
