"""``codecsplat eval``: the paper's evaluation (Tables 1, 2 and 4) on a folder of scenes.

For every scene sample (context views -> target views: from an evaluation index file with ``index``, else
picked by :func:`codecsplat_warp.data.split_context_targets` around evenly spread anchors):

* **CodecSplat** at each lambda: ``model.encode_scene`` -> bitstream -> ``model.decode_scene`` -> render the
  targets. Bytes are the whole bitstream (header, cameras, feature streams).
* **Codec-free reference and baselines**, all on the same model's codec-free output (``model(images,
  cameras)``: Gaussians, ``F_c``, ``D_enc``): the Gaussians as an uncompressed float32 3DGS PLY (the
  reconstruction upper bound), (a) PLY attributes quantised + Deflate, (b) gsplat-style PNG, (c) the
  feature ``F_c`` (and depth) in float16 + Deflate, each encoded, decoded and rendered.
* **Copy the nearest context view**: the floor every table shows, at zero bytes: each target is predicted
  by the context image whose camera centre is nearest to the target's, unchanged.

Metrics on the targets: PSNR (prediction clipped to [0,1]), SSIM (11x11 Gaussian window), LPIPS-VGG and
LPIPS-Alex (when weights are found); see :mod:`codecsplat_warp.metrics.image`.

Timing (Table 2, seconds; CUDA work is synchronised before a clock is read): *GS generation* is the
network work before compression: for CodecSplat the encoder's backbone up to ``F_c`` (MVEnc, FeatHead,
R_pre), for the baselines the whole codec-free forward pass that produces their Gaussians; *compress* is
the rest of the encoder (CodecSplat: latent analysis, entropy coding, bitstream) or the baseline's
encoder; *decompress* is bytes -> Gaussians on the device. A warm-up pass on the first sample (Warp
kernel loading, allocator) is not timed.

Outputs (``--out``): ``results.json`` (every sample and the summary), ``tables.md`` (Tables 1 and 2 in
the paper's form), ``rate_distortion.png`` and ``distortion_vs_time.png``.
"""

from __future__ import annotations

import contextlib
import pathlib
import statistics
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Iterator

import torch
from tqdm.auto import tqdm

from .baselines import FeatureDeflate, PlyDeflate, PngCompression
from .cameras import Cameras
from .codec import bytes_report, check_lambda
from .data import detect_formats, load_evaluation_index, load_scene, split_context_targets
from .data.preprocess import DatasetConfig, preprocess_scene
from .errors import DataError, InputError
from .export.files import atomic_output, write_json, write_text
from .export.ply import decode_ply, encode_ply
from .gaussians import Gaussians
from .measure import format_table, machine_name, synchronize, timed
from .metrics.image import ImageMetrics
from .model.codecsplat import model_id

CODECSPLAT = "CodecSplat"
BACKBONE = "CodecSplat w/o codec"
COPY_NEAREST = "Copy nearest context view"
BASELINE_NAMES = ("ply", "png", "feature")
"""Baselines ``--baselines`` may name: (a) PLY + Deflate, (b) PNG, (c) float16 feature + Deflate."""

PAPER_LAMBDAS = (16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0)


@dataclass(frozen=True)
class Protocol:
    """Image size and view counts of an evaluation protocol.

    Attributes:
        name: ``re10k``, ``dl3dv`` or ``scene``.
        width, height: protocol image size (resize to cover, centre-crop); None keeps each scene's stored
            size, cropped to multiples of 4.
        context_views: context views per sample; None uses the model's ``num_views``.
        target_views: target views rendered and scored per sample.
    """

    name: str
    width: int | None
    height: int | None
    context_views: int | None
    target_views: int = 3


PROTOCOLS = {
    "re10k": Protocol("re10k", 256, 256, 2),
    "dl3dv": Protocol("dl3dv", 448, 256, 8),
    "scene": Protocol("scene", None, None, None),
}
"""RE10K: 2 views at 256x256; DL3DV: 8 views at 256x448 (HxW); scene: stored size, the model's view count."""


@dataclass
class Sample:
    """One evaluation item: context and target views of a scene, images float32 [V,3,H,W] in [0,1]."""

    scene: str
    context: list[int]
    target: list[int]
    context_images: torch.Tensor
    context_cameras: Cameras
    target_images: torch.Tensor
    target_cameras: Cameras

    def to(self, device: torch.device) -> "Sample":
        return Sample(self.scene, self.context, self.target, self.context_images.to(device),
                      self.context_cameras.to(device), self.target_images.to(device), self.target_cameras.to(device))


