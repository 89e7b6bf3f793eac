"""The encoder presets and the settings of one optimisation (:class:`RDOConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass


from ...choices import (RDO_CROSS_VIEW_MAX_VIEWS, RDO_CROSS_VIEW_MIN_STEPS, RDO_CROSS_VIEW_WEIGHT, RDO_MIN_PRESET_STEPS,
                        RDO_PRESETS)
from ...errors import InputError


LATENT_LIMIT = 4096.0
"""Latents are clamped to [-LATENT_LIMIT, LATENT_LIMIT] quantisation steps after every step."""


VARIABLES = ("latents", "feature")
"""What the optimisation can move (:attr:`RDOConfig.variable`)."""


PRESETS = tuple(RDO_PRESETS)
"""The presets' names: ``fast`` is the amortised encoder alone (the API's default), ``medium`` and ``slow`` optimise
(:func:`preset_steps`)."""


def preset_steps(preset: str, views: int) -> int:
    """Optimisation steps of ``preset`` for ``views`` context views: :data:`~codecsplat_warp.choices.RDO_PRESETS`'s
    factor times views squared, at least :data:`~codecsplat_warp.choices.RDO_MIN_PRESET_STEPS`, and at least the
    preset's :data:`~codecsplat_warp.choices.RDO_CROSS_VIEW_MIN_STEPS` where the cross-view term is on
    (:func:`cross_view_default`): 25 / 160 for 2 views, 80 / 320 for 8 (0 for ``fast``). InputError for an unknown
    preset."""
    if preset not in RDO_PRESETS:
        raise InputError(f"unknown RDO preset {preset!r}; choose one of {', '.join(PRESETS)}")
    factor = RDO_PRESETS[preset]
    if factor == 0:
        return 0
    least = RDO_CROSS_VIEW_MIN_STEPS[preset] if cross_view_default(views) > 0 else RDO_MIN_PRESET_STEPS
    return max(least, round(factor * views * views))


def cross_view_default(views: int) -> float:
    """The tuned cross-view weight for ``views`` context views: :data:`~codecsplat_warp.choices.
    RDO_CROSS_VIEW_WEIGHT` for 2 to :data:`~codecsplat_warp.choices.RDO_CROSS_VIEW_MAX_VIEWS` views, else 0."""
    return RDO_CROSS_VIEW_WEIGHT if 2 <= views <= RDO_CROSS_VIEW_MAX_VIEWS else 0.0


@dataclass(frozen=True)
class RDOConfig:
    """Settings of one optimisation.

    Attributes:
        steps: Adam steps (0: none, the amortised latents); None runs until ``time_budget`` is spent.
        time_budget: wall seconds the steps may take (None: no limit); the run stops at whichever of ``steps``
            and ``time_budget`` comes first.
        learning_rate: Adam's step at the start, in quantisation steps of the gained grid; it falls on a cosine to
            ``final_lr_fraction`` of that over the run (by steps, or by the budget's seconds when that ends sooner).
        final_lr_fraction: see ``learning_rate``.
        rate_weight: beta, the weight of the rate in bits per context pixel (the shipped model's stage-2 value).
        cross_view_weight: weight of the cross-view term (:func:`cross_view_error`; 0: off; needs at least 2
            views). :func:`rdo_config` sets the tuned one for the view count (:func:`cross_view_default`).
        depth_weight: weight of |S - S_amortised|_1 (0: off).
        perceptual_weight: weight of a perceptual distance (LPIPS) of the context renders (0: off; needs the
            ``perceptual`` network, see :func:`rdo_target`).
        anchor_weight: weight of the mean squared change of the latents from the amortised ones, in quantisation
            steps squared (0: off).
        check_every: steps between two real codings of the latents (the best measured is kept); 0 codes only the
            amortised latents and the last ones.
        seed: seed of the training quantiser's noise.
        precision: ``"float32"`` or ``"bfloat16"`` (bf16 autocast for the networks, on CUDA and on the CPU; the
            geometry, the rasterizer and the real codings at the checks stay float32).
        cuda_graphs: on CUDA, run the decoder up to the Gaussians (:class:`GraphedDecoder`, in either precision)
            and the loss's fixed terms (:func:`context_loss`) as CUDA graphs captured once per run; ignored on the
            CPU.
        variable: what Adam moves: ``"latents"`` (the posterior means on the gained grid) or ``"feature"`` (the
            encoder's F_c, through the codec's analysis and posterior; :func:`optimise_latents` then needs it).
        feature_step: with ``variable="feature"``, Adam's start step as a fraction of the amortised F_c's standard
            deviation (``learning_rate`` is the step for the latents).
        rounding: the training quantiser's: ``"noise"`` (straight-through rounding to the decoder, the rate at
            uniform noise) or ``"annealed"`` (stochastic Gumbel annealing for both, its temperature falling
            geometrically from ``anneal_start`` to ``anneal_end`` over the run; :class:`~codecsplat_warp.codec.
            latent.NoisyQuantizer`).
        anneal_start, anneal_end: see ``rounding``.
    """

    steps: int | None = 0
    time_budget: float | None = None
    learning_rate: float = 0.1
    final_lr_fraction: float = 0.1
    rate_weight: float = 1.3e-3
    cross_view_weight: float = 0.0
    depth_weight: float = 0.0
    perceptual_weight: float = 0.0
    anchor_weight: float = 0.0
    check_every: int = 100
    seed: int = 0
    precision: str = "float32"
    cuda_graphs: bool = True
    variable: str = "latents"
    feature_step: float = 0.01
    rounding: str = "noise"
    anneal_start: float = 0.5
    anneal_end: float = 0.05

    def __post_init__(self) -> None:
        if self.steps is None and self.time_budget is None:
            raise InputError("RDO needs a step count or a time budget (both are None)")
        if self.steps is not None and (isinstance(self.steps, bool) or not isinstance(self.steps, int)
                                       or self.steps < 0):
            raise InputError(f"RDO steps must be an integer >= 0, got {self.steps!r}")
        if self.time_budget is not None and not (math.isfinite(self.time_budget) and self.time_budget > 0):
            raise InputError(f"the RDO time budget must be a number of seconds > 0, got {self.time_budget!r}")
        positive = {"learning_rate": self.learning_rate, "final_lr_fraction": self.final_lr_fraction,
                    "feature_step": self.feature_step, "anneal_start": self.anneal_start,
                    "anneal_end": self.anneal_end}
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"RDOConfig.{name} must be > 0, got {value!r}")
        weights = {"rate_weight": self.rate_weight, "cross_view_weight": self.cross_view_weight,
                   "depth_weight": self.depth_weight, "perceptual_weight": self.perceptual_weight,
                   "anchor_weight": self.anchor_weight}
        for name, value in weights.items():
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"RDOConfig.{name} must be >= 0, got {value!r}")
        if self.check_every < 0:
            raise InputError(f"RDOConfig.check_every must be >= 0, got {self.check_every}")
        if self.rounding not in ("noise", "annealed"):
            raise InputError(f"RDOConfig.rounding must be noise or annealed, got {self.rounding!r}")
        if self.variable not in VARIABLES:
            raise InputError(f"RDOConfig.variable must be one of {', '.join(VARIABLES)}, got {self.variable!r}")
        if self.variable == "feature" and self.anchor_weight > 0:
            raise InputError("RDOConfig.anchor_weight needs variable='latents' (it measures the latents' change)")
        if self.precision not in ("float32", "bfloat16"):
            raise InputError(f"RDOConfig.precision must be float32 or bfloat16, got {self.precision!r}")

    @property
    def optimises(self) -> bool:
        """Whether this config takes any step (False: the amortised encoder alone)."""
        return self.steps != 0


def rdo_config(preset: str = "fast", steps: int | None = None, time_budget: float | None = None,
               seed: int = 0, views: int = 2, **settings) -> RDOConfig:
    """The :class:`RDOConfig` of a preset for ``views`` context views (:func:`preset_steps`), with ``steps``
    (overrides the preset's count), ``time_budget`` and any other field given. Unless given, ``cross_view_weight``
    is the tuned one for the view count (:func:`cross_view_default`), with a preset or an explicit step count alike.

    With a ``time_budget`` and neither ``steps`` nor a preset that optimises, the steps are unlimited: the budget
    alone ends the run.

    Raises:
        InputError: an unknown preset, steps < 0, a budget <= 0, or another bad setting.
    """
    preset_count = preset_steps(preset, views)
    settings.setdefault("cross_view_weight", cross_view_default(views))
    if steps is None:
        steps = preset_count
        if time_budget is not None and steps == 0:
            steps = None
    return RDOConfig(steps=steps, time_budget=time_budget, seed=seed, **settings)
