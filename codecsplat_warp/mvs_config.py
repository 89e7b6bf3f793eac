"""The parameters of multi-view stereo depth (:func:`codecsplat_warp.ops.mvs_depth`, ``codecsplat depth``), in a
module that imports neither torch nor Warp, so that the command line can show their defaults at once.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from .errors import InputError

MAX_SOURCES = 8
"""Most source views per reference view: the length of the vector the MVS kernels sort the per-source costs in
(``codecsplat_warp.kernels.mvs.MAX_SOURCES``, which a test holds equal to this)."""


@dataclass(frozen=True)
class MVSConfig:
    """Parameters of :func:`mvs_depth` (units in brackets).

    Attributes:
        num_planes: sweep planes, uniform in inverse depth between each view's near and far.
        num_sources: source views per reference view (at most :data:`MAX_SOURCES`); fewer where fewer qualify.
        window_radius: NCC window half-size [samples]: (2 r + 1)^2 samples.
        window_step: distance between window samples [pixels].
        support_contrast: grey-level difference (0-1 scale) from the window's centre pixel at which a sample's
            weight in the NCC halves (samples unlike the centre likely lie on another surface); 0: uniform weights.
        refine_steps: the winner is refined at 1/refine_steps of the plane spacing, then by a parabola fit.
        slant_degrees: tilts [degrees] of the slanted planes tried when refining, each towards the four image
            directions (left, right, up, down), beside the fronto-parallel one; () for fronto-parallel only.
        min_texture: smallest standard deviation of the window's grey levels (in [0,1]) for a confident depth.
        min_ncc: smallest aggregated NCC of the winner for a confident depth.
        min_consistent_views: source views that must agree with a depth to keep it.
        max_reprojection_px: largest reprojection error [pixels] of an agreeing view.
        max_relative_depth: largest relative depth difference of an agreeing view.
        min_overlap: smallest fraction of the reference's pixel grid (at depths from near to far) a source must see.
        min_triangulation_deg, max_triangulation_deg: range of a source's triangulation angle [degrees] at the
            middle depth (geometric mean of near and far) over the reference's pixel grid (median).
        good_triangulation_deg: angle [degrees] sources are preferred at (a Gaussian weight of the angle, 1/3 as
            wide below it as above, times the overlap, ranks the candidates).
        max_view_angle_deg: largest angle [degrees] between the optical axes of the reference and a source.
        views_per_launch: reference views per kernel launch on CUDA (bounds one launch's time; the CPU launches
            one view at a time, split by rows over its threads).
        allow_unmatched: give a view without a usable source view an empty depth map instead of raising
            :class:`~codecsplat_warp.errors.MVSError` (e.g. an isolated view of a 360-degree capture).
    """

    num_planes: int = 128
    num_sources: int = 5
    window_radius: int = 2
    window_step: int = 1
    support_contrast: float = 0.05
    refine_steps: int = 4
    slant_degrees: tuple[float, ...] = (35.0, 60.0)
    min_texture: float = 0.01
    min_ncc: float = 0.3
    min_consistent_views: int = 2
    max_reprojection_px: float = 1.0
    max_relative_depth: float = 0.01
    min_overlap: float = 0.2
    min_triangulation_deg: float = 1.0
    max_triangulation_deg: float = 30.0
    good_triangulation_deg: float = 8.0
    max_view_angle_deg: float = 60.0
    views_per_launch: int = 8
    allow_unmatched: bool = False

    def __post_init__(self) -> None:
        at_least = {"num_planes": 2, "num_sources": 1, "window_radius": 1, "window_step": 1, "refine_steps": 1,
                    "min_consistent_views": 0, "views_per_launch": 1}
        for name, low in at_least.items():
            value = getattr(self, name)
            if not isinstance(value, int) or value < low:
                raise InputError(f"MVSConfig.{name} must be an integer >= {low}, got {value!r}")
        if not all(isinstance(a, (int, float)) and 0 < a < 80 for a in self.slant_degrees):
            raise InputError(f"MVSConfig.slant_degrees must be angles in (0, 80) degrees, got {self.slant_degrees!r}")
        if self.num_sources > MAX_SOURCES:
            raise InputError(f"MVSConfig.num_sources must be <= {MAX_SOURCES}, got {self.num_sources}")
        if self.min_consistent_views > self.num_sources:
            raise InputError(f"MVSConfig.min_consistent_views ({self.min_consistent_views}) exceeds num_sources "
                             f"({self.num_sources})")
        for name in ("support_contrast", "min_texture", "max_reprojection_px", "max_relative_depth", "min_overlap",
                     "min_triangulation_deg", "max_triangulation_deg", "good_triangulation_deg", "max_view_angle_deg"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InputError(f"MVSConfig.{name} must be a finite number >= 0, got {value!r}")
        if not -1.0 <= self.min_ncc <= 1.0:
            raise InputError(f"MVSConfig.min_ncc must be in [-1, 1], got {self.min_ncc!r}")
        if self.min_triangulation_deg >= self.max_triangulation_deg:
            raise InputError(f"MVSConfig needs min_triangulation_deg < max_triangulation_deg, got "
                             f"{self.min_triangulation_deg} and {self.max_triangulation_deg}")

    def to_dict(self) -> dict:
        """Every parameter by name (JSON-serialisable)."""
        return {**asdict(self), "slant_degrees": list(self.slant_degrees)}