@dataclass
class Row:
    """One method on one sample: bytes, quality of the target renders, seconds."""

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


# --------------------------------------------------------------------------------------------------
# Samples
def find_scenes(path) -> list[pathlib.Path]:
    """``path`` itself when it is a scene folder or pose file, else its sub-folders that hold a scene.

    Raises:
        DataError: ``path`` does not exist or holds no scene.
    """
    path = pathlib.Path(path)
    if not path.exists():
        raise DataError(f"{path} does not exist")
    if path.is_file() or detect_formats(path):
        return [path]
    scenes = sorted(p for p in path.iterdir() if p.is_dir() and detect_formats(p))
    if not scenes:
        raise DataError(f"{path} is neither a scene nor a folder of scenes (no pose file found)")
    return scenes


def select_scenes(paths: list[pathlib.Path], names: tuple[str, ...]) -> list[pathlib.Path]:
    """The ``paths`` whose folder name is in ``names``, in the order of ``names`` (all paths when it is empty).

    Raises:
        DataError: a name matches no path (the error lists the scenes found).
    """
    if not names:
        return paths
    by_name = {p.name: p for p in paths}
    missing = sorted(set(names) - set(by_name))
    if missing:
        raise DataError(f"scene(s) {', '.join(missing)} not found; found {', '.join(by_name)}")
    return [by_name[name] for name in names]


def scene_samples(path: pathlib.Path, protocol: Protocol, context_views: int, samples: int) -> list[Sample]:
    """``samples`` items of one scene, anchors evenly spread over its views, preprocessed to the protocol.

    The scene keeps its own near/far (real captures are not in the RE10K/DL3DV scale).
    """
    scene = load_scene(path)
    V = scene.num_views
    out = []
    for s in range(samples):
        anchor = min(V - 1, int((s + 0.5) * V / samples))
        context, target = split_context_targets(scene.cameras, anchor, context_views, protocol.target_views)
        out.append(protocol_sample(path.name, scene, protocol, context, target))
    return out


def index_samples(paths: list[pathlib.Path], index_file, protocol: Protocol) -> list[Sample]:
    """One item per entry of an evaluation index file (``{"<scene folder>": {"context": [...], "target":
    [...]}}``, see :func:`codecsplat_warp.data.load_evaluation_index`) among the scene folders ``paths``,
    preprocessed to the protocol, in the index's order.

    Raises:
        DataError: an entry names no scene folder of ``paths``, or a frame the scene does not have.
    """
    selections = load_evaluation_index(index_file)
    by_name = {p.name: p for p in paths}
    missing = [key for key in selections if key not in by_name]
    if missing:
        raise DataError(f"{index_file}: scene(s) {', '.join(missing)} are not in the data "
                        f"(found {', '.join(by_name) or 'none'})")
    out = []
    for key, selection in selections.items():
        scene = load_scene(by_name[key])
        frames = selection.context + selection.target
        if max(frames) >= scene.num_views:
            raise DataError(f"{index_file}: scene {key} has {scene.num_views} views, the index asks for frame "
                            f"{max(frames)}")
        out.append(protocol_sample(key, scene, protocol, list(selection.context), list(selection.target)))
    return out


def protocol_sample(name: str, scene, protocol: Protocol, context: list[int], target: list[int]) -> Sample:
    """The context and target frames of ``scene`` resized and centre-cropped to the protocol size (the stored
    size cropped to multiples of 4 when the protocol has none), keeping the scene's near/far."""
    width = protocol.width or scene.cameras.width // 4 * 4
    height = protocol.height or scene.cameras.height // 4 * 4
    frames = preprocess_scene(scene, DatasetConfig(width=width, height=height, near=0.0, far=0.0),
                              frames=context + target, use_config_depth_range=False)
    pixels = frames.images.float() / 255.0
    cameras = frames.cameras.to(dtype=torch.float32)
    n = len(context)
    return Sample(name, context, target, pixels[:n], cameras.select(list(range(n))), pixels[n:],
                  cameras.select(list(range(n, n + len(target)))))


def nearest_context_images(context_images: torch.Tensor, context_cameras: Cameras,
                           target_cameras: Cameras) -> torch.Tensor:
    """[T,3,H,W]: for each target camera, the context image [V,3,H,W] whose camera centre is nearest to its own
    (the "copy the nearest context view" prediction)."""
    distance = torch.cdist(target_cameras.centers.double(), context_cameras.centers.double())
    return context_images[distance.argmin(dim=1)]


