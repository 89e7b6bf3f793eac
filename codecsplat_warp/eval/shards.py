"""Work spread over worker processes, one per GPU (or several per GPU, or CPU processes), and ``codecsplat eval``
split that way.

Scene samples are independent, so an evaluation, or a benchmark over scenes, can give each worker process a part of
the work:

* :func:`shard_devices`: the workers' devices for a ``--device`` and a worker count;
* :func:`split_round_robin`: items dealt over the workers;
* :func:`run_sharded`: ``task(shard, device)`` for every shard in its own spawned process, the results in shard
  order; tasks report their progress with :func:`report_progress`, which the parent shows as one bar;
* :func:`evaluate_sharded`: :func:`~codecsplat_warp.eval.evaluate.evaluate` with the scenes (with RDO rows, each
  scene's base rows and RDO row groups) dealt over workers, each evaluating its share into ``OUT/shards/<k>/``,
  merged into the files a one-process run writes.

Workers are started with the ``spawn`` method: the task must be a module-level function, its shards and results
picklable, and a script that calls :func:`run_sharded` must do so under ``if __name__ == "__main__":``.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import pathlib
import pickle
import shutil
import signal
import sys
import time
import traceback
from collections import Counter
from dataclasses import replace
from multiprocessing.connection import wait
from typing import Callable, Sequence

import torch
from tqdm.auto import tqdm

from ..device import available_cores, freed_memory_kept, keep_freed_memory, resolve_device, set_cpu_threads
from ..errors import CodecSplatError, DataError, InputError, NoSamplesError, ShardError
from ..model.pretrained import load_pretrained
from .evaluate import (BASE_GROUP, EvalConfig, check_config, evaluate, layout_rows, no_samples_error, plan_scenes,
                       results_header, scene_groups, write_results)
from .report import Row

STOP_S = 10.0
"""Seconds a worker has to end after SIGTERM (and, after the last result, to exit by itself) before SIGKILL."""
INTERRUPT_S = 5.0
"""Seconds the workers have to end by themselves after a Ctrl-C, which a terminal sends them too, before SIGTERM."""


# --------------------------------------------------------------------------------------------------
# Devices and splits
def shard_devices(device_arg: str, workers: int | None) -> list[torch.device]:
    """The devices of the worker processes for a ``--device`` value and a worker count.

    Args:
        device_arg: ``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (CUDA when torch sees a GPU, else the CPU).
        workers: how many worker processes; None: one per GPU torch sees for ``cuda`` and ``auto`` on a GPU
            machine, else one.
    Returns:
        one device per worker: for ``cuda``/``auto``, the GPUs ``cuda:0``, ``cuda:1``, ... in turn (several workers
        per GPU when ``workers`` exceeds the GPUs: one process leaves its GPU idle between small launches); for
        ``cuda:N``, that GPU for every worker; for ``cpu``, the CPU for every worker.
    Raises:
        InputError: ``workers`` is not a positive integer; CUDA asked for without a GPU, or ``cuda:N`` beyond the
            GPUs torch sees.
    """
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InputError(f"the worker count must be a positive integer, got {workers!r}")
    device = resolve_device(device_arg)
    if device.type != "cuda":
        return [device] * (workers or 1)
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise InputError(f"device {device} was asked for but torch sees {count} GPU(s)")
    gpus = [device] if device.index is not None else [torch.device("cuda", i) for i in range(count)]
    return [gpus[i % len(gpus)] for i in range(workers or len(gpus))]


def split_round_robin(items: Sequence, parts: int) -> list[list]:
    """``items`` dealt over ``parts`` lists like cards: part k holds items k, k + parts, k + 2 parts, ... in their
    order, so part sizes differ by at most one (parts beyond the item count are empty).

    Raises:
        InputError: ``parts`` is not a positive integer.
    """
    _check_parts(parts)
    items = list(items)
    return [items[k::parts] for k in range(parts)]


def _check_parts(parts: int) -> None:
    """InputError unless ``parts`` is a positive integer (a count of lists to deal into)."""
    if isinstance(parts, bool) or not isinstance(parts, int) or parts < 1:
        raise InputError(f"the part count must be a positive integer, got {parts!r}")


def deal_by_cost(items: Sequence, costs: Sequence[float], parts: int) -> list[list]:
    """``items`` dealt over ``parts`` lists by their ``costs``: the costliest first (ties in their order), each to
    the part with the least cost so far (ties to the first), the longest-processing-time rule, so the parts' totals
    differ by at most about the dearest item's cost; each part holds its items in their given order.

    Raises:
        InputError: ``parts`` is not a positive integer, or ``costs`` is not one number >= 0 per item.
    """
    _check_parts(parts)
    items, costs = list(items), [float(c) for c in costs]
    if len(costs) != len(items) or any(not c >= 0 for c in costs):
        raise InputError(f"deal_by_cost needs one cost >= 0 per item, got {len(costs)} for {len(items)} items")
    loads, hands = [0.0] * parts, [[] for _ in range(parts)]
    for i in sorted(range(len(items)), key=lambda i: -costs[i]):
        k = loads.index(min(loads))
        hands[k].append(i)
        loads[k] += costs[i]
    return [[items[i] for i in sorted(hand)] for hand in hands]


# --------------------------------------------------------------------------------------------------
# Running shards in processes
_report: Callable[[int, int], None] | None = None
"""Where :func:`report_progress` sends its counts: set by :func:`run_sharded` around the task it runs."""


def report_progress(done: int, total: int) -> None:
    """Tell :func:`run_sharded` that the calling task's shard has finished ``done`` of its ``total`` units of work
    (e.g. samples); its progress bar shows the sums over the shards. Does nothing outside :func:`run_sharded`."""
    if _report is not None:
        _report(done, total)


def worker_seconds(units: int, started: float, entered: float, loaded: float) -> dict[str, float]:
    """Where a worker of :func:`run_sharded` spent its time, for :func:`format_worker_seconds`: its ``units`` of
    work, ``start_s`` from the command's split (``started``, ``time.time()`` in the command's process) to the task's
    first instruction (``entered``: process start, imports; ~0 for a single worker, which runs in the command's
    process), ``load_s`` to ``loaded`` (the model and what the task loads once), ``work_s`` from then to now."""
    return {"units": units, "start_s": entered - started, "load_s": loaded - entered, "work_s": time.time() - loaded}


def format_worker_seconds(wall_s: float, workers: list[dict[str, float]], unit: str) -> str:
    """A line per worker of its :func:`worker_seconds` (``unit``: what a unit is, plural, e.g. ``"samples"``); the
    wall seconds from the split to the last result first."""
    lines = [f"{len(workers)} worker(s), {wall_s:.1f} s from the split to the last result"]
    lines += [f"  worker {k}: {w['units']} {unit}, start {w['start_s']:.1f} s, load {w['load_s']:.1f} s, "
              f"work {w['work_s']:.1f} s" for k, w in enumerate(workers)]
    return "\n".join(lines)


def run_sharded(task: Callable, shards: list, devices: list[torch.device], *, threads: int | None = None,
                progress: bool = True, desc: str = "shards", unit: str = "shard") -> list:
    """``task(shards[i], devices[i])`` for every shard, each in its own spawned process; the results in shard order.

    Each worker process runs on ``threads`` CPU threads (:func:`~codecsplat_warp.device.set_cpu_threads`; None: the
    cores this process may use shared out among the workers, at least one each), with its device as the current
    GPU (``torch.cuda.set_device``). Workers print no progress: one bar in this process (on a terminal's stderr,
    when ``progress``) counts the units the tasks report through :func:`report_progress`, a shard counting as one
    unit until its task reports. A single shard runs in this process, as it is set up (its GPU current during the
    task), its errors raised unchanged.

    If a worker fails, the other workers are ended and its error raised: one of this package's errors keeps its
    type, its message prefixed with the shard and device (the worker's traceback is its ``__cause__``); any other
    exception, or a worker that ends without a result, raises :class:`~codecsplat_warp.errors.ShardError`. On
    Ctrl-C (and on any other exception in this process) every worker is ended before the exception goes on; on
    Linux a worker also ends when this process dies.

    Args:
        task: a module-level function ``task(shard, device) -> result`` (shard and result picklable).
        shards: one item per worker.
        devices: the device of each worker (:func:`shard_devices`), as many as ``shards``.
        threads: CPU threads per worker process (None: shared out, see above).
        progress: show the progress bar.
        desc, unit: the bar's label and unit name (e.g. ``"sample"`` when tasks report samples).
    Raises:
        InputError: ``shards`` and ``devices`` differ in length; ``threads`` is not a positive integer; the task
            or a shard cannot be pickled.
        ShardError: a worker failed other than with one of this package's errors.
    """
    if len(shards) != len(devices):
        raise InputError(f"run_sharded needs one device per shard, got {len(shards)} shards and {len(devices)} devices")
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise InputError(f"the thread count must be a positive integer, got {threads!r}")
    if not shards:
        return []
    bar = _Progress(len(shards), desc, unit, progress)
    try:
        if len(shards) == 1:
            return [_run_here(task, shards[0], devices[0], bar)]
        return _run_processes(task, shards, devices, threads or max(1, available_cores() // len(shards)), bar)
    finally:
        bar.close()


class _Progress:
    """The parent's bar: the sums over the shards of (done, total) units; a shard is (0, 1) until it reports."""

    def __init__(self, shards: int, desc: str, unit: str, enabled: bool):
        self.counts = [(0, 1)] * shards
        self.bar = tqdm(total=shards, desc=desc, unit=unit, disable=None if enabled else True)  # None: on a terminal

    def update(self, shard: int, done: int, total: int) -> None:
        self.counts[shard] = (done, total)
        self.bar.total = sum(t for _, t in self.counts)
        self.bar.n = sum(d for d, _ in self.counts)
        self.bar.refresh()

    def finish(self, shard: int) -> None:
        total = self.counts[shard][1]
        self.update(shard, total, total)

    def close(self) -> None:
        self.bar.close()


def _run_here(task: Callable, shard, device: torch.device, bar: _Progress):
    """The single shard's task in this process, its reports going to ``bar``."""
    global _report
    _report = lambda done, total: bar.update(0, done, total)  # noqa: E731
    try:
        with torch.cuda.device(device) if device.type == "cuda" else contextlib.nullcontext():
            result = task(shard, device)
    finally:
        _report = None
    bar.finish(0)
    return result


def _run_processes(task: Callable, shards: list, devices: list[torch.device], threads: int, bar: _Progress) -> list:
    """The tasks in one spawned process each, each sending its messages on a pipe of its own, read until every
    result is in (see :func:`run_sharded`)."""
    for item in (task, *shards):
        try:
            pickle.dumps(item)
        except (pickle.PicklingError, AttributeError, TypeError) as exc:
            raise InputError(f"run_sharded needs a module-level task and picklable shards: {exc}") from None
    context = torch.multiprocessing.get_context("spawn")
    workers, pipes = [], {}
    results: dict[int, object] = {}
    grace = 0.0  # after an error: end the other workers at once
    try:
        for index, (shard, device) in enumerate(zip(shards, devices)):
            reader, writer = context.Pipe(duplex=False)
            arguments = (task, shard, device, threads, freed_memory_kept(), writer)
            workers.append(context.Process(target=_worker, args=arguments, name=f"codecsplat-shard-{index}"))
            pipes[reader] = index
            workers[-1].start()
            writer.close()  # the worker's end: once the worker ends, its pipe reads end-of-file
        while len(results) < len(shards):
            for reader in wait(list(pipes)):
                index = pipes[reader]
                try:
                    kind, payload = reader.recv()
                except EOFError:  # the worker ended
                    del pipes[reader]
                    if index not in results:
                        raise _ended_error(index, devices[index], workers[index]) from None
                    continue
                if kind == "progress":
                    bar.update(index, *payload)
                elif kind == "result":
                    results[index] = pickle.loads(payload)
                    bar.finish(index)
                else:
                    raise _worker_error(index, devices[index], payload)
        grace = STOP_S
    except KeyboardInterrupt:
        grace = INTERRUPT_S
        raise
    finally:
        _stop(workers, grace)
        for reader in pipes:
            reader.close()
    return [results[index] for index in range(len(shards))]


def _worker(task: Callable, shard, device: torch.device, threads: int, keep_memory: bool, pipe) -> None:
    """A worker process: ``task(shard, device)`` on ``threads`` CPU threads with ``device`` current, keeping the
    memory it frees when the parent does (``keep_memory``, :func:`~codecsplat_warp.device.keep_freed_memory`);
    sends its progress reports, then its pickled result or error, on ``pipe``."""
    global _report
    try:
        _end_with_parent()
        set_cpu_threads(threads)
        if keep_memory:
            keep_freed_memory()
        if device.type == "cuda":
            torch.cuda.set_device(device)
        _report = lambda done, total: pipe.send(("progress", (done, total)))  # noqa: E731
        message = ("result", pickle.dumps(task(shard, device)))
    except KeyboardInterrupt:  # Ctrl-C reached the whole process group: the parent ends the workers
        return
    except Exception as exc:  # noqa: BLE001 - every failure goes back to the parent, which raises it
        message = ("error", _pickled_error(exc))
    pipe.send(message)
    pipe.close()


PR_SET_PDEATHSIG = 1
"""Linux prctl option: the signal this process gets when its parent dies."""


def _end_with_parent() -> None:
    """On Linux, have the kernel send this worker SIGTERM when the parent process dies (a killed parent leaves no
    worker running); elsewhere nothing."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def _pickled_error(exc: Exception) -> bytes:
    """A worker's error for the parent: (its class when it is one of this package's, else None; "Type: message";
    the message; the worker's traceback), pickled (without the class when that cannot be pickled)."""
    kind = type(exc) if isinstance(exc, CodecSplatError) else None
    payload = (kind, f"{type(exc).__name__}: {exc}", str(exc), traceback.format_exc())
    try:
        return pickle.dumps(payload)
    except (pickle.PicklingError, AttributeError, TypeError):
        return pickle.dumps((None, *payload[1:]))


def _worker_error(index: int, device: torch.device, payload: bytes) -> Exception:
    """The exception the parent raises for shard ``index``'s error (see :func:`run_sharded`)."""
    kind, text, message, trace = pickle.loads(payload)
    where = f"shard {index} on {device}"
    if kind is not None:
        with contextlib.suppress(TypeError):  # an error class that takes more than a message becomes a ShardError
            error = kind(f"{where}: {message}")
            error.__cause__ = ShardError(f"{where}: the worker's traceback:\n{trace}")
            return error
    return ShardError(f"{where} failed: {text}\nthe worker's traceback:\n{trace}")


def _ended_error(index: int, device: torch.device, worker) -> ShardError:
    """The ShardError of shard ``index``, whose worker process ended without a result."""
    worker.join(STOP_S)
    code = worker.exitcode
    how = (f"was killed by signal {-code}" if code is not None and code < 0 else
           "ended" if code is None else f"exited with code {code}")
    return ShardError(f"shard {index} on {device}: its worker process {how} without a result")


def _stop(workers: list, grace: float) -> None:
    """Give every started worker ``grace`` seconds to exit, then SIGTERM, then SIGKILL after :data:`STOP_S`;
    reap them all."""
    started = [worker for worker in workers if worker.pid is not None]
    for worker in started:
        worker.join(grace)
        if worker.exitcode is None:
            worker.terminate()
    for worker in started:
        worker.join(STOP_S)
        if worker.exitcode is None:
            worker.kill()
            worker.join()


# --------------------------------------------------------------------------------------------------
# codecsplat eval over workers
def evaluate_sharded(config: EvalConfig, checkpoint: str | None, device: torch.device, workers: list[torch.device],
                     threads: int | None = None) -> dict:
    """:func:`~codecsplat_warp.eval.evaluate.evaluate` of a pretrained model dealt over worker processes
    (:func:`run_sharded`), merged into what one process writes.

    What is dealt: without RDO rows, whole scenes in the plan's order, like cards (:func:`split_round_robin`). With
    RDO rows nearly all the time is their encodes, one per (sample, RDO setting, lambda), and whole scenes would bound
    the speed-up by the scene count (ten scenes on four GPUs leave one worker three: at most 3.3x). So the units are
    finer: a scene's *base* rows (copy-nearest, CodecSplat at every lambda, the codec-free reference and the
    baselines: :data:`~codecsplat_warp.eval.evaluate.BASE_GROUP`) and each of its RDO row groups (a setting at a
    lambda), dealt by their estimated cost (:func:`deal_by_cost`: the dearest first, each to the least loaded
    worker; :func:`_group_costs`: an RDO group costs in proportion to its steps), so that the workers finish
    together. A worker evaluates only its units' rows (:attr:`EvalConfig.units`): one that has only RDO units of a
    scene loads its samples but runs no base row. A sample's ``renders`` picture shows every row, which would take
    the renders of several workers: with ``renders`` whole scenes are dealt.

    Worker k loads the model on its device and evaluates its share into ``config.out/shards/<k>/`` (its own
    results.json, resumed like any evaluation when the same command runs again with the same workers, and
    tables.md; no plots, :attr:`EvalConfig.plots`). Then this
    process writes results.json, tables.md and the plots to ``config.out`` as a one-process run does: each sample's
    rows in a one-process run's order, the samples in the plan's order, the same summary and tables, ``device`` and
    the machine of the first worker; with ``renders`` it copies each sample's picture to its one-process name,
    ``renders/<scene>-<sample>.png``. The timings are each worker's own wall-clock seconds (workers sharing a GPU
    lengthen each other's). With one worker, or a single unit (one scene without RDO rows), the evaluation runs in
    this process on ``device``, straight into ``config.out``.

    Args:
        config: the evaluation (without ``units``); ``progress`` shows one bar of the samples the workers finish (a
            sample whose rows several workers share counts once in each).
        checkpoint: the pretrained model file (:func:`~codecsplat_warp.model.pretrained.load_pretrained`; None: the
            shipped model).
        device: the evaluation's device as given (``--device`` resolved, e.g. ``cuda``): the one-process run's, and
            what results.json records.
        workers: the workers' devices (:func:`shard_devices`); more workers than units are not started.
        threads: CPU threads per worker process (None: the available cores shared out).
    Returns:
        the result dict of :func:`~codecsplat_warp.eval.evaluate.evaluate` (what results.json holds); dealt over
        workers, with ``wall_s`` (from the split to the merge) and each worker's ``worker_seconds``
        (:func:`worker_seconds`) beside it, which results.json does not hold.
    Raises:
        InputError, DataError: as :func:`~codecsplat_warp.eval.evaluate.evaluate` (raised in a worker: prefixed with
            its shard; a worker whose scenes are all unusable only adds them to ``skipped``); DataError also when
            ``config.out/shards`` holds this evaluation split another way, over another number of workers (with
            ``resume``).
        ShardError: a worker failed otherwise.
    """
    scenes = plan_scenes(config) if len(workers) > 1 else []
    shards = _split(config, scenes, len(workers))
    if len(shards) <= 1:
        return evaluate(load_pretrained(checkpoint, device), config, device)
    if config.resume:
        _check_split(pathlib.Path(config.out), shards)
    started = time.time()
    results = run_sharded(_evaluate_shard, [(shard, checkpoint, started) for shard in shards], workers[:len(shards)],
                          threads=threads, progress=config.progress, desc="eval", unit="sample")
    merged = _merge(config, device, scenes, shards, results)
    return {**merged, "wall_s": time.time() - started, "worker_seconds": [r["worker_seconds"] for r in results]}


def _units(config: EvalConfig, scenes: list[str]) -> list[tuple[str, str | None]]:
    """The units :func:`evaluate_sharded` deals, of ``scenes`` (the plan's order): (scene, None), a whole scene, for
    each scene when ``config`` has no RDO rows or writes renders; else (scene, row group): each scene's base rows
    and each of its RDO row groups."""
    groups = list(dict.fromkeys(check_config(config).layout))  # the base group first, then the RDO groups
    if len(groups) == 1 or config.renders:
        return [(scene, None) for scene in scenes]
    return [(scene, group) for scene in scenes for group in groups]


BASE_ROW_STEPS = 8.0
"""The cost of a base row in RDO steps, for :func:`_group_costs`: on an H200 with 8 views at 256x448 a scene's 11
base rows took 3.7 s (the codec-free model on the decoded photographs of each image-codec quality, the PLY of the
codec-free reference), an RDO step 53 ms, and each row is scored alike."""


def _group_costs(config: EvalConfig) -> dict[str, float]:
    """The estimated cost of each row group of a sample, in RDO steps, to deal the units of :func:`_units` by cost:
    an RDO group its steps, the base group :data:`BASE_ROW_STEPS` a row."""
    checked = check_config(config)
    views = checked.protocol.context_views or 2  # the shipped models' count when the protocol leaves it open
    costs = {BASE_GROUP: BASE_ROW_STEPS * checked.layout.count(BASE_GROUP)}
    costs.update({setting.group(lam): float(setting.step_count(views))
                  for setting in checked.rdo for lam in config.lambdas})
    return costs


def _split(config: EvalConfig, scenes: list[str], workers: int) -> list[EvalConfig]:
    """The evaluation of each worker, at most ``workers`` and no more than the units (:func:`_units`): whole scenes
    dealt like cards, or a scene's base rows and RDO groups dealt by their estimated cost (:func:`deal_by_cost`,
    :func:`_group_costs`); worker k's units' scenes (in the plan's order ``scenes``) into
    ``config.out/shards/<k>/``, restricted to its units when they are not whole scenes."""
    units = _units(config, scenes)
    parts = min(workers, len(units))
    if not units:
        hands = []
    elif units[0][1] is None:
        hands = split_round_robin(units, parts)
    else:
        costs = _group_costs(config)
        hands = deal_by_cost(units, [costs[group] for _, group in units], parts)
    return [_shard(config, scenes, k, hand) for k, hand in enumerate(hands)]


def _shard(config: EvalConfig, scenes: list[str], k: int, units: list[tuple[str, str | None]]) -> EvalConfig:
    """Worker ``k``'s evaluation of its ``units`` (see :func:`_split`)."""
    names = {scene for scene, _ in units}
    return replace(config, scenes=tuple(scene for scene in scenes if scene in names),
                   units=tuple((scene, group) for scene, group in units if group is not None),
                   out=str(pathlib.Path(config.out) / "shards" / str(k)), progress=False, plots=False)


def _evaluate_shard(shard: tuple[EvalConfig, str | None, float], device: torch.device) -> dict:
    """A worker of :func:`evaluate_sharded`: the evaluation of its share (config, checkpoint, the split's
    ``time.time()``) on ``device``, reporting its finished samples; only the skipped scenes (and an empty plan and
    rows) when none is usable; with where its time went (``worker_seconds``: :func:`worker_seconds`, its samples
    the units, the model its load; LPIPS, the samples and a warm-up encode are work)."""
    config, checkpoint, started = shard
    entered = time.time()
    model = load_pretrained(checkpoint, device)
    loaded = time.time()
    try:
        result = evaluate(model, config, device, on_sample=report_progress)
    except NoSamplesError as exc:  # every scene of this shard is unusable; other shards may have samples
        result = {"plan": [], "rows": [], "skipped": exc.skipped, "notes": []}
    return {**result, "worker_seconds": worker_seconds(len(result["plan"]), started, entered, loaded)}


def _check_split(out: pathlib.Path, shards: list[EvalConfig]) -> None:
    """DataError when a shard's results.json under ``out/shards`` holds other scenes or units than this split gives
    it: the evaluation was split over another number of workers (or by a version that dealt otherwise), and only
    that split resumes it."""
    for shard in shards:
        file = pathlib.Path(shard.out) / "results.json"
        try:
            saved = json.loads(file.read_text())["config"]
            split = [saved["scenes"], saved.get("units", [])]
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue  # nothing finished yet, or not an evaluation's file: evaluate says which
        if split != json.loads(json.dumps([shard.scenes, shard.units])):
            raise DataError(f"{out / 'shards'} holds an evaluation split over another number of workers ({file} has "
                            "other scenes or units): run it with the worker count it had to resume it, or --restart")


def _merge(config: EvalConfig, device: torch.device, scenes: list[str], shards: list[EvalConfig],
           results: list[dict]) -> dict:
    """The one-process result of the workers' ``results`` (shard k evaluated ``shards[k]``; ``scenes`` in the
    plan's order), written to ``config.out`` (see :func:`evaluate_sharded`).

    Raises:
        NoSamplesError: no worker had a usable scene.
    """
    position = {scene: i for i, scene in enumerate(scenes)}
    checked = check_config(config)
    samples, placed = _gather(shards, results, checked.layout, position)
    order = sorted(samples)
    skipped = sorted({s["scene"]: s for result in results for s in result["skipped"]}.values(),
                     key=lambda s: position[s["scene"]])
    if not order:
        raise no_samples_error(config, checked.protocol, skipped)
    out = pathlib.Path(config.out)
    if config.renders:
        (out / "renders").mkdir(parents=True, exist_ok=True)
        for number, sample in enumerate(order, 1):
            key, k, local = samples[sample]
            source = pathlib.Path(shards[k].out) / "renders" / f"{key[0]}-{local}.png"
            if source.is_file():  # a sample an earlier run without renders finished has none
                shutil.copyfile(source, out / "renders" / f"{key[0]}-{number}.png")
    rows = [row for *_, row in sorted(placed, key=lambda entry: entry[:2])]
    first = next(result for result in results if result["plan"])  # the first worker that had samples
    keys = [samples[sample][0] for sample in order]
    header = results_header(config, checked.protocol, device, machine=first["machine"], model=first["model_id"],
                            scenes=[key[0] for key in keys], skipped=skipped, lpips=first["lpips"], plan=keys,
                            rdo=first["rdo"])
    return write_results(header, rows, config.mvs_depth, [note for result in results for note in result["notes"]])


def _gather(shards: list[EvalConfig], results: list[dict], layout: list[str],
            position: dict[str, int]) -> tuple[dict[tuple[int, int], tuple], list[tuple]]:
    """The workers' samples and rows, each sample known by (position of its scene in ``position``, its number among
    the scene's samples), the same in every worker that has units of the scene: the samples as {sample: (key, the
    first worker that has it, its number in that worker's plan)}, the rows as (sample, position among a full run's
    rows of the sample, row). A worker's rows of a sample are those of its groups of the sample's ``layout`` in its
    order (:func:`~codecsplat_warp.eval.evaluate.layout_rows`), which places them among the other workers' rows."""
    samples: dict[tuple[int, int], tuple] = {}
    placed: list[tuple] = []
    for k, (shard, result) in enumerate(zip(shards, results)):
        slots = []
        for local, (key, sample) in enumerate(zip(result["plan"], _sample_ids(result["plan"], position)), 1):
            samples.setdefault(sample, (key, k, local))
            slots += [(sample, slot) for slot in layout_rows(layout, scene_groups(shard, key[0]))]
        placed += [(*where, Row(**row)) for where, row in zip(slots, result["rows"], strict=True)]
    return samples, placed


def _sample_ids(plan: list, position: dict[str, int]) -> list[tuple[int, int]]:
    """(position of its scene, its number among the scene's samples) of each sample of a worker's ``plan``."""
    numbers: Counter = Counter()
    ids = []
    for scene, *_ in plan:
        numbers[scene] += 1
        ids.append((position[scene], numbers[scene]))
    return ids
