"""The one place where torch meets Warp: initialisation, devices, streams, dtypes and argument checks.

Rules every op in this package follows (and that this module implements):

* Warp is initialised once, lazily, on first use (:func:`init_warp`).
* An op takes its device from its input tensors (:func:`common_device`); tensors on different
  devices raise :class:`~codecsplat_warp.errors.DeviceMismatchError` naming the arguments.
* Every Warp launch runs on torch's *current* CUDA stream of that device (:func:`warp_scope`), so Warp
  work is ordered with the surrounding torch work without host synchronisation.
* Tensors cross to Warp zero-copy (:func:`to_warp`): ``wp.from_torch(t.detach(), requires_grad=False)``;
  gradients are returned as fresh tensors by the autograd Functions, never through Warp's grad arrays
  (wrapping a leaf that requires grad would double its gradient, Warp issue #159).
* Non-contiguous inputs are made contiguous deliberately (a copy only when needed) by
  :func:`check_tensor`; wrong shapes or dtypes raise :class:`~codecsplat_warp.errors.InputError`.
* Finite-value checks (one device-to-host sync each) run unless ``CODECSPLAT_VALIDATE=0`` is set or
  :func:`set_validation` turned them off, e.g. in a training loop whose inputs are known to be good.
"""

from __future__ import annotations

import contextlib
import os
import threading
from typing import Iterator, Mapping, Sequence

import torch
import warp as wp

from .errors import DeviceMismatchError, InputError

FLOAT_DTYPES: tuple[torch.dtype, ...] = (torch.float32, torch.float64)
"""Floating dtypes the Warp kernels are instantiated for (float32 for speed, float64 for gradchecks)."""

_TORCH_TO_WARP_DTYPE = {
    torch.float32: wp.float32,
    torch.float64: wp.float64,
    torch.int32: wp.int32,
    torch.int64: wp.int64,
    torch.uint8: wp.uint8,
}

if os.environ.get("CODECSPLAT_WARP_VERBOSE", "0") == "0":  # Warp logs every module load otherwise
    wp.config.log_level = wp.LOG_WARNING

_init_lock = threading.Lock()
_initialised = False
_validate = os.environ.get("CODECSPLAT_VALIDATE", "1") != "0"


def init_warp() -> None:
    """Initialise Warp once per process (quietly). Safe to call from any op, any thread."""
    global _initialised
    if _initialised:
        return
    with _init_lock:
        if not _initialised:
            wp.init()
            _initialised = True


def set_validation(enabled: bool) -> None:
    """Turn the finite-value checks of every op on or off (default: on, or ``CODECSPLAT_VALIDATE``)."""
    global _validate
    _validate = bool(enabled)


def validation_enabled() -> bool:
    """Whether ops check their inputs for NaN/Inf (each check costs one device sync)."""
    return _validate


def warp_dtype(dtype: torch.dtype):
    """Warp scalar type for a torch dtype (float32, float64, int32, int64, uint8)."""
    try:
        return _TORCH_TO_WARP_DTYPE[dtype]
    except KeyError:
        raise InputError(f"dtype {dtype} has no Warp counterpart here") from None


def warp_device(device: torch.device | str) -> "wp.context.Device":
    """The Warp device that aliases a torch device (``cpu`` or ``cuda:N``)."""
    init_warp()
    device = torch.device(device)
    if device.type == "cuda":
        index = torch.cuda.current_device() if device.index is None else device.index
        return wp.get_device(f"cuda:{index}")
    if device.type == "cpu":
        return wp.get_device("cpu")
    raise InputError(f"device {device} is not supported (cpu or cuda only)")


def resolve_device(name: str | torch.device | None) -> torch.device:
    """Turn a user's ``cpu`` / ``cuda`` / ``cuda:N`` / ``auto`` / None into a torch device.

    ``auto`` and None pick CUDA when torch sees a GPU, else the CPU.
    """
    if name is None or str(name) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError("device 'cuda' was asked for but torch sees no CUDA GPU")
    return device


def available_devices() -> list[torch.device]:
    """CPU plus every CUDA device torch can see, in that order."""
    return [torch.device("cpu")] + [torch.device(f"cuda:{i}") for i in range(torch.cuda.device_count())]


@contextlib.contextmanager
def warp_scope(device: torch.device) -> Iterator["wp.context.Device"]:
    """Context in which Warp launches for ``device`` run on torch's current stream of that device.

    Yields the Warp device to pass as ``device=`` to every ``wp.launch``. On the CPU this only
    initialises Warp.
    """
    wdev = warp_device(device)
    if device.type != "cuda":
        yield wdev
        return
    stream = wp.stream_from_torch(torch.cuda.current_stream(device))
    with wp.ScopedStream(stream, sync_enter=False):
        yield wdev


def to_warp(tensor: torch.Tensor, dtype=None, ndim: int | None = None):
    """Zero-copy Warp view of a contiguous tensor, never tracking gradients on the Warp side.

    ``dtype`` may be a Warp vector/matrix type whose trailing dimension(s) the tensor provides.
    """
    return wp.from_torch(tensor.detach(), dtype=dtype, requires_grad=False)


def common_device(**tensors: torch.Tensor | None) -> torch.device:
    """The device shared by all given tensors (None entries are skipped).

    Raises:
        DeviceMismatchError: naming each argument and its device when they differ.
        InputError: when no tensor is given.
    """
    present = {name: t for name, t in tensors.items() if t is not None}
    if not present:
        raise InputError("no tensor argument to take the device from")
    devices = {name: t.device for name, t in present.items()}
    first = next(iter(devices.values()))
    if any(d != first for d in devices.values()):
        listing = ", ".join(f"{n} on {d}" for n, d in devices.items())
        raise DeviceMismatchError(f"arguments are on different devices: {listing}")
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
    if tensor.dim() != len(shape):
        raise InputError(f"{name} must have shape {_shape_text(shape)}, got {tuple(tensor.shape)}")
    dims = {} if dims is None else dims
    for axis, (want, got) in enumerate(zip(shape, tensor.shape)):
        if want is None:
            continue
        if isinstance(want, str):
            bound = dims.setdefault(want, int(got))
            if bound != got:
                raise InputError(
                    f"{name} has {want}={got} on axis {axis} but another argument has {want}={bound}"
                )
        elif want != got:
            raise InputError(f"{name} must have shape {_shape_text(shape)}, got {tuple(tensor.shape)}")
    if tensor.dtype not in dtypes:
        allowed = ", ".join(str(d).replace("torch.", "") for d in dtypes)
        raise InputError(f"{name} must have dtype {allowed}, got {str(tensor.dtype).replace('torch.', '')}")
    return tensor.contiguous()


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
    flags = [torch.isfinite(t).all() for t in finite.values()]
    flags += [(torch.isfinite(t) & (t > 0)).all() for t in positive.values()]
    if not flags or all(torch.stack(flags).tolist()):
        return
    for name, t in finite.items():
        check_finite(name, t)
    for name, t in positive.items():
        check_positive(name, t)


def _shape_text(shape: Sequence[int | str | None]) -> str:
    return "[" + ",".join("*" if s is None else str(s) for s in shape) + "]"


def describe_devices(devices: Mapping[str, torch.device] | None = None) -> str:
    """One line per available device, for ``selfcheck`` and benchmark headers."""
    lines = []
    for dev in available_devices():
        if dev.type == "cuda":
            lines.append(f"{dev}: {torch.cuda.get_device_name(dev)}")
        else:
            import platform

            lines.append(f"cpu: {platform.processor() or platform.machine()} ({os.cpu_count()} logical cores)")
    return "\n".join(lines)