# --------------------------------------------------------------------------------------------------
# Running the methods
@contextlib.contextmanager
def backbone_clock(model: torch.nn.Module, device: torch.device) -> Iterator[dict]:
    """Record in the yielded dict, under ``"features_done"``, the clock time when the backbone's last
    module (``model.refine_pre``, which outputs F_c) finishes: splits encoder time into GS generation and
    compression."""
    marks: dict[str, float] = {}

    def hook(*_):
        synchronize(device)
        marks["features_done"] = time.perf_counter()

    handle = model.refine_pre.register_forward_hook(hook)
    try:
        yield marks
    finally:
        handle.remove()


class Evaluator:
    """Runs every method on samples and scores the renders.

    Args:
        model: a :class:`CodecSplat` with its codec, in eval mode, on ``device``.
        metrics: the image metrics.
        lambdas: CodecSplat operating points.
        baselines: subset of :data:`BASELINE_NAMES`.
        png: the PNG baseline with its settings (K_SH and Lloyd steps).
    """

    def __init__(self, model, metrics: ImageMetrics, lambdas, baselines, device: torch.device,
                 png: PngCompression = PngCompression()):
        self.model = model
        self.metrics = metrics
        self.lambdas = [float(lam) for lam in lambdas]
        self.baselines = list(baselines)
        self.device = device
        self.ply_deflate = PlyDeflate()
        self.png = png
        self.feature = FeatureDeflate()

    @property
    def steps_per_sample(self) -> int:
        """Methods run per sample (progress bar units)."""
        return 2 + len(self.lambdas) + len(self.baselines)

    def warm_up(self, sample: Sample) -> None:
        """Run the network, codec and renderer once, untimed (loads Warp kernels, warms allocators)."""
        sample = sample.to(self.device)
        with torch.no_grad(), self._autocast():
            self.model(sample.context_images, sample.context_cameras)
        data = self.model.encode(sample.context_images, sample.context_cameras, self.lambdas[0])
        self.model.render(self.model.decode(data), sample.target_cameras)

    def run(self, sample: Sample, progress: tqdm | None = None) -> list[Row]:
        """Every method's :class:`Row` on one sample."""
        sample = sample.to(self.device)
        rows = []

        def step(row: Row) -> None:
            rows.append(row)
            if progress is not None:
                progress.update(1)

        step(self._copy_nearest(sample))
        for lam in self.lambdas:
            step(self._codecsplat(sample, lam))
        with torch.no_grad(), self._autocast():
            out, gen_s = timed(lambda: self.model(sample.context_images, sample.context_cameras), self.device)
        gaussians = out["gaussians"].detach()
        step(self._gaussian_codec(sample, BACKBONE + "→PLY", "float32", gaussians, gen_s, encode_ply, decode_ply))
        if "ply" in self.baselines:
            step(self._gaussian_codec(sample, BACKBONE + "→PLY+Deflate", self.ply_deflate.setting, gaussians, gen_s,
                                      self.ply_deflate.encode, self.ply_deflate.decode))
        if "png" in self.baselines:
            step(self._gaussian_codec(sample, BACKBONE + "→PNG", self.png.setting, gaussians, gen_s,
                                      self.png.encode, self.png.decode))
        if "feature" in self.baselines:
            step(self._feature_codec(sample, out, gen_s))
        return rows

    def _autocast(self):
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.device.type == "cuda")

    def _score(self, gaussians: Gaussians, sample: Sample) -> dict[str, float]:
        """Mean of each metric over the target views rendered from ``gaussians``."""
        with torch.no_grad():
            rgb = self.model.render(gaussians, sample.target_cameras)["rgb"]
        values = self.metrics(rgb, sample.target_images)
        return {name: statistics.fmean(v) for name, v in values.items()}

    def _copy_nearest(self, sample: Sample) -> Row:
        rgb = nearest_context_images(sample.context_images, sample.context_cameras, sample.target_cameras)
        values = self.metrics(rgb, sample.target_images)
        return Row(sample.scene, COPY_NEAREST, "no bitstream", 0, {name: statistics.fmean(v) for name, v in values.items()},
                   0.0, 0.0, 0.0)

    def _codecsplat(self, sample: Sample, lam: float) -> Row:
        with backbone_clock(self.model, self.device) as marks:
            synchronize(self.device)
            start = time.perf_counter()
            encoded = self.model.encode_scene(sample.context_images, sample.context_cameras, lam)
            synchronize(self.device)
            end = time.perf_counter()
        decoded, decompress_s = timed(lambda: self.model.decode_scene(encoded.data), self.device)
        return Row(sample.scene, CODECSPLAT, f"λ={lam:g}", len(encoded.data), self._score(decoded.gaussians, sample),
                   gen_s=marks["features_done"] - start, compress_s=end - marks["features_done"],
                   decompress_s=decompress_s, lam=lam, parts=bytes_report(encoded.data))

    def _gaussian_codec(self, sample: Sample, method: str, setting: str, gaussians: Gaussians, gen_s: float,
                        encode: Callable, decode: Callable) -> Row:
        data, compress_s = timed(lambda: encode(gaussians), self.device)
        decoded, decompress_s = timed(lambda: decode(data, self.device), self.device)
        return Row(sample.scene, method, setting, len(data), self._score(decoded, sample), gen_s, compress_s,
                   decompress_s)

    def _feature_codec(self, sample: Sample, out: dict, gen_s: float) -> Row:
        data, compress_s = timed(lambda: self.feature.encode(out["F_c"], out["D_enc"], sample.context_cameras),
                                 self.device)

        def decode() -> Gaussians:
            scene = self.feature.decode(data, self.device)
            with torch.no_grad(), self._autocast():
                return self.model.decode_gaussians(scene.feature, scene.depth, scene.cameras)

        decoded, decompress_s = timed(decode, self.device)
        return Row(sample.scene, "CodecSplat w/ Deflate", self.feature.setting, len(data), self._score(decoded, sample),
                   gen_s, compress_s, decompress_s)


