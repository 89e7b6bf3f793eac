"""Reports of ``codecsplat eval``: the per-sample :class:`Row`, means over samples, Tables 1 and 2 in the paper's
form with Table 3 (self-render and depth), the Markdown file, and the rate-distortion and distortion-vs-time
plots."""

from __future__ import annotations

import itertools
import pathlib
import statistics
import textwrap
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..export.files import atomic_output
from ..measure import format_table

CODECSPLAT = "CodecSplat"
BACKBONE = "CodecSplat w/o codec"
COPY_NEAREST = "Copy nearest context view"
IMAGE_CODEC_SUFFIX = " + codec-free"
FIGURE_DPI = 130
"""Dots per inch of every written plot (a comparison panel shows its image at about one pixel per pixel)."""
TITLE_POINTS = 8
"""Font size of a comparison panel's title."""
AVERAGE_CHAR_EM = 0.6
"""The mean width of a title character in ems (DejaVu Sans, mixed case, with spaces), slightly generous."""


def rdo_method(name: str) -> str:
    """The method of the CodecSplat rows encoded with rate-distortion optimisation ``name`` (a preset such as
    ``slow``, or :func:`steps_text`): ``CodecSplat RDO (slow)``."""
    return f"{CODECSPLAT} RDO ({name})"


def steps_text(steps: int | str) -> str:
    """``1 step``, ``50 steps``; a preset's rule (a string) as it is."""
    if isinstance(steps, str):
        return steps
    return f"{steps} step" if steps == 1 else f"{steps} steps"


def image_codec_method(label: str) -> str:
    """The method of the image-codec baseline in format ``label`` (``WebP``, ``JPEG``): the context photographs
    coded as image files, the codec-free model run on the decoded ones (``WebP + codec-free``)."""
    return label + IMAGE_CODEC_SUFFIX


def generated_at_receiver(method: str) -> bool:
    """Whether ``method`` generates its Gaussians after decompression (the image-codec baselines): its GS generation
    is receiver time, not sender time."""
    return method.endswith(IMAGE_CODEC_SUFFIX)


@dataclass
class Row:
    """One method on one sample: bytes, quality of the target renders, seconds, and the geometry measures.

    ``bytes``: the method's whole coded size; ``parts`` its bytes per part where it has parts (CodecSplat:
    :func:`~codecsplat_warp.codec.bytes_report`; the image codecs: ``header`` and ``cameras`` as CodecSplat spends
    them, then ``view0`` ... one image file per view, and ``total``). ``lam``: the CodecSplat rate trade-off;
    ``quality``: the image codec's quality (None: not such a row). ``rdo``: the encoder's rate-distortion
    optimisation (:meth:`~codecsplat_warp.model.rdo.RDOResult.to_dict`; None: the amortised encoder or not
    CodecSplat). Seconds: ``gen_s`` GS generation, ``compress_s``, ``decompress_s``.

    ``self_render``: the image metrics of the method's Gaussians rendered into the sample's own context views
    against the context images (None: the method has no Gaussians). ``depth``: the errors of the method's depth
    map against the reference depth of the context views (:func:`~codecsplat_warp.eval.geometry.depth_errors`;
    None: the method has no depth map, empty: no reference depth for this sample).
    """

    scene: str
    method: str
    setting: str
    bytes: int
    metrics: dict[str, float]
    gen_s: float
    compress_s: float
    decompress_s: float
    lam: float | None = None
    parts: dict[str, int] = field(default_factory=dict)
    self_render: dict[str, float] | None = None
    depth: dict[str, float] | None = None
    quality: int | None = None
    rdo: dict | None = None


SELF_RENDER_PREFIX = "self_"
DEPTH_KEYS = ("abs_rel", "delta_1_25")


