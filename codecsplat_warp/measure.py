"""Timing, memory, machine-name and table helpers: the one place the package measures time. Used by the codec
(its phase :data:`Timer`), the evaluation (``codecsplat eval``), the commands, the benchmarks (``codecsplat bench
...``), the self-check and the training curves. Imports nothing of the package, so it sits in the lowest layer and
every layer may use it.

Two ways of timing, one synchronisation rule (:func:`synchronize`: wait for the device's queued work, so that a
time covers the CUDA work it launched):

* one call, as a user waits for it: :func:`timed` (wall seconds) and, per named phase inside a call,
  :class:`PhaseTimer` (the codec's ``timer(phase)`` hook, :data:`Timer`; :func:`no_timer` times nothing);
* a benchmark: warm-up runs first (Warp module load, allocator warm-up), then the median of repeated runs
  (:func:`time_call`, :func:`interleaved_medians`); on CUDA each run is bracketed by CUDA events on the current
  stream, on the CPU by ``time.perf_counter``.
"""

from __future__ import annotations

import contextlib
import gc
import os
import platform
import statistics
import time
from dataclasses import dataclass
from typing import Callable, Hashable, Iterator, Sequence

import torch

Timer = Callable[[str], contextlib.AbstractContextManager]
"""``timer(phase)`` returns a context manager that times that phase of a call (the codec's ``entropy`` and
``bitstream`` phases in ``compress``/``decompress``, ``encode_scene``/``decode_scene``); the default,
:func:`no_timer`, times nothing; :class:`PhaseTimer` sums seconds per phase."""


def no_timer(_phase: str) -> contextlib.AbstractContextManager:
    """The default :data:`Timer`: measures nothing."""
    return contextlib.nullcontext()


def synchronize(device: torch.device) -> None:
    """Wait until ``device`` has finished its queued work (CUDA); nothing to wait for on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


Clock = Callable[[], float]
"""A clock read in seconds: :func:`time.perf_counter` by default; tests pass a scripted one."""


def timed(fn: Callable[[], object], device: torch.device,
          clock: Clock = time.perf_counter) -> tuple[object, float]:
    """``(fn(), seconds)``: wall time of one call of ``fn``, the device work it queued included (``clock`` read
    once before the call and once after the device finished)."""
    synchronize(device)
    start = clock()
    result = fn()
    synchronize(device)
    return result, clock() - start


class PhaseTimer:
    """A :data:`Timer` that sums wall seconds per phase in :attr:`seconds` (``{phase: seconds}``), synchronising
    ``device`` at each phase's start and end and reading ``clock`` (:data:`Clock`) there."""

    def __init__(self, device: torch.device, clock: Clock = time.perf_counter):
        self.device = device
        self.clock = clock
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        synchronize(self.device)
        start = self.clock()
        try:
            yield
        finally:
            synchronize(self.device)
            self.seconds[phase] = self.seconds.get(phase, 0.0) + self.clock() - start


@dataclass
class Timing:
    """Median and spread of repeated runs, in milliseconds."""

    median_ms: float
    min_ms: float
    max_ms: float
    reps: int


def time_call(fn: Callable[[], object], device: torch.device, reps: int, warmup: int = 2) -> Timing:
    """Run ``fn`` ``warmup`` times untimed, then ``reps`` timed times; return the median in ms."""
    for _ in range(warmup):
        fn()
    samples = []
    synchronize(device)
    if device.type == "cuda":
        for _ in range(reps):
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            samples.append(start.elapsed_time(end))
    else:
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            samples.append((time.perf_counter() - t0) * 1e3)
    return Timing(statistics.median(samples), min(samples), max(samples), reps)


def interleaved_medians(calls: dict[Hashable, Callable[[], object]], device: torch.device,
                        reps: int) -> dict[Hashable, float]:
    """Median ms of each call over ``reps`` rounds that run every call once in turn (after one untimed
    warm-up each), so that a machine's load drifting during the benchmark affects all of them alike. Every
    other round runs the calls in reverse order, so that no call always follows the same one (a call
    after a heavier one may find the GPU clocked higher, or the host's garbage still to collect)."""
    for call in calls.values():
        call()
    samples: dict[Hashable, list[float]] = {name: [] for name in calls}
    order = list(calls)
    for round_index in range(reps):
        for name in order if round_index % 2 == 0 else reversed(order):
            samples[name].append(time_call(calls[name], device, 1, warmup=0).median_ms)
    return {name: statistics.median(values) for name, values in samples.items()}


def cuda_kernel_times(fn: Callable[[], object], device: torch.device, reps: int) -> list[tuple[str, float, float]]:
    """GPU time of every kernel, copy and fill that one call of ``fn`` issues: ``(name, us per call, launches per
    call)``, largest first, from ``torch.profiler`` device times over ``reps`` calls after one warm-up call. Host
    time and the gaps between launches are left out: what the call asks the GPU to do, not how long the caller
    waits."""
    from torch.profiler import ProfilerActivity, profile

    fn()
    torch.cuda.synchronize(device)
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(reps):
            fn()
        torch.cuda.synchronize(device)
    rows = [(event.key, event.self_device_time_total / reps, event.count / reps) for event in prof.key_averages()
            if event.device_type == torch.autograd.DeviceType.CUDA and event.self_device_time_total > 0]  # fmt: skip
    return sorted(rows, key=lambda row: -row[1])


def cuda_kernel_ms(fn: Callable[[], object], device: torch.device, reps: int) -> float:
    """Sum of :func:`cuda_kernel_times` of one call of ``fn``, in ms."""
    return sum(us for _, us, _ in cuda_kernel_times(fn, device, reps)) / 1e3


def cuda_peak_bytes(fn: Callable[[], object], device: torch.device) -> int:
    """Peak CUDA memory allocated by torch's allocator while ``fn`` runs, above what was live before."""
    torch.cuda.synchronize(device)
    base = torch.cuda.memory_allocated(device)
    torch.cuda.reset_peak_memory_stats(device)
    fn()
    torch.cuda.synchronize(device)
    return torch.cuda.max_memory_allocated(device) - base


def rss_peak_growth_bytes(fn: Callable[[], object]) -> int:
    """Peak resident memory while ``fn`` runs, above the resident size before it (CPU memory, Linux).

    Resets the kernel's high-water mark first (``/proc/self/clear_refs``), so earlier peaks (imports,
    input construction) do not hide this one. Counts every allocation: torch's, Warp's and Python's.
    """
    gc.collect()
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    before = _proc_status_kib("VmRSS")
    fn()
    return max(0, _proc_status_kib("VmHWM") - before) * 1024


def _proc_status_kib(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise OSError(f"{field} not in /proc/self/status")


def machine_name(device: torch.device) -> str:
    """Human-readable name of the machine a benchmark ran on."""
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        return f"{props.name} ({props.total_memory / 2**30:.0f} GiB), torch {torch.__version__}"
    cpu = _cpu_model() or platform.processor() or platform.machine()
    return f"{cpu}, {os.cpu_count()} logical cores, torch {torch.__version__}"


def _cpu_model() -> str | None:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        return None
    return None


def format_table(rows: Sequence[dict], columns: Sequence[tuple[str, str, str]]) -> str:
    """Markdown table; ``columns`` are (key, header, format spec) triples; missing values print as ``n/a``."""
    header = "| " + " | ".join(h for _, h, _ in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"
    lines = [header, rule]
    for row in rows:
        cells = []
        for key, _, spec in columns:
            value = row.get(key)
            cells.append("n/a" if value is None else format(value, spec))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