# --------------------------------------------------------------------------------------------------
# Summaries, tables, plots
def summarize(rows: list[Row]) -> list[dict]:
    """Mean over samples of every (method, setting), in first-appearance order."""
    groups: dict[tuple[str, str], list[Row]] = {}
    for row in rows:
        groups.setdefault((row.method, row.setting), []).append(row)
    summary = []
    for (method, setting), group in groups.items():
        entry = {"method": method, "setting": setting, "lam": group[0].lam, "samples": len(group),
                 "bytes": statistics.fmean(r.bytes for r in group)}
        for name in group[0].metrics:
            entry[name] = statistics.fmean(r.metrics[name] for r in group)
        for key in ("gen_s", "compress_s", "decompress_s"):
            entry[key] = statistics.fmean(getattr(r, key) for r in group)
        summary.append(entry)
    return summary


def format_bytes(count: float) -> str:
    """Bytes as the paper prints them: KiB below 1 MiB, MiB above."""
    return f"{count / 2**20:.2f} MiB" if count >= 2**20 else f"{count / 2**10:.2f} KiB"


TABLE1_COLUMNS = [("method", "Method", "s"), ("setting", "Codec Setting", "s"), ("bytes_text", "Bytes/scene ↓", "s"),
                  ("psnr", "PSNR ↑", ".2f"), ("ssim", "SSIM ↑", ".3f"), ("lpips_vgg", "LPIPS-VGG ↓", ".3f"),
                  ("lpips_alex", "LPIPS-Alex ↓", ".3f")]
TABLE2_COLUMNS = [("method", "Method", "s"), ("setting", "Codec Setting", "s"), ("gen_s", "GS Gen. T. ↓", ".3f"),
                  ("compress_s", "Compress T. ↓", ".3f"), ("decompress_s", "Decompress T. ↓", ".3f")]


def table1(summary: list[dict]) -> str:
    """Table 1 (and 4): bytes per scene and target-view quality of every method (n/a: LPIPS without weights)."""
    return format_table([{**s, "bytes_text": format_bytes(s["bytes"])} for s in _paper_order(summary)], TABLE1_COLUMNS)


def table2(summary: list[dict]) -> str:
    """Table 2: GS generation, compression and decompression seconds; CodecSplat averaged over its lambdas."""
    rows = [s for s in _paper_order(summary) if s["method"] not in (CODECSPLAT, COPY_NEAREST)]
    codec = [s for s in summary if s["method"] == CODECSPLAT]
    if codec:
        lams = sorted(s["lam"] for s in codec)
        setting = f"λ={lams[0]:g}" if len(lams) == 1 else f"λ={lams[0]:g},…,{lams[-1]:g}"
        mean = {k: statistics.fmean(s[k] for s in codec) for k in ("gen_s", "compress_s", "decompress_s")}
        rows.append({"method": CODECSPLAT, "setting": setting, **mean})
    return format_table(rows, TABLE2_COLUMNS)