def summarize(rows: list[Row]) -> list[dict]:
    """Mean over samples of every (method, setting), in first-appearance order.

    Geometry keys: ``gaussians`` (whether the method has any), ``self_<metric>`` (mean over its samples);
    for a method with a depth map ``depth_samples`` (samples with reference depth) and ``depth_abs_rel``,
    ``depth_delta_1_25`` (means over those samples, each a mean over its pixels).
    """
    groups: dict[tuple[str, str], list[Row]] = {}
    for row in rows:
        groups.setdefault((row.method, row.setting), []).append(row)
    summary = []
    for (method, setting), group in groups.items():
        entry = {"method": method, "setting": setting, "lam": group[0].lam, "quality": group[0].quality,
                 "samples": len(group), "bytes": statistics.fmean(r.bytes for r in group)}
        for name in group[0].metrics:
            entry[name] = statistics.fmean(r.metrics[name] for r in group)
        for key in ("gen_s", "compress_s", "decompress_s"):
            entry[key] = statistics.fmean(getattr(r, key) for r in group)
        summary.append({**entry, **_geometry_means(group)})
    return summary


def _geometry_means(group: list[Row]) -> dict:
    """The geometry keys of :func:`summarize` for one (method, setting)."""
    rendered = [r.self_render for r in group if r.self_render is not None]
    entry: dict = {"gaussians": bool(rendered)}
    for name in rendered[0] if rendered else ():
        entry[SELF_RENDER_PREFIX + name] = statistics.fmean(r[name] for r in rendered)
    depths = [r.depth for r in group if r.depth is not None]
    if depths:
        scored = [d for d in depths if d]
        entry["depth_samples"] = len(scored)
        for key in DEPTH_KEYS if scored else ():
            entry[f"depth_{key}"] = statistics.fmean(d[key] for d in scored)
    return entry


def format_bytes(count: float) -> str:
    """Bytes as the paper prints them: KiB below 1 MiB, MiB above."""
    return f"{count / 2**20:.2f} MiB" if count >= 2**20 else f"{count / 2**10:.2f} KiB"


TABLE1_COLUMNS = [("method", "Method", "s"), ("setting", "Codec Setting", "s"), ("bytes_text", "Bytes/scene ↓", "s"),
                  ("psnr", "PSNR ↑", ".2f"), ("ssim", "SSIM ↑", ".3f"), ("lpips_vgg", "LPIPS-VGG ↓", ".3f"),
                  ("lpips_alex", "LPIPS-Alex ↓", ".3f"), ("self_psnr", "Self-render PSNR ↑", ".2f"),
                  ("depth_abs_rel", "Depth AbsRel ↓", ".3f"), ("depth_delta_1_25", "Depth δ<1.25 ↑", ".3f")]
TABLE3_COLUMNS = [("method", "Method", "s"), ("setting", "Codec Setting", "s"), ("self_psnr", "Self PSNR ↑", ".2f"),
                  ("self_ssim", "Self SSIM ↑", ".3f"), ("self_lpips_vgg", "Self LPIPS-VGG ↓", ".3f"),
                  ("self_lpips_alex", "Self LPIPS-Alex ↓", ".3f"), ("depth_abs_rel", "Depth AbsRel ↓", ".3f"),
                  ("depth_delta_1_25", "Depth δ<1.25 ↑", ".3f"), ("depth_samples", "Depth samples", "d")]
TABLE2_COLUMNS = [("method", "Method", "s"), ("setting", "Codec Setting", "s"), ("gen_s", "GS Gen. T. ↓", ".3f"),
                  ("compress_s", "Compress T. ↓", ".3f"), ("decompress_s", "Decompress T. ↓", ".3f")]


def table1(summary: list[dict]) -> str:
    """Table 1 (and 4): bytes per scene and target-view quality of every method (n/a: LPIPS without weights),
    with the self-render PSNR and depth errors of Table 3 ("-": the method has no Gaussians or depth map; n/a:
    not measured)."""
    return format_table([{**_geometry_cells(s, TABLE1_COLUMNS), "bytes_text": format_bytes(s["bytes"])}
                         for s in _paper_order(summary)], _as_text(TABLE1_COLUMNS))


def table3(summary: list[dict]) -> str:
    """Table 3: each method's Gaussians rendered into their own context views (image metrics against the
    context images) and its depth map against the reference depth ("-": no Gaussians or no depth map; n/a: not
    measured, e.g. LPIPS without weights or no reference depth)."""
    return format_table([_geometry_cells(s, TABLE3_COLUMNS) for s in _paper_order(summary)],
                        _as_text(TABLE3_COLUMNS))


