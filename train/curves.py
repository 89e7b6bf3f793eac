"""Training curves of one or more runs (their ``metrics.jsonl``): a PNG and a table of throughput and loss.

    python -m train.curves runs/one-gpu runs/ddp-2gpu --labels "1 GPU, accumulate 2" "2 GPUs, DDP" \\
        --metrics loss,psnr --out ddp-vs-one-gpu.png

Each metric gets a panel against step; with ``--against-time`` a second row plots it against wall-clock
seconds (``elapsed_s``, logged by :mod:`train.stage1`). The table (stdout, and JSON with ``--json``) gives per
run: logged steps, scenes per second (``scenes`` per step over the ``elapsed_s`` between the first and the
last record, so the first record's start-up and compilation time is left out) and the mean of each metric
over the steps every run logged (a like-for-like comparison of runs of different lengths). Runs that recorded
their process count (``world_size`` in ``config.json``; torchrun runs) also get their GPUs and the scaling
efficiency against the first run: scenes per second per GPU over the first run's (1.0 is linear scaling; give runs
of equal per-GPU batch).

    torchrun --nproc_per_node 4 -m train.stage1 --time-limit-s 120 --out runs/s1-4gpu ...
    python -m train.curves runs/s1-1gpu runs/s1-2gpu runs/s1-4gpu --metrics loss --out scaling.png
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics

from codecsplat_warp.measure import format_table
from codecsplat_warp.errors import InputError
from codecsplat_warp.export.files import atomic_output, write_text

from .stage1 import METRICS_FILE
from .validate import read_metrics


def throughput(records: list[dict]) -> float | None:
    """Scenes per second: the median of the logged ``scenes_per_s`` (robust to a chunk's start-up and to resumed
    chunks); for older logs without it, between the first and the last record of the last chunk (``elapsed_s``
    restarts with every resumed chunk). None without ``elapsed_s``/``scenes``."""
    rates = [r["scenes_per_s"] for r in records if "scenes_per_s" in r]
    if rates:
        return statistics.median(rates)
    timed = [r for r in records if "elapsed_s" in r and "scenes" in r]
    restarts = [i for i in range(1, len(timed)) if timed[i]["elapsed_s"] < timed[i - 1]["elapsed_s"]]
    timed = timed[restarts[-1]:] if restarts else timed
    if len(timed) < 2 or timed[-1]["elapsed_s"] <= timed[0]["elapsed_s"]:
        return None
    scenes = sum(r["scenes"] for r in timed[1:]) / len(timed[1:]) * (timed[-1]["step"] - timed[0]["step"])
    return scenes / (timed[-1]["elapsed_s"] - timed[0]["elapsed_s"])


def compare(runs: dict[str, list[dict]], metrics: list[str], gpus: dict[str, int] | None = None) -> list[dict]:
    """One row per run: steps logged, scenes/s, and each metric's mean over the steps that every run logged; with
    ``gpus`` (each run's process count), also the GPUs and the scaling efficiency (scenes/s per GPU over the
    first run's).

    Raises:
        InputError: no step was logged by every run.
    """
    common = set.intersection(*({r["step"] for r in records} for records in runs.values()))
    if not common:
        raise InputError("the runs have no logged step in common (different --log-every?)")
    rows = []
    rates = {label: throughput(records) for label, records in runs.items()}
    first = next(iter(runs))
    base = rates[first] / gpus[first] if gpus and rates[first] else None
    for label, records in runs.items():
        rate = rates[label]
        row = {"run": label, "last step": records[-1]["step"], "scenes/s": round(rate, 2) if rate else None}
        if gpus:
            row["GPUs"] = gpus[label]
            row["scaling"] = round(rate / gpus[label] / base, 3) if rate and base else None
        shared = [r for r in records if r["step"] in common]
        for name in metrics:
            values = [r[name] for r in shared if name in r]
            row[f"mean {name} (steps {min(common)}-{max(common)})"] = statistics.fmean(values) if values else None
        rows.append(row)
    return rows


def moving_average(values: list[float], window: int) -> list[float]:
    """Trailing mean over the last ``window`` values (fewer at the start); ``window`` 1 returns ``values``."""
    return [statistics.fmean(values[max(0, i + 1 - window):i + 1]) for i in range(len(values))]


def plot(runs: dict[str, list[dict]], metrics: list[str], path: pathlib.Path, against_time: bool,
         smooth: int = 1) -> None:
    """Metric panels against step (and, with ``against_time``, against elapsed seconds) written as a PNG; with
    ``smooth`` > 1 the trailing mean over that many records is drawn over the faint raw curve."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    rows = 2 if against_time else 1
    fig, axes = pyplot.subplots(rows, len(metrics), figsize=(4.2 * len(metrics), 3.4 * rows), squeeze=False)
    for colour, (label, records) in zip(matplotlib.rcParams["axes.prop_cycle"].by_key()["color"], runs.items()):
        for column, name in enumerate(metrics):
            points = [r for r in records if name in r]
            timed = [r for r in points if "elapsed_s" in r]
            panels = [(axes[0][column], "step", points)] + ([(axes[1][column], "elapsed_s", timed)] if against_time else [])
            for ax, key, chosen in panels:
                xs, ys = [r[key] for r in chosen], [r[name] for r in chosen]
                if smooth > 1:
                    ax.plot(xs, ys, color=colour, lw=0.6, alpha=0.25)
                    ys = moving_average(ys, smooth)
                ax.plot(xs, ys, color=colour, lw=1.2, label=label + (f" (mean of {smooth})" if smooth > 1 else ""))
    for column, name in enumerate(metrics):
        axes[0][column].set(xlabel="step", ylabel=name)
        if against_time:
            axes[1][column].set(xlabel="wall-clock seconds", ylabel=name)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=120)
    pyplot.close(fig)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m train.curves``."""
    parser = argparse.ArgumentParser(prog="python -m train.curves", description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=pathlib.Path, help=f"run folders (or {METRICS_FILE} files)")
    parser.add_argument("--labels", nargs="+", help="one label per run (default: the folder names)")
    parser.add_argument("--metrics", default="loss,psnr",
                        help="comma list of logged metrics to plot, e.g. loss,psnr,bpp,lpips (default %(default)s)")
    parser.add_argument("--against-time", action="store_true",
                        help="also plot against wall-clock seconds (default off: against steps only)")
    parser.add_argument("--smooth", type=int, default=1,
                        help="draw the trailing mean over this many logged records (default %(default)s: none)")
    parser.add_argument("--out", type=pathlib.Path, required=True, help="PNG to write")
    parser.add_argument("--json", type=pathlib.Path, help="also write the table as JSON here (default: none)")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    labels = args.labels or [p.name for p in args.runs]
    if len(labels) != len(args.runs):
        raise InputError(f"{len(args.runs)} runs but {len(labels)} labels")
    runs = {label: read_metrics(_folder(path)) for label, path in zip(labels, args.runs)}
    worlds = {label: _world_size(_folder(path)) for label, path in zip(labels, args.runs)}
    for label, records in runs.items():
        if not records:
            raise InputError(f"run {label!r} has no logged steps")
    metrics = [m for m in args.metrics.split(",") if m]
    rows = compare(runs, metrics, worlds if None not in worlds.values() else None)
    if args.smooth < 1:
        raise InputError("--smooth must be >= 1")
    plot(runs, metrics, args.out, args.against_time, args.smooth)
    if args.json:
        write_text(args.json, json.dumps(rows, indent=1) + "\n")
    print(format_table(rows, [(key, key, "" if key in ("run", "last step", "GPUs") else ".4g") for key in rows[0]]))
    print(f"wrote {args.out}")


def _folder(path: pathlib.Path) -> pathlib.Path:
    return path.parent if path.name == METRICS_FILE else path


def _world_size(folder: pathlib.Path) -> int | None:
    """The process count a run recorded in its config.json (None: not recorded, or no readable config.json)."""
    try:
        world = json.loads((folder / "config.json").read_text()).get("world_size")
    except (OSError, ValueError, AttributeError):
        return None
    return world if isinstance(world, int) and world >= 1 else None


if __name__ == "__main__":
    main()