def _paper_order(summary: list[dict]) -> list[dict]:
    """Baselines and the reference first, CodecSplat rows (by lambda) last, as in the paper."""
    return [s for s in summary if s["method"] != CODECSPLAT] + sorted(
        (s for s in summary if s["method"] == CODECSPLAT), key=lambda s: s["lam"])


def plot_rate_distortion(summary: list[dict], path: pathlib.Path) -> None:
    """Quality against bytes per scene (log scale): CodecSplat's lambda curve, baselines as points."""
    names = [n for n in ("psnr", "ssim", "lpips_alex") if n in summary[0]]
    labels = {"psnr": "PSNR (dB) ↑", "ssim": "SSIM ↑", "lpips_alex": "LPIPS-Alex ↓"}
    fig, axes = _figure(len(names))
    for ax, name in zip(axes, names):
        _plot_methods(ax, summary, x=lambda s: s["bytes"] / 1024, y=lambda s, n=name: s[n], connect=True)
        ax.set_xlabel("KiB per scene")
        ax.set_ylabel(labels[name])
    _save(fig, axes, path)


def plot_distortion_vs_time(summary: list[dict], path: pathlib.Path) -> None:
    """PSNR against encoder (GS generation + compression) and decoder seconds, log scale."""
    fig, axes = _figure(2)
    for ax, (label, x) in zip(axes, (("encode s (GS gen. + compress)", lambda s: s["gen_s"] + s["compress_s"]),
                                      ("decompress s", lambda s: s["decompress_s"]))):
        _plot_methods(ax, summary, x=x, y=lambda s: s["psnr"], connect=False)
        ax.set_xlabel(label)
        ax.set_ylabel("PSNR (dB) ↑")
    _save(fig, axes, path)


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
    """CodecSplat's operating points (joined in lambda order when ``connect``) and one marker per other method,
    on a log x axis; the copy-nearest floor (no bytes, no time) as a dashed horizontal line."""
    codec = sorted((s for s in summary if s["method"] == CODECSPLAT), key=lambda s: s["lam"])
    if codec:
        ax.plot([x(s) for s in codec], [y(s) for s in codec], "o-" if connect else "o", color="C3", label=CODECSPLAT,
                zorder=3)
        for s in codec:
            ax.annotate(f"λ={s['lam']:g}", (x(s), y(s)), textcoords="offset points", xytext=(4, -10), fontsize=7)
    styles = zip("sD^vP*X", ("C0", "C1", "C2", "C4", "C5", "C6", "C7"))
    for s, (marker, colour) in zip((s for s in summary if s["method"] not in (CODECSPLAT, COPY_NEAREST)), styles):
        ax.plot([x(s)], [y(s)], marker, color=colour, label=f"{s['method']} ({s['setting']})")
    for s in summary:
        if s["method"] == COPY_NEAREST:
            ax.axhline(y(s), color="0.4", ls="--", lw=1, label=f"{COPY_NEAREST} (0 bytes)")
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(pyplot().NullFormatter())
    ax.grid(True, which="both", alpha=0.3)


def _save(fig, axes, path: pathlib.Path) -> None:
    axes[0].legend(fontsize=7, loc="best")
    save_figure(fig, path)


def save_figure(fig, path: pathlib.Path) -> None:
    """Write a matplotlib figure as PNG (atomically) and close it."""
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=130)
    pyplot().close(fig)


# --------------------------------------------------------------------------------------------------
# Entry point
@dataclass
class EvalConfig:
    """Options of ``codecsplat eval`` (see :func:`evaluate`)."""

    data: str
    out: str = "codecsplat-eval"
    protocol: str = "re10k"
    lambdas: tuple[float, ...] = PAPER_LAMBDAS
    baselines: tuple[str, ...] = BASELINE_NAMES
    samples_per_scene: int = 1
    target_views: int | None = None
    lpips_weights: str | None = None
    png_sh_clusters: int = 8192
    kmeans_iterations: int = 10
    progress: bool = True
    scenes: tuple[str, ...] = ()
    """Scene folder names to keep (e.g. the held-out ones); empty keeps every scene under ``data``."""
    index: str | None = None
    """Evaluation index file: the scenes and their context/target frames (``samples_per_scene`` unused)."""