def _geometry_cells(entry: dict, columns) -> dict:
    """``entry`` with its geometry columns formatted as text: "-" where the method has no Gaussians (self-render
    columns) or no depth map (depth columns), n/a where a value was not measured."""
    cells = dict(entry)
    for key, _, spec in columns:
        if key.startswith(SELF_RENDER_PREFIX) or key.startswith("depth_"):
            applies = entry.get("gaussians") if key.startswith(SELF_RENDER_PREFIX) else "depth_samples" in entry
            value = entry.get(key)
            cells[key] = "-" if not applies else "n/a" if value is None else format(value, spec)
    return cells


def _as_text(columns) -> list[tuple[str, str, str]]:
    """``columns`` with the geometry columns printed as the text :func:`_geometry_cells` made."""
    return [(key, header, "s" if key.startswith((SELF_RENDER_PREFIX, "depth_")) else spec)
            for key, header, spec in columns]


def table2(summary: list[dict]) -> str:
    """Table 2: GS generation, compression and decompression seconds of every method but the copy floor; a method
    run at several lambdas or qualities (CodecSplat, each RDO setting, the image codecs) as one row, the means over
    them."""
    rows = []
    for group in _by_method(summary):
        if group[0]["method"] == COPY_NEAREST:
            continue
        if _curve(group[0]) is None:
            rows += group
            continue
        mean = {k: statistics.fmean(s[k] for s in group) for k in ("gen_s", "compress_s", "decompress_s")}
        rows.append({"method": group[0]["method"], "setting": _span(group), **mean})
    return format_table(rows, TABLE2_COLUMNS)


EQUAL_BYTES_METRICS = (("psnr", "PSNR gain, dB", 1.0), ("lpips_vgg", "LPIPS-VGG lead", -1.0))
"""The metrics :func:`equal_bytes` compares: key, Table 4's header, and the sign that makes a positive difference
mean CodecSplat is better (PSNR higher, LPIPS lower)."""

EQUAL_BYTES_POINTS = 64
"""Sizes at which :func:`equal_bytes` compares two curves, evenly spread in log bytes over the range they share."""


def equal_bytes(summary: list[dict]) -> list[dict]:
    """Each CodecSplat curve (a method with lambdas) against each image-codec curve (a method with qualities), at
    equal bytes: both interpolated linearly in log bytes at :data:`EQUAL_BYTES_POINTS` sizes over the range of
    bytes they share. For each metric of :data:`EQUAL_BYTES_METRICS` the least and the most difference, CodecSplat
    against the baseline, signed so that positive means CodecSplat is better: it is better at every size of the
    range where the least is positive. A pair where a curve has fewer than two entries or the two share no range
    gives no entry; a metric that either lacks (LPIPS without weights) gives None.

    Returns:
        dicts with ``method``, ``baseline``, ``from_bytes`` and ``to_bytes`` (the shared range), and per metric
        ``<key>_least`` and ``<key>_most`` (the metric's units).
    """
    curves = [group for group in _by_method(summary) if len(group) >= 2 and _curve(group[0])]
    ours = [group for group in curves if _curve(group[0])[0] == "λ"]
    theirs = [group for group in curves if _curve(group[0])[0] == "q"]
    entries = []
    for mine, baseline in itertools.product(ours, theirs):
        low = max(min(e["bytes"] for e in mine), min(e["bytes"] for e in baseline))
        high = min(max(e["bytes"] for e in mine), max(e["bytes"] for e in baseline))
        if not 0 < low < high:
            continue
        sizes = np.geomspace(low, high, EQUAL_BYTES_POINTS)
        entry = {"method": mine[0]["method"], "baseline": baseline[0]["method"], "from_bytes": low, "to_bytes": high}
        for key, _, sign in EQUAL_BYTES_METRICS:
            difference = None
            if all(e.get(key) is not None for e in (*mine, *baseline)):
                difference = sign * (_at_bytes(mine, key, sizes) - _at_bytes(baseline, key, sizes))
            entry[f"{key}_least"] = None if difference is None else float(difference.min())
            entry[f"{key}_most"] = None if difference is None else float(difference.max())
        entries.append(entry)
    return entries


