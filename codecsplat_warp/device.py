"""The one place where torch meets Warp: initialisation, devices, streams, dtypes, launches and host reads.

Rules every op in this package follows (and that this module implements; argument checks are in
:mod:`codecsplat_warp.checks`, Warp's native sort and scan and concurrent CPU launches in
:mod:`codecsplat_warp.ops.primitives`):

* Warp is initialised once, lazily, on first use (:func:`init_warp`), without its CUDA driver warning on a
  machine that has no NVIDIA driver (:func:`cuda_driver_missing` tells whether it had one).
* CPU work runs on :func:`cpu_threads` threads (``$CODECSPLAT_THREADS``, else the available cores), torch's
  intra-op pool included (:func:`set_cpu_threads`). The ``codecsplat`` command keeps the memory it frees for its
  next allocations (:func:`keep_freed_memory`).
* Every Warp launch runs on torch's *current* CUDA stream of that device (:func:`warp_scope`), so Warp
  work is ordered with the surrounding torch work without host synchronisation.
* Tensors cross to Warp zero-copy (:func:`to_warp`): ``wp.from_torch(t.detach(), requires_grad=False)``;
  gradients are returned as fresh tensors by the autograd Functions, never through Warp's grad arrays
  (wrapping a leaf that requires grad would double its gradient, Warp issue #159).
* Kernels are launched through :func:`launch`, which checks and records a launch once per combination of
  argument types (or per ``layout`` the op names) and thread, and then replays it with tensors as raw array
  descriptors, calling CPU kernels directly on a persistent argument struct (low host overhead).
* Small int64 results go to the host through a pinned buffer and an event (:func:`stage_host_values`), so that
  the host waits for that copy only, not for the whole stream.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import gc
import os
import sys
import tempfile
import threading
from typing import Hashable, Iterator, NamedTuple, Sequence

import torch
import warp as wp
from warp._src import context as warp_context  # Launch internals the replay relies on (see _Command)
from warp._src.types import array_t  # the descriptor type wp.from_torch(return_ctype=True) returns

from .errors import InputError

_UNSIGNED_WIDE = (torch.uint32, torch.uint16)
"""Unsigned dtypes that ``wp.from_torch`` does not take, wrapped by :func:`to_warp` itself."""

_TORCH_TO_WARP_DTYPE = {
    torch.float32: wp.float32,
    torch.float64: wp.float64,
    torch.int32: wp.int32,
    torch.int64: wp.int64,
    torch.uint32: wp.uint32,
    torch.uint16: wp.uint16,
    torch.uint8: wp.uint8,
}

if os.environ.get("CODECSPLAT_WARP_VERBOSE", "0") == "0":  # Warp logs every module load otherwise
    wp.config.log_level = wp.LOG_WARNING

_init_lock = threading.Lock()
_initialised = False
_cuda_driver_missing = False

CUDA_DRIVER_WARNING = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver."
"""The start of the line Warp's native library prints on stderr when it finds no CUDA driver, on every
initialisation of a machine without a GPU: :func:`init_warp` keeps it off stderr."""


def init_warp() -> None:
    """Initialise Warp once per process (quietly: without its CUDA driver warning, see
    :func:`cuda_driver_missing`; anything else Warp prints on stderr is kept). Safe to call from any op, any
    thread."""
    global _initialised, _cuda_driver_missing
    if _initialised:
        return
    with _init_lock:
        if not _initialised:
            with _native_stderr_without(CUDA_DRIVER_WARNING) as dropped:
                wp.init()
            _cuda_driver_missing = bool(dropped)
            _initialised = True


def cuda_driver_missing() -> bool:
    """Whether Warp found no CUDA driver when it was initialised (a machine without an NVIDIA GPU); initialises
    Warp."""
    init_warp()
    return _cuda_driver_missing


@contextlib.contextmanager
def _native_stderr_without(line_start: str):
    """Capture what is written to file descriptor 2 (native code included) inside the block, then write it to
    stderr without the lines that start with ``line_start``; yields the list that receives the dropped lines."""
    dropped: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as capture:
            os.dup2(capture.fileno(), 2)
            try:
                yield dropped
            finally:
                sys.stderr.flush()
                os.dup2(saved, 2)
                capture.seek(0)
                text = capture.read().decode(errors="replace")
    finally:
        os.close(saved)
    lines = text.splitlines(keepends=True)
    dropped.extend(line for line in lines if line.startswith(line_start))
    kept = "".join(line for line in lines if not line.startswith(line_start))
    if kept:
        sys.stderr.write(kept)
        sys.stderr.flush()


THREADS_VARIABLE = "CODECSPLAT_THREADS"
"""Environment variable with the number of threads CPU work uses (see :func:`cpu_threads`)."""

_threads: int | None = None


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity is not None else os.cpu_count() or 1


def cpu_threads() -> int:
    """Threads the Warp launches that the ops split run on (see
    :func:`codecsplat_warp.ops.primitives.run_concurrently`): the count of :func:`set_cpu_threads`, else
    ``$CODECSPLAT_THREADS`` (which then sets torch's intra-op count too), else :func:`available_cores`.

    Raises:
        InputError: ``$CODECSPLAT_THREADS`` is not a positive integer.
    """
    global _threads
    if _threads is None:
        if _threads_variable() is None:
            _threads = available_cores()
        else:
            set_cpu_threads()
    return _threads


def set_cpu_threads(count: int | None = None) -> int:
    """Run CPU work on ``count`` threads from now on (None: ``$CODECSPLAT_THREADS``, else the available cores): the
    Warp launches that the ops split and torch's intra-op pool alike. Either runs while the other waits, so the two
    never take more cores than this between them. Returns the count.

    Raises:
        InputError: ``count`` (or ``$CODECSPLAT_THREADS``) is not a positive integer.
    """
    global _threads
    if count is None:
        count = _threads_variable() or available_cores()
    elif isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise InputError(f"the thread count must be a positive integer, got {count!r}")
    if torch.get_num_threads() != count:
        torch.set_num_threads(count)
    _threads = count
    return count


def _threads_variable() -> int | None:
    """``$CODECSPLAT_THREADS`` as a positive int, None when unset or empty; InputError for anything else."""
    text = os.environ.get(THREADS_VARIABLE, "").strip()
    if not text:
        return None
    count = int(text) if text.isdigit() else 0
    if count < 1:
        raise InputError(f"${THREADS_VARIABLE} must be a positive integer, got {text!r}")
    return count


FREED_MEMORY_VARIABLE = "CODECSPLAT_KEEP_FREED_MEMORY"
"""Environment variable: ``0`` has the ``codecsplat`` command give the memory it frees back to the system as the C
library decides, ``1`` (or unset) keeps it (:func:`keep_freed_memory`)."""

_MALLOPT_TRIM_THRESHOLD, _MALLOPT_MMAP_MAX = -1, -4
"""glibc's ``mallopt`` parameters ``M_TRIM_THRESHOLD`` and ``M_MMAP_MAX`` (malloc.h)."""

_freed_memory_kept = False


def keep_freed_memory() -> bool:
    """Keep the memory this process frees for its next allocations instead of giving it back to the system, where
    the C library is glibc (Linux): large blocks are no longer mapped from the system and unmapped one by one, and
    the heap's top is not trimmed (``mallopt``). A step of RDO or training on the CPU allocates its large tensors
    afresh each time (the decoder's full-resolution activations are 33.5 MB with 2 views at 256x256), and every
    page of a freshly mapped block faults when it is first written: on the 2-core EPYC an RDO step took 2.25-2.38 s
    before and 1.89-1.90 s after (2026-11-27). The resident size then stays near its peak for the rest of the
    process. Process-wide and not undone; the ``codecsplat`` command calls it (and its worker processes) unless
    ``$CODECSPLAT_KEEP_FREED_MEMORY`` is 0. Returns whether it applied (False where the C library is not glibc)."""
    global _freed_memory_kept
    if not _freed_memory_kept:
        libc = _glibc()
        if libc is None:
            return False
        no_mapping = libc.mallopt(_MALLOPT_MMAP_MAX, 0)
        _freed_memory_kept = bool(no_mapping and libc.mallopt(_MALLOPT_TRIM_THRESHOLD, 2**31 - 1))
    return _freed_memory_kept


def freed_memory_kept() -> bool:
    """Whether :func:`keep_freed_memory` applied in this process."""
    return _freed_memory_kept


def freed_memory_wanted() -> bool:
    """``$CODECSPLAT_KEEP_FREED_MEMORY`` as a bool: False for ``0``, True for ``1`` or unset (or empty); InputError
    for anything else."""
    text = os.environ.get(FREED_MEMORY_VARIABLE, "").strip()
    if text not in ("", "0", "1"):
        raise InputError(f"${FREED_MEMORY_VARIABLE} must be 0 or 1, got {text!r}")
    return text != "0"


@contextlib.contextmanager
def cudnn_autotuned(device: torch.device) -> Iterator[None]:
    """On a CUDA ``device``, cuDNN's algorithm search on inside the block (``torch.backends.cudnn.benchmark``): the
    first convolution of each shape times cuDNN's algorithms and keeps the fastest for the process; the flag's
    former value is given back when the block ends, however it ends. Elsewhere nothing changes.

    For loops that run the same convolutions many times (the RDO decoder's CUDA graphs). The search picks by
    timing, so two processes may pick differently and round differently; on CUDA a run does not repeat bit for bit
    anyway (the rasterizer's gradients are atomic sums). A shape that already ran in the process with cuDNN's
    heuristics keeps the algorithm they chose (torch's plan cache does not key on the flag)."""
    if device.type != "cuda":
        yield
        return
    searching = torch.backends.cudnn.benchmark
    torch.backends.cudnn.benchmark = True
    try:
        yield
    finally:
        torch.backends.cudnn.benchmark = searching


def _glibc():
    """The process's C library when it is glibc (it has ``gnu_get_libc_version``), else None."""
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018 - only glibc has it
    except (OSError, AttributeError):
        return None
    return libc


def warp_dtype(dtype: torch.dtype):
    """Warp scalar type for a torch dtype (float32, float64, int32, int64, uint32, uint16, uint8)."""
    try:
        return _TORCH_TO_WARP_DTYPE[dtype]
    except KeyError:
        raise InputError(f"dtype {dtype} has no Warp counterpart here") from None


_WARP_DEVICES: dict = {}
"""torch device (or name) -> Warp device, for devices that name one device (``cpu``, ``cuda:N``)."""


def warp_device(device: torch.device | str) -> "wp.context.Device":
    """The Warp device that aliases a torch device (``cpu`` or ``cuda:N``)."""
    cached = _WARP_DEVICES.get(device)
    if cached is not None:
        return cached
    init_warp()
    resolved = torch.device(device)
    if resolved.type == "cuda":
        index = torch.cuda.current_device() if resolved.index is None else resolved.index
        wdev = wp.get_device(f"cuda:{index}")
    elif resolved.type == "cpu":
        wdev = wp.get_device("cpu")
    else:
        raise InputError(f"device {resolved} is not supported (cpu or cuda only)")
    if resolved.type == "cpu" or resolved.index is not None:
        _WARP_DEVICES[device] = wdev
    return wdev


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
def capture_guard(device: torch.device) -> Iterator[None]:
    """Run a CUDA graph capture on ``device`` (its body) safely in a long process: Python's garbage collector is held
    off until the capture ends; when the body raises, torch's CUDA generator of ``device`` is taken out of the
    capturing state a failed capture leaves it in and given back the state it had before, and the error propagates.

    Why: a capture records the stream's work and forbids the CUDA calls that would act on the device at once;
    freeing a CUDA graph (``cuGraphExecDestroy``) is one of them. Graphs that only Python's cyclic garbage
    collector frees (objects that refer to each other) were freed when the collector happened to run in the middle
    of a later capture: the capture was invalidated (``cudaErrorStreamCaptureInvalidated``; seen in a long process,
    ``pytest -m cuda`` run whole), and torch's CUDA generator, left in its capturing state, refused every random
    draw after it ("Offset increment outside graph capture"). Holding the collector off is enough, so no collection
    runs first: in ``bench rdo`` (H200) one made a ``medium`` encode, forward graphs off, take 0.85 s against 0.43."""
    collecting = gc.isenabled()
    gc.disable()
    rng_state = torch.cuda.get_rng_state(device)
    try:
        yield
    except BaseException:
        _end_generator_capture(device)
        torch.cuda.set_rng_state(rng_state, device)
        raise
    finally:
        if collecting:
            gc.enable()


@contextlib.contextmanager
def cuda_graph_capture(graph: torch.cuda.CUDAGraph, device: torch.device) -> Iterator[None]:
    """Capture the work the block queues on ``device`` into ``graph`` (errors of other threads' CUDA calls not
    counted, ``capture_error_mode="thread_local"``), inside :func:`capture_guard`. The block runs on a side stream
    that first waits for the current stream's work; a replay runs on the stream current at the time.

    Unlike ``torch.cuda.graph``, it neither synchronises the device nor empties torch's memory caches before the
    capture: a capture that an optimisation's step makes (a rasterizer's forward graph, when the counts outgrow it)
    then costs about what its launches cost, and the allocations after it are not sent back to ``cudaMalloc``. When
    the block raises, its error propagates (not the one ending the broken capture gives)."""
    side = torch.cuda.Stream(device=device)
    side.wait_stream(torch.cuda.current_stream(device))
    with capture_guard(device), torch.cuda.stream(side):
        graph.capture_begin(capture_error_mode="thread_local")
        try:
            yield
        except BaseException:
            with contextlib.suppress(Exception):
                graph.capture_end()
            raise
        graph.capture_end()


def _end_generator_capture(device: torch.device) -> None:
    """Take torch's CUDA generator of ``device`` out of the capturing state that a capture which failed before its
    end leaves it in (its prologue ran, its epilogue did not): one trivial capture runs both."""
    with torch.cuda.device(device):
        torch.cuda.synchronize(device)
        scratch = torch.zeros(1, device=device)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            scratch.add_(1.0)
        del graph


@contextlib.contextmanager
def warp_capture(device: torch.device) -> Iterator[list]:
    """Tell Warp that torch's current stream of the CUDA ``device`` is being captured (by a capture entered before,
    :func:`cuda_graph_capture`): inside the block Warp's launches keep their modules loaded for the graph and its
    temporary buffers (e.g. its scan's) are freed when the graph is, not at once (which a capture forbids). Yields a
    list that holds Warp's record of the capture once the block ends: keep it as long as the captured graph."""
    wdev = warp_device(device)
    stream = _warp_stream(wdev, torch._C._cuda_getCurrentRawStream(wdev.ordinal))
    wp.capture_begin(device=wdev, stream=stream, external=True)
    record: list = []
    try:
        yield record
    except BaseException:
        with contextlib.suppress(Exception):  # the capture's own error is the one to report
            wp.capture_end(device=wdev, stream=stream)
        raise
    record.append(wp.capture_end(device=wdev, stream=stream))


def warp_scope(device: torch.device) -> "_WarpScope":
    """Context in which Warp launches for ``device`` run on torch's current stream of that device.

    Yields the Warp device to pass as ``device=`` to every ``wp.launch``. On the CPU this only
    initialises Warp.
    """
    return _WarpScope(device)


class _WarpScope:
    """The context manager :func:`warp_scope` returns (a class: cheaper to enter than a generator).

    On CUDA it sets the Warp device's current stream to torch's current stream of the device (restored on exit;
    nothing to do when it already is, as in a nested scope) and, when torch's current device is another one, makes
    the device's CUDA context current (Warp's native radix sort runs in the current context). Cheaper than
    ``wp.ScopedStream(wp.stream_from_torch(...))``, which took 19.5 us per enter and exit on a lent H100's host:
    the raw stream handle is read without making a ``torch.cuda.Stream``, and no device scope is entered when
    none is needed."""

    __slots__ = ("device", "warp_device", "saved_stream", "device_scope")

    def __init__(self, device: torch.device):
        self.device = device
        self.saved_stream = None
        self.device_scope = None

    def __enter__(self) -> "wp.context.Device":
        wdev = self.warp_device = warp_device(self.device)
        if self.device.type == "cuda":
            index = wdev.ordinal
            if torch.cuda.current_device() != index:
                self.device_scope = wp.ScopedDevice(wdev)
                self.device_scope.__enter__()
            stream = _warp_stream(wdev, torch._C._cuda_getCurrentRawStream(index))
            if wdev.stream is not stream:
                self.saved_stream = wdev.stream
                wdev.set_stream(stream, sync=False)
        return wdev

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        if self.saved_stream is not None:
            self.warp_device.set_stream(self.saved_stream, sync=False)
            self.saved_stream = None
        if self.device_scope is not None:
            self.device_scope.__exit__(exc_type, exc_value, traceback)
            self.device_scope = None


_warp_streams: dict[tuple[int, int], "wp.Stream"] = {}


def _warp_stream(wdev, handle: int) -> "wp.Stream":
    """The Warp stream wrapping the CUDA stream ``handle`` (a torch stream's ``cuda_stream``) of Warp device
    ``wdev``, created once per (device, handle); it does not own the stream."""
    key = (wdev.ordinal, handle)
    stream = _warp_streams.get(key)
    if stream is None:
        stream = _warp_streams[key] = wp.Stream(wdev, cuda_stream=handle)
    return stream


_pinned = threading.local()
"""This thread's staging for :func:`stage_host_values`: ``buffer``, a pinned int64 tensor, and ``address``, its
host address; ``events``, one Warp event per CUDA device ordinal; ``generation``, how many reads were staged (a
read is valid until the next one)."""


class HostValues:
    """Values of a small int64 tensor on their way to the host (made by :func:`stage_host_values`): either read
    already (``ready``, on the CPU) or ``count`` values at pinned host ``address`` behind a Warp ``event``."""

    __slots__ = ("ready", "address", "count", "event", "generation")

    def __init__(self, ready: list | None, address: int = 0, count: int = 0, event=None, generation: int = 0):
        self.ready = ready
        self.address = address
        self.count = count
        self.event = event
        self.generation = generation

    def values(self) -> list:
        """The values as a list of ints; on CUDA this waits for the copy only, not for later work on the stream.

        Raises:
            RuntimeError: a later :func:`stage_host_values` in this thread has reused the staging buffer.
        """
        if self.ready is not None:
            return self.ready
        if _pinned.generation != self.generation:
            raise RuntimeError("a later stage_host_values in this thread reused the buffer of this read")
        warp_context.runtime.core.wp_cuda_event_synchronize(self.event.cuda_event)
        return list((ctypes.c_int64 * self.count).from_address(self.address))


def stage_host_values(tensor: torch.Tensor, wdev, start: int = 0, count: int | None = None) -> HostValues:
    """Start reading ``tensor[start : start + count]`` (all from ``start`` when ``count`` is None) of a contiguous
    1-D int64 tensor back to the host, as it is once the work queued so far has run (no slice is made);
    :meth:`HostValues.values` finishes the read.

    On CUDA (inside :func:`warp_scope`, whose Warp device ``wdev`` is) the values go through this thread's pinned
    buffer: one asynchronous copy on torch's current stream and an event after it, by Warp's native calls (a
    torch ``copy_`` and ``tolist`` cost 10 us more per read on a lent H100's host), so that the host can queue more
    work on the stream before it waits, and then waits for the copy alone (a ``tolist`` of the device tensor syncs
    the whole stream). One read per thread at a time: staging the next one invalidates the previous one. On the
    CPU the values are read at once.

    Raises:
        InputError: not a contiguous 1-D int64 tensor, or the range is not inside it.
        RuntimeError: the copy could not be queued.
    """
    count = _read_count("stage_host_values", tensor, start, count)
    if not tensor.is_cuda:
        return HostValues(tensor[start : start + count].tolist())
    if not hasattr(_pinned, "events"):
        _pinned.buffer, _pinned.address, _pinned.events, _pinned.generation = None, 0, {}, 0
    if _pinned.buffer is None or _pinned.buffer.numel() < count:
        for event in _pinned.events.values():  # copies still on their way into the old buffer land first
            warp_context.runtime.core.wp_cuda_event_synchronize(event.cuda_event)
        _pinned.buffer = torch.empty(max(count, 1024), dtype=torch.int64, pin_memory=True)
        _pinned.address = _pinned.buffer.data_ptr()
    event = _pinned.events.get(wdev.ordinal)
    if event is None:
        event = _pinned.events[wdev.ordinal] = wp.Event(wdev)
    _queue_copy(tensor, wdev, start, count, _pinned.address)
    warp_context.runtime.core.wp_cuda_event_record(event.cuda_event, wdev.stream.cuda_stream, False)
    _pinned.generation += 1
    return HostValues(None, _pinned.address, count, event, _pinned.generation)


def _read_count(reader: str, tensor: torch.Tensor, start: int, count: int | None) -> int:
    """How many values ``reader`` reads from ``tensor`` at ``start`` (``count``; None: all from ``start``).

    Raises:
        InputError: not a contiguous 1-D int64 tensor, or the range is not inside it.
    """
    if tensor.dtype != torch.int64 or tensor.dim() != 1 or not tensor.is_contiguous():
        raise InputError(f"{reader} reads a contiguous 1-D int64 tensor")
    length = tensor.shape[0]
    count = length - start if count is None else count
    if not (0 <= start and 0 <= count and start + count <= length):
        raise InputError(f"{reader}: values [{start}, {start + count}) are not inside a tensor of {length}")
    return count


def _queue_copy(tensor: torch.Tensor, wdev, start: int, count: int, address: int) -> None:
    """Queue the copy of ``count`` int64 values of the CUDA ``tensor`` from ``start`` on to the pinned host
    ``address`` on Warp's current stream of ``wdev``."""
    source = tensor.data_ptr() + 8 * start
    if count and not warp_context.runtime.core.wp_memcpy_d2h(wdev.context, address, source, 8 * count,
                                                             wdev.stream.cuda_stream):  # fmt: skip
        raise RuntimeError(f"Warp could not queue a device-to-host copy: {warp_context.runtime.get_error_string()}")


class PinnedRead:
    """A read of ``count`` int64 values of a CUDA tensor into a pinned host buffer of its own, behind an event of its
    own: for a read that a CUDA graph captures (the graph keeps the buffer's address; the event is an external one,
    which a graph records as a node that the host can wait for; :func:`stage_host_values` shares one buffer per
    thread). :meth:`stage` queues it (with :func:`stage_host_values`' arguments, inside
    :func:`warp_scope`), :meth:`values` waits for the last one queued or replayed and returns it."""

    def __init__(self, count: int):
        self.count = count
        self.buffer = torch.empty(max(count, 1), dtype=torch.int64, pin_memory=True)
        self.address = self.buffer.data_ptr()
        self.event = torch.cuda.Event(external=True)

    def stage(self, tensor: torch.Tensor, wdev, start: int, count: int) -> "PinnedRead":
        """Queue the read of ``tensor[start : start + count]`` (a contiguous 1-D int64 CUDA tensor, ``count`` as
        given to the constructor) on Warp's current stream of ``wdev``, which :func:`warp_scope` made torch's current
        stream; returns this read.

        Raises:
            InputError: another count, or not a contiguous 1-D int64 tensor holding the range.
        """
        if count != self.count:
            raise InputError(f"a PinnedRead of {self.count} values cannot read {count}")
        _read_count("PinnedRead", tensor, start, count)
        _queue_copy(tensor, wdev, start, count, self.address)
        self.event.record(torch.cuda.current_stream(tensor.device))
        return self

    def values(self) -> list:
        """The values as a list of ints, once the copy has landed (waits for it alone)."""
        self.event.synchronize()
        return list((ctypes.c_int64 * self.count).from_address(self.address))


def to_warp(tensor: torch.Tensor, dtype=None):
    """Zero-copy Warp view of a contiguous tensor, never tracking gradients on the Warp side.

    ``dtype`` may be a Warp vector/matrix type whose trailing dimension(s) the tensor provides.
    """
    if tensor.dtype in _UNSIGNED_WIDE:  # wp.from_torch does not take these (scalar elements only here)
        size = tensor.element_size()
        array = wp.array(ptr=tensor.data_ptr(), dtype=_TORCH_TO_WARP_DTYPE[tensor.dtype], shape=tuple(tensor.shape),
                         strides=tuple(size * s for s in tensor.stride()), device=warp_device(tensor.device))  # fmt: skip
        array._tensor = tensor  # keeps the memory alive, as wp.from_torch does
        return array
    return wp.from_torch(tensor.detach(), dtype=dtype, requires_grad=False)


class Grouped(NamedTuple):
    """A tensor whose trailing ``element_rank`` dimensions (1: vectors, 2: matrices) form Warp vectors or matrices
    (made by :func:`vectors` and :func:`matrices`, consumed by :func:`launch`)."""

    tensor: torch.Tensor
    element_rank: int

    @property
    def inner(self) -> tuple[int, ...]:
        """The element shape: the tensor's trailing ``element_rank`` sizes."""
        return tuple(self.tensor.shape[-self.element_rank :])


def vectors(tensor: torch.Tensor) -> Grouped:
    """``tensor [..., n]`` as a Warp array of n-vectors of its scalar dtype, for :func:`launch`."""
    return Grouped(tensor, 1)


def matrices(tensor: torch.Tensor) -> Grouped:
    """``tensor [..., r, c]`` as a Warp array of r x c matrices of its scalar dtype, for :func:`launch`."""
    return Grouped(tensor, 2)


_RESOLVED_OVERLOADS: dict[tuple, tuple] = {}
"""(kernel, adjoint, argument type keys) -> (concrete overload, Warp element dtype of every argument: None for
scalars and None)."""

_resolve_lock = threading.Lock()
_thread_state = threading.local()
"""``commands``: this thread's recorded launches (a ``wp.Launch`` is mutable, so threads never share one)."""


def launch(
    kernel,
    dim,
    args: Sequence,
    device,
    *,
    adj_args: Sequence | None = None,
    block_dim: int | None = None,
    layout: Hashable = None,
) -> None:
    """Launch a Warp kernel on tensors zero-copy, with Warp's per-launch argument processing paid once.

    The first launch of ``kernel`` with a combination of argument types (torch dtype, rank and grouped
    trailing shape of every tensor, type of every scalar) on a device, in a thread, wraps the tensors as
    ``wp.array`` and goes through all of Warp's argument checks (instantiating the concrete overload of a
    generic kernel), then records the launch as a ``wp.Launch`` command (``record_cmd=True``). Later launches
    with the same types replay that command: every tensor's data pointer is written into the recorded array
    descriptor (which holds no reference to it: the command keeps no tensor alive), its shape only when it
    changed, scalars are written in place, the launch dimensions are updated when they change, and the kernel
    is called (on the CPU directly on one persistent argument struct, on CUDA by Warp's native launch call).
    Nothing runs when a launch dimension is 0.

    Args:
        kernel: a ``@wp.kernel``, generic (``typing.Any`` annotations) or concrete.
        dim: launch dimensions (an int or up to 4 ints).
        args: every kernel argument in order (inputs and outputs alike): contiguous tensors (arrays of their
            scalar dtype and rank), :func:`vectors` / :func:`matrices` of contiguous tensors, Python ints,
            or Warp scalars such as ``wp.float64(x)`` for ``Any`` scalar parameters.
        device: the Warp device yielded by :func:`warp_scope` (the launch must run inside that scope).
        adj_args: given for an adjoint launch (``adjoint=True``): the adjoint of every argument, in the
            same forms (None for arrays without gradient, zero scalars for scalars).
        block_dim: lanes per block of a tiled kernel (``wp.launch_tiled``); None for a plain launch.
        layout: optional hashable that determines the type of every argument (e.g. the dtypes an op
            instantiates the kernel for); given, the per-argument type keys are not computed, which saves
            host time on every launch. The caller guarantees that launches of ``kernel`` with equal layouts
            pass arguments of equal types (a tensor of another dtype or rank would be misread).

    Raises:
        InputError: a tensor argument is not contiguous, or has no dimension left outside its vector or
            matrix elements.
    """
    dims = (dim,) if isinstance(dim, int) else tuple(dim)
    if 0 in dims:
        return
    adjoint = adj_args is not None
    adj_args = adj_args or ()
    explicit = layout is not None
    if not explicit:
        layout = (*map(_type_key, args), *map(_type_key, adj_args))
    key = (kernel, adjoint, block_dim, device.alias, explicit, layout)
    commands = _thread_commands()
    command = commands.get(key)
    if command is None:
        commands[key] = _Command.first_launch(kernel, dims, args, adj_args, adjoint, block_dim, device)
    else:
        command.replay(dims, (*args, *adj_args) if adjoint else args)


def _thread_commands() -> dict:
    commands = getattr(_thread_state, "commands", None)
    if commands is None:
        commands = _thread_state.commands = {}
    return commands


class _Command:
    """A recorded ``wp.Launch`` of one concrete kernel, replayed with new arguments of the recorded types.

    Warp's ``Launch`` keeps the packed value of forward argument ``i`` in ``params[1 + i]`` (launch bounds
    first) and of adjoint argument ``i`` after all forward ones. Both launch paths read those objects when
    launched (the CPU path copies them into its argument struct, the CUDA path passes their addresses), so a
    replay updates them in place: the data pointer of each array descriptor (shape and strides only when
    they change) and the value of each scalar. On the CPU those objects are made views of one persistent
    argument struct per direction (:func:`_bind_cpu_arguments`), which the kernel entry point is called with.

    Attributes:
        recorded: the ``wp.Launch``.
        arrays: ``(position, descriptor, scalar bytes)`` of every tensor argument, positions counting the
            forward then the adjoint arguments; shapes: the tensor shape each descriptor last took.
        scalars: ``(position, ctypes value, is a Warp scalar)`` of every scalar argument.
        packed: ``(position, index, adjoint)`` of every argument written through Warp's own argument packing
            (half-precision scalars, vectors, structs).
        labels: kernel argument name of every position (for errors).
        dims: the launch dimensions last set (without the lane dimension of a tiled launch).
        lanes: ``(block_dim,)``, the lane dimension ``wp.launch_tiled`` appends, or ``()``.
        invoke: runs the command as it stands.
    """

    def __init__(self, recorded, values: Sequence, dtypes: Sequence, num_args: int, dims: tuple, tiled: bool):
        self.recorded = recorded
        arg_specs = recorded.kernel.adj.args
        self.labels = [arg_specs[j % num_args].label for j in range(len(values))]
        self.packed = [(j, j % num_args, j >= num_args) for j, (value, dtype) in enumerate(zip(values, dtypes))
                       if _written_by_warp(value, dtype, arg_specs[j % num_args].type)]  # fmt: skip
        self.invoke = recorded.launch
        if recorded.device.is_cpu and recorded.block_dim <= 1 and not self.packed:
            self.invoke = _CpuInvoker(recorded)
        elif recorded.device.is_cuda:
            self.invoke = _CudaInvoker(recorded)
        params = recorded.params
        self.arrays = [(j, params[1 + j], ctypes.sizeof(dtype._type_)) for j, dtype in enumerate(dtypes)
                       if dtype is not None]  # fmt: skip
        self.shapes = [_tensor(values[j]).shape for j, _, _ in self.arrays]
        packed_positions = {j for j, _, _ in self.packed}
        self.scalars = [(j, params[1 + j], not isinstance(value, (int, float)))
                        for j, (value, dtype) in enumerate(zip(values, dtypes))
                        if dtype is None and value is not None and j not in packed_positions]  # fmt: skip
        self.dims = dims
        self.lanes = (recorded.block_dim,) if tiled else ()

    @classmethod
    def first_launch(cls, kernel, dims, args, adj_args, adjoint: bool, block_dim: int | None, device) -> "_Command":
        """Launch with every Warp check, then record the command for later launches of the same types."""
        with _resolve_lock:  # concurrent CPU launches (run_concurrently) must not compile a module twice
            concrete, dtypes = _resolve_overload(kernel, adjoint, args, adj_args)
            inputs = _wrap_arrays(args, dtypes, concrete)
            adj_inputs = _wrap_arrays(adj_args, dtypes[len(args):], concrete)
            _launch_checked(concrete, dims, inputs, adj_inputs, adjoint, block_dim, device)
            positions = [*range(len(args)), *range(len(adj_args))]
            packed = [_descriptor(a, d, concrete, i) if d is not None else a
                      for a, d, i in zip((*args, *adj_args), dtypes, positions)]  # fmt: skip
            recorded = _launch_checked(concrete, dims, packed[: len(args)], packed[len(args):], adjoint, block_dim,
                                       device, record_cmd=True)  # fmt: skip
        return cls(recorded, (*args, *adj_args), dtypes, len(args), dims, tiled=block_dim is not None)

    def replay(self, dims: tuple, values: Sequence) -> None:
        """Write the new arguments (forward then adjoint ones) and dimensions into the command and launch it."""
        if dims != self.dims:
            self.recorded.set_dim((*dims, *self.lanes))
            self.dims = dims
        shapes = self.shapes
        for k, (position, descriptor, scalar_bytes) in enumerate(self.arrays):
            tensor = values[position]
            if tensor.__class__ is Grouped:
                tensor = tensor.tensor
            if not tensor.is_contiguous():
                raise _not_contiguous(self.labels[position], self.recorded.kernel)
            descriptor.data = tensor.data_ptr()
            shape = tensor.shape
            if shape != shapes[k]:
                strides = tensor.stride()
                for d in range(descriptor.ndim):
                    descriptor.shape[d] = shape[d]
                    descriptor.strides[d] = strides[d] * scalar_bytes
                shapes[k] = shape
        for position, target, warp_scalar in self.scalars:
            value = values[position]
            target.value = value.value if warp_scalar else value
        for position, index, adjoint in self.packed:
            self.recorded.set_param_at_index(index, values[position], adjoint)
        self.invoke()


class _CpuInvoker:
    """Runs a recorded CPU launch by calling its kernel entry point on persistent argument structs, instead of
    ``wp.Launch.launch``, which builds and fills a fresh struct on every launch (Warp's ``invoke``). Under an
    active Warp CPU graph capture it defers to ``wp.Launch.launch`` so that the capture records the launch."""

    __slots__ = ("recorded", "entry", "structs")

    def __init__(self, recorded):
        self.recorded = recorded
        self.entry = recorded.hooks.backward if recorded.adjoint else recorded.hooks.forward
        self.structs = _bind_cpu_arguments(recorded)

    def __call__(self) -> None:
        recorded = self.recorded
        if warp_context._get_apic_capture_for_device(recorded.device) is not None:  # Launch.launch's own check
            recorded.launch()
        else:
            self.entry(ctypes.byref(recorded.bounds), *self.structs)


class _CudaInvoker:
    """Runs a recorded CUDA launch by Warp's native launch call on the command's packed parameters, the constant
    arguments of that call taken once, instead of ``wp.Launch.launch``, which looks them up on every launch. Under
    an active Warp graph capture or APIC capture it defers to ``wp.Launch.launch``, which does what those need
    (keeping the module loaded, recording the launch)."""

    __slots__ = ("recorded", "function", "shared_bytes", "grid_stride")

    def __init__(self, recorded):
        self.recorded = recorded
        hooks = recorded.hooks
        self.function = hooks.backward if recorded.adjoint else hooks.forward
        self.shared_bytes = hooks.backward_smem_bytes if recorded.adjoint else hooks.forward_smem_bytes
        self.grid_stride = int(recorded.grid_stride)

    def __call__(self) -> None:
        recorded = self.recorded
        device = recorded.device
        if warp_context.runtime.captures or warp_context._get_apic_capture_for_device(device) is not None:
            recorded.launch()
            return
        failed = warp_context.runtime.core.wp_cuda_launch_kernel(
            device.context, self.function, recorded.bounds.size, recorded.max_blocks, recorded.block_dim,
            self.grid_stride, recorded.cluster_dim, self.shared_bytes, recorded.params_addr,
            device.stream.cuda_stream, None,
        )  # fmt: skip
        if failed:
            warp_context._raise_cuda_launch_error(recorded.kernel, device, recorded.hooks, recorded.adjoint)


def _bind_cpu_arguments(recorded) -> list:
    """Copy the packed arguments of a recorded CPU launch into one ctypes struct per direction (forward, and
    adjoint for an adjoint launch), laid out as Warp's CPU entry points take them, and replace every
    ``recorded.params`` entry by a view of its field, so that writes to the params reach the structs.
    Returns ``ctypes.byref`` of the structs (each keeps its struct alive)."""
    specs = recorded.kernel.adj.args
    firsts = (1, 1 + len(specs)) if recorded.adjoint else (1,)
    refs = []
    for first in firsts:
        fields = [(spec.label, type(recorded.params[first + i])) for i, spec in enumerate(specs)]
        struct_type = type("ArgsStruct", (ctypes.Structure,), {"_fields_": fields})
        struct = struct_type()
        for i, (name, ctype) in enumerate(fields):
            setattr(struct, name, recorded.params[first + i])
            recorded.params[first + i] = ctype.from_buffer(struct, getattr(struct_type, name).offset)
        refs.append(ctypes.byref(struct))
    return refs


_HALF_TYPES = (wp.float16, wp.bfloat16)


def _written_by_warp(value, dtype, arg_type) -> bool:
    """Whether a non-array argument is packed by Warp on every replay (half scalars, vectors, structs...)."""
    if dtype is not None or value is None:
        return False
    return arg_type in _HALF_TYPES or not wp.types.type_is_scalar(type(value))


def _tensor(arg) -> torch.Tensor:
    return arg.tensor if isinstance(arg, Grouped) else arg



def _type_key(arg) -> object:
    if isinstance(arg, torch.Tensor):
        return arg.dtype, arg.dim()
    if isinstance(arg, Grouped):
        return arg.tensor.dtype, arg.tensor.dim(), arg.inner
    return type(arg)


def _element_dtype(arg):
    """Warp dtype of the array an argument becomes (None for scalars and None)."""
    if isinstance(arg, torch.Tensor):
        return warp_dtype(arg.dtype)
    if isinstance(arg, Grouped):
        if arg.tensor.dim() <= len(arg.inner):
            raise InputError(
                f"a tensor of shape {tuple(arg.tensor.shape)} has no array dimension left for {arg.inner} elements"
            )
        scalar = warp_dtype(arg.tensor.dtype)
        if len(arg.inner) == 1:
            return wp.types.vector(arg.inner[0], scalar)
        return wp.types.matrix(arg.inner, scalar)
    return None


def _resolve_overload(kernel, adjoint: bool, args: Sequence, adj_args: Sequence) -> tuple:
    """(concrete overload, element dtypes of all arguments), instantiated once per combination of types."""
    key = (kernel, adjoint, *map(_type_key, args), *map(_type_key, adj_args))
    resolved = _RESOLVED_OVERLOADS.get(key)
    if resolved is None:
        dtypes = [_element_dtype(a) for a in (*args, *adj_args)]
        concrete = kernel
        if kernel.is_generic:
            concrete = wp.overload(kernel, kernel.infer_argument_types(_wrap_arrays(args, dtypes, kernel)))
        resolved = _RESOLVED_OVERLOADS[key] = (concrete, dtypes)
    return resolved


def _tensor_of(arg, position: int, kernel) -> torch.Tensor:
    tensor = _tensor(arg)
    if not tensor.is_contiguous():
        raise _not_contiguous(kernel.adj.args[position].label, kernel)
    return tensor


def _not_contiguous(label: str, kernel) -> InputError:
    """The error for a non-contiguous tensor given for kernel argument ``label``."""
    return InputError(f"tensor for argument {label!r} of kernel {kernel.key} must be contiguous")


def _wrap_arrays(args: Sequence, dtypes: Sequence, kernel) -> list:
    """Arguments with tensors as ``wp.array`` views (first launch: Warp checks them fully)."""
    return [
        arg if dtype is None else to_warp(_tensor_of(arg, i, kernel), dtype=dtype)
        for i, (arg, dtype) in enumerate(zip(args, dtypes))
    ]


def _descriptor(arg, dtype, kernel, position: int) -> array_t:
    """Warp array descriptor (element ``dtype``) of a contiguous tensor or :class:`Grouped`, holding no reference
    to it: the caller keeps the tensor alive for the launch (a CUDA launch copies the descriptor when issued)."""
    tensor = _tensor_of(arg, position, kernel)
    ndim = tensor.dim() - (len(arg.inner) if isinstance(arg, Grouped) else 0)
    scalar_bytes, strides = ctypes.sizeof(dtype._type_), tensor.stride()
    return array_t(tensor.data_ptr(), 0, ndim, tensor.shape, [strides[d] * scalar_bytes for d in range(ndim)])


def _launch_checked(kernel, dims, inputs, adj_inputs, adjoint: bool, block_dim: int | None, device,
                    record_cmd: bool = False):  # fmt: skip
    """``wp.launch`` (or ``wp.launch_tiled`` with ``block_dim``) with Warp's full argument processing."""
    launcher = wp.launch if block_dim is None else functools.partial(wp.launch_tiled, block_dim=block_dim)
    return launcher(kernel, dim=dims, inputs=inputs, adj_inputs=adj_inputs, adjoint=adjoint, device=device,
                    record_cmd=record_cmd)  # fmt: skip