def evaluate(model, config: EvalConfig, device: torch.device) -> dict:
    """Evaluate ``model`` on every scene of ``config.data``; write results.json, tables.md and the plots.

    Scenes with too few views for the protocol are skipped and listed under ``skipped``. results.json is
    rewritten after every sample (``samples_done`` of ``samples_total``), so an interrupted run keeps its rows.

    Returns:
        {"config", "device", "machine", "model_id", "scenes", "skipped", "lpips", "files", "samples_done",
        "samples_total", "summary", "rows", "tables"}.
    Raises:
        InputError: unknown protocol or baseline, empty lambda list; DataError: no usable scene.
    """
    protocol = _protocol(config)
    unknown = sorted(set(config.baselines) - set(BASELINE_NAMES))
    if unknown:
        raise InputError(f"unknown baseline(s) {', '.join(unknown)}; choose from {', '.join(BASELINE_NAMES)}")
    if not config.lambdas:
        raise InputError("give at least one lambda")
    for lam in config.lambdas:
        check_lambda(lam)
    png = PngCompression(sh_clusters=config.png_sh_clusters, kmeans_iterations=config.kmeans_iterations)
    metrics = ImageMetrics(config.lpips_weights, device)
    samples, skipped = [], []
    paths = select_scenes(find_scenes(config.data), tuple(sorted(config.scenes)))
    if config.index:
        samples = index_samples(paths, config.index, protocol)
    else:
        for path in paths:
            try:
                samples += scene_samples(path, protocol, protocol.context_views or model.config.num_views,
                                         config.samples_per_scene)
            except DataError as exc:
                skipped.append({"scene": path.name, "reason": str(exc)})
    if not samples:
        raise DataError(f"no scene under {config.data} is usable with the {protocol.name} protocol: "
                        + "; ".join(f"{s['scene']}: {s['reason']}" for s in skipped))
    evaluator = Evaluator(model, metrics, config.lambdas, config.baselines, device, png)
    out = pathlib.Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"json": out / "results.json", "markdown": out / "tables.md", "rate_distortion": out / "rate_distortion.png",
             "distortion_vs_time": out / "distortion_vs_time.png"}
    header = {
        "config": {**asdict(config), "protocol": asdict(protocol)}, "device": str(device),
        "machine": machine_name(device), "model_id": model_id(model), "scenes": sorted({s.scene for s in samples}),
        "skipped": skipped, "lpips": metrics.lpips_missing or "LPIPS-VGG and LPIPS-Alex v0.1",
        "files": {k: str(v) for k, v in files.items()},
    }
    evaluator.warm_up(samples[0])
    rows: list[Row] = []
    with tqdm(total=len(samples) * evaluator.steps_per_sample, desc="eval", unit="method",
              disable=None if config.progress else True) as progress:  # None: only on a terminal
        for done, sample in enumerate(samples, 1):
            progress.set_postfix_str(sample.scene)
            rows += evaluator.run(sample, progress)
            # after every sample, so an interrupted run keeps what it measured
            write_json(files["json"], {**header, "samples_done": done, "samples_total": len(samples),
                                       "summary": summarize(rows), "rows": [asdict(r) for r in rows]})
    summary = summarize(rows)
    result = {**header, "samples_done": len(samples), "samples_total": len(samples), "summary": summary,
              "rows": [asdict(r) for r in rows], "tables": {"table1": table1(summary), "table2": table2(summary)}}
    write_json(files["json"], result)
    write_text(files["markdown"], markdown_report(result))
    plot_rate_distortion(summary, files["rate_distortion"])
    plot_distortion_vs_time(summary, files["distortion_vs_time"])
    return result


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
        result["tables"]["table1"],
        "",
        "## Table 2: timing (seconds)",
        "",
        result["tables"]["table2"],
        "",
    ]
    if result["skipped"]:
        lines += ["Skipped: " + "; ".join(f"{s['scene']} ({s['reason']})" for s in result["skipped"]), ""]
    return "\n".join(lines)


def _protocol(config: EvalConfig) -> Protocol:
    if config.protocol not in PROTOCOLS:
        raise InputError(f"unknown protocol {config.protocol!r}; choose one of {', '.join(PROTOCOLS)}")
    protocol = PROTOCOLS[config.protocol]
    if config.target_views is not None:
        if config.target_views < 1:
            raise InputError(f"target views must be >= 1, got {config.target_views}")
        protocol = Protocol(protocol.name, protocol.width, protocol.height, protocol.context_views, config.target_views)
    if config.samples_per_scene < 1:
        raise InputError(f"samples per scene must be >= 1, got {config.samples_per_scene}")
    return protocol