def _at_bytes(curve: list[dict], key: str, sizes: np.ndarray) -> np.ndarray:
    """``curve``'s ``key`` at ``sizes`` bytes, linear in log bytes between its entries (sorted by bytes)."""
    ordered = sorted(curve, key=lambda e: e["bytes"])
    return np.interp(np.log(sizes), [np.log(e["bytes"]) for e in ordered], [e[key] for e in ordered])


def table4(summary: list[dict]) -> str:
    """Table 4: :func:`equal_bytes` as Markdown, the least and the most difference per metric ("-": no curves to
    compare; n/a: the metric was not measured)."""
    entries = equal_bytes(summary)
    if not entries:
        return "-"
    rows = []
    for entry in entries:
        row = {"method": entry["method"], "baseline": entry["baseline"],
               "range": f"{format_bytes(entry['from_bytes'])} to {format_bytes(entry['to_bytes'])}"}
        for key, _, _ in EQUAL_BYTES_METRICS:
            least, most = entry[f"{key}_least"], entry[f"{key}_most"]
            row[key] = None if least is None else f"{least:+.3f} / {most:+.3f}"
        rows.append(row)
    columns = [("method", "Method", "s"), ("baseline", "against", "s"), ("range", "at equal bytes over", "s"),
               *((key, f"{header} (least / most)", "s") for key, header, _ in EQUAL_BYTES_METRICS)]
    return format_table(rows, columns)


def _curve(entry: dict) -> tuple[str, float] | None:
    """What a method's entries vary along: ``("λ", lambda)``, ``("q", image quality)``, or None (one setting)."""
    if entry.get("lam") is not None:
        return "λ", entry["lam"]
    if entry.get("quality") is not None:
        return "q", entry["quality"]
    return None


def _span(group: list[dict]) -> str:
    """The settings of one method's entries (in order) as Table 2 prints them: ``λ=16`` or ``λ=16,…,1024``."""
    name, first = _curve(group[0])
    return f"{name}={first:g}" if len(group) == 1 else f"{name}={first:g},…,{_curve(group[-1])[1]:g}"


def _by_method(summary: list[dict]) -> list[list[dict]]:
    """The entries of each method, methods in first-appearance order but those with lambdas (CodecSplat, then each
    RDO setting) last, as in the paper; within a method by lambda or quality."""
    methods: dict[str, list[dict]] = {}
    for entry in summary:
        methods.setdefault(entry["method"], []).append(entry)
    groups = sorted(methods.values(), key=lambda group: group[0].get("lam") is not None)  # stable
    return [sorted(group, key=lambda s: _curve(s)[1] if _curve(s) else 0) for group in groups]


def _paper_order(summary: list[dict]) -> list[dict]:
    """The entries in :func:`_by_method` order: baselines and the reference first, CodecSplat rows (by lambda) last."""
    return [entry for group in _by_method(summary) for entry in group]


def plot_rate_distortion(summary: list[dict], path: pathlib.Path) -> None:
    """Quality against bytes per scene (log scale): a line per method with several lambdas or qualities (CodecSplat,
    each RDO setting, the image codecs), the other methods as points."""
    names = [n for n in ("psnr", "ssim", "lpips_vgg", "lpips_alex") if n in summary[0]]
    labels = {"psnr": "PSNR (dB) ↑", "ssim": "SSIM ↑", "lpips_vgg": "LPIPS-VGG ↓", "lpips_alex": "LPIPS-Alex ↓"}
    fig, axes = _figure(len(names))
    for ax, name in zip(axes, names):
        _plot_methods(ax, summary, x=lambda s: s["bytes"] / 1024, y=lambda s, n=name: s[n], connect=True)
        ax.set_xlabel("KiB per scene")
        ax.set_ylabel(labels[name])
    _save(fig, axes, path)


def plot_distortion_vs_time(summary: list[dict], path: pathlib.Path) -> None:
    """PSNR against sender seconds (GS generation + compression) and receiver seconds (decompression), log scale;
    for the methods that generate their Gaussians at the receiver (the image codecs) GS generation counts there."""
    fig, axes = _figure(2)
    for ax, (label, x) in zip(axes, (("sender s: GS gen. + compress (image codecs: compress)", _sender_seconds),
                                      ("receiver s: decompress (image codecs: + GS gen.)", _receiver_seconds))):
        _plot_methods(ax, summary, x=x, y=lambda s: s["psnr"], connect=False)
        ax.set_xlabel(label)
        ax.set_ylabel("PSNR (dB) ↑")
    _save(fig, axes, path)


def _sender_seconds(entry: dict) -> float:
    return entry["compress_s"] + (0.0 if generated_at_receiver(entry["method"]) else entry["gen_s"])


def _receiver_seconds(entry: dict) -> float:
    return entry["decompress_s"] + (entry["gen_s"] if generated_at_receiver(entry["method"]) else 0.0)


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _figure(panels: int):
    fig, axes = pyplot().subplots(1, panels, figsize=(5.2 * panels, 4.2), squeeze=False)
    return fig, list(axes[0])


def _plot_methods(ax, summary: list[dict], x: Callable, y: Callable, connect: bool) -> None:
    """Every method on a log x axis: one with several lambdas or qualities as one series (a line in lambda or
    quality order when ``connect``, points otherwise), the amortised CodecSplat's points labelled with their lambda
    and the image codecs' with their quality; one with a single setting as a marker; the copy-nearest floor (no
    bytes, no time) as a dashed horizontal line."""
    styles = zip(itertools.cycle("sD^vP*Xph<>"), itertools.cycle(f"C{i}" for i in range(10) if i != 3))
    for group in _by_method(summary):
        method, curve = group[0]["method"], _curve(group[0])
        if method == COPY_NEAREST:
            ax.axhline(y(group[0]), color="0.4", ls="--", lw=1, label=f"{COPY_NEAREST} (0 bytes)")
            continue
        marker, colour = ("o", "C3") if method == CODECSPLAT else next(styles)
        ax.plot([x(s) for s in group], [y(s) for s in group], marker + ("-" if connect and curve else ""),
                color=colour, label=method if curve else f"{method} ({group[0]['setting']})",
                zorder=3 if method == CODECSPLAT else 2)
        if curve and (method == CODECSPLAT or curve[0] == "q"):
            for s in group:
                name, value = _curve(s)
                ax.annotate(f"{name}={value:g}", (x(s), y(s)), textcoords="offset points", xytext=(4, -10), fontsize=7)
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(pyplot().NullFormatter())
    ax.grid(True, which="both", alpha=0.3)


def _save(fig, axes, path: pathlib.Path) -> None:
    axes[0].legend(fontsize=7, loc="best")
    save_figure(fig, path)


def plot_comparison(columns: list, titles: list[str], path: pathlib.Path, inputs=None,
                    input_title: str = "input") -> None:
    """Side-by-side images: ``columns[j]`` is [T,H,W,3] uint8 (one frame per target view, the rows), titled
    ``titles[j]`` above its first row (e.g. ground truth, references, each lambda). ``inputs`` [V,H,W,3] uint8,
    when given, fills a first column of its own, one image per row titled ``input_title`` and its number (e.g. the
    context photographs that a bitstream encodes). Each panel is shown at about its pixel size (:data:`FIGURE_DPI`)."""
    views, height, width = columns[0].shape[:3]
    offset = 0 if inputs is None else 1
    input_count = 0 if inputs is None else len(inputs)
    rows = max(views, input_count)
    panel = max(width / FIGURE_DPI, 1.6)  # inches: one image pixel per figure pixel, with room for a title
    titles = [fit_title(title, panel * FIGURE_DPI) for title in titles]
    input_titles = [fit_title(f"{input_title} {i + 1}", panel * FIGURE_DPI) for i in range(input_count)]
    title_lines = max(title.count("\n") + 1 for title in titles + input_titles)
    fig, axes = pyplot().subplots(rows, offset + len(columns), squeeze=False,
                                  figsize=(panel * (offset + len(columns)),
                                           panel * rows * height / width + 0.2 + 0.15 * title_lines))
    for i, row_axes in enumerate(axes):
        for j, ax in enumerate(row_axes):
            ax.set_axis_off()
            if j < offset:
                frames, title = inputs, input_titles[i] if i < input_count else ""
            else:
                frames, title = columns[j - offset], titles[j - offset] if i == 0 else ""
            if i < len(frames):
                ax.imshow(frames[i])
                ax.set_title(title, fontsize=TITLE_POINTS)
    save_figure(fig, path)


def fit_title(title: str, width_px: float, points: float = TITLE_POINTS) -> str:
    """``title`` with each of its lines broken at spaces so that none runs wider than ``width_px`` figure pixels
    (at :data:`FIGURE_DPI`) in a ``points``-point font: a panel's title that would otherwise run into its
    neighbour's. The words and their order are kept."""
    em_px = points / 72 * FIGURE_DPI
    chars = max(8, int(width_px / (AVERAGE_CHAR_EM * em_px)))
    return "\n".join(textwrap.fill(line, chars) for line in title.split("\n"))


def save_figure(fig, path: pathlib.Path) -> None:
    """Write a matplotlib figure as PNG (atomically) and close it."""
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=FIGURE_DPI)
    pyplot().close(fig)



def markdown_report(result: dict) -> str:
    """The Markdown file: what was run, then Tables 1 and 2."""
    protocol = result["config"]["protocol"]
    size = f"{protocol['height']}x{protocol['width']}" if protocol["width"] else "stored size"
    lines = [
        f"# codecsplat eval: {protocol['name']} protocol",
        "",
        f"{len(result['scenes'])} scene(s), {result['config']['samples_per_scene']} sample(s) each; "
        f"{protocol['context_views'] or 'model'} context view(s) at {size} (HxW), {protocol['target_views']} target "
        f"view(s) per sample. Device: {result['machine']}. Model {result['model_id']}. LPIPS: {result['lpips']}.",
        "",
        "## Table 1: bytes per scene and target-view quality",
        "",
        *_method_notes(result),
        result["tables"]["table1"],
        "",
        "## Table 2: timing (seconds)",
        "",
        *(["GS generation of the image codecs runs at the receiver, on the decoded photographs.", ""]
          if any(generated_at_receiver(s["method"]) for s in result["summary"]) else []),
        result["tables"]["table2"],
        "",
        "## Table 3: self-render and depth",
        "",
        "Self-render: each method's Gaussians rendered into the sample's own context views, against the context "
        "images (mean over views, then over samples). Depth: the codec-free row (→PLY float32) scores the encoder "
        "depth D_enc, CodecSplat at each λ the decoder depth D̂, CodecSplat w/ Deflate its float16 D_enc, the "
        "image codecs the encoder depth of the decoded photographs; "
        "AbsRel and δ<1.25 over the pixels of all context views of a sample that have reference depth, then the "
        "mean over samples. " + result["depth_reference"]["text"],
        "",
        result["tables"]["table3"],
        "",
        "## Table 4: at equal bytes",
        "",
        "Each CodecSplat curve against each image codec's, both interpolated linearly in log bytes over the range of "
        "sizes they share: the least and the most difference there, positive where CodecSplat is better (PSNR "
        "gain in dB; LPIPS-VGG lead, the baseline's minus CodecSplat's). A least above 0 means better at every "
        "size of the range.",
        "",
        result["tables"]["table4"],
        "",
    ]
    if result["skipped"]:
        lines += ["Skipped: " + "; ".join(f"{s['scene']} ({s['reason']})" for s in result["skipped"]), ""]
    for note in result["notes"]:
        lines += [note, ""]
    return "\n".join(lines)


def _method_notes(result: dict) -> list[str]:
    """Paragraphs on the image-codec and RDO rows of ``result``, where it has them."""
    notes = []
    if any(generated_at_receiver(s["method"]) for s in result["summary"]):
        notes += ["WebP / JPEG + codec-free: each context photograph coded as an image file at quality q, decoded, "
                  "and the codec-free model run on the decoded photographs with the true cameras; bytes are the image "
                  "files plus the header and camera bytes of the sample's CodecSplat bitstream.", ""]
    if result["rdo"]:
        settings = ", ".join(f"{s['method']}: {steps_text(s['steps'])}" for s in result["rdo"])
        notes += [f"CodecSplat RDO: the latents optimised for each scene at the encoder ({settings}; seed "
                  f"{result['rdo'][0]['seed']}); compress time includes the optimisation.", ""]
    return notes
