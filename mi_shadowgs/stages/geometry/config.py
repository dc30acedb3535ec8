"""Stage 1's settings: ``GeometryConfig`` (paper defaults; the presets are in
``mi_shadowgs.presets``, the reasons for non-paper values in docs/decisions.md) and its
form for views without masks (``unmasked``)."""

from __future__ import annotations

import dataclasses

from mi_shadowgs.config import check_fields
from mi_shadowgs.core import losses
from mi_shadowgs.core.raster import RasterConfig
from mi_shadowgs.stages.geometry.densify import DensifyConfig

INITS = ("hull", "random", "points")
GAIN_MODES = ("auto", "on", "off")  # ``view_gains``
DARK_ALPHA_SUPPORTS = ("none", "points")  # see ``background``
BACKDROPS = ("auto", "black")  # see ``background``


@dataclasses.dataclass(frozen=True)
class GeometryConfig:
    """Stage-1 hyperparameters; defaults are the paper's (and 2DGS's where it is silent)."""

    iterations: int = 40000
    sh_degree: int = 3
    sh_degree_interval: int = 1000  # one more active SH degree every so many iterations
    # Learning rates (3DGS/2DGS); position ones are multiplied by the scene extent.
    lr_position_init: float = 0.00016
    lr_position_final: float = 0.0000016
    lr_position_delay_mult: float = 0.01
    lr_position_delay_steps: int = 0
    lr_position_max_steps: int | None = None  # None: the whole run
    lr_sh_dc: float = 0.0025
    lr_sh_rest: float = 0.0025 / 20.0
    lr_opacity: float = 0.05
    lr_scale: float = 0.005
    lr_rotation: float = 0.001
    # Loss weights (paper Sec. V: l_n, l_d, l_o = 0.05, 1000, 0.01; 2DGS: l_ssim = 0.2).
    lambda_dssim: float = 0.2
    lambda_normal: float = 0.05
    lambda_dist: float = 1000.0
    lambda_mask: float = 0.01
    normal_from: int = 7000  # 2DGS switches the regularisers on late
    # How the normal-consistency term's depth normals are differenced
    # (``losses.depth_normals``): "central" (2DGS) or "same_plane".
    normal_depth_differences: str = "central"
    dist_from: int = 3000
    # Initialisation.
    # "hull" (visual hull of the masks) or "random" (scene bounds); "points" (the SfM points)
    # is what "hull" becomes on views without masks.
    init: str = "hull"
    init_points: int = 100_000
    init_opacity: float = 0.1  # not 0.5: logit 0 is a known zero-gradient point
    hull_resolution: int = 96
    # The hull's cube: centre +- the mean camera distance when None; else this many times
    # the half-width a typical view sees at the centre (``view_radius``).
    hull_extent: float | None = None
    init_consistent_fraction: float = 0.0  # share of hull points in photo-consistent cells
    init_consistent_top: float = 0.05  # ... which are this share of the hull's cells, best first
    init_scale_factor: float = 1.0  # initial std-dev = factor * mean 3-NN distance (3DGS: 1)
    # Views without masks only: lambda * L1 of the rendered alpha at the training pixels
    # whose channels are all <= dark_max (a black background): transparency preferred where
    # it costs nothing. The default scene's background is 0; its object and base are above
    # 1e-3 but for 0.013% of their test pixels (shadows get indirect light), so the term does
    # not hollow out shadowed receivers there. A lit background leaves it no pixels.
    lambda_dark_alpha: float = 0.0
    dark_max: float = 1.0 / 255.0
    # One RGB gain per training view, times the render in the photometric loss (a camera's
    # exposure and white balance per photo; ``gains``): "on", "off", or "auto" (on for
    # datasets imported from photos, off for generated ones, whose exposure is constant).
    view_gains: str = "auto"
    lr_view_gain: float = 0.05  # Adam learning rate of the views' log gains (per view step)
    # Which dark pixels the term acts on (``background``): "points", those whose rays miss
    # the SfM points' support (a cast shadow on the mat is dark too); "none", every one.
    dark_alpha_support: str = "points"
    dark_alpha_margin: float = 0.05  # the support grown by this much (object radii)
    # What lies behind the surfels in views without masks (``background``): "auto", one
    # colour estimated from the pixels that miss the SfM points' support (a lit room; black
    # where there are none), or "black" (the paper's darkroom).
    backdrop: str = "auto"
    densify: DensifyConfig = DensifyConfig()
    raster: RasterConfig = RasterConfig()
    seed: int = 0
    # Training views without masks (``unmasked``): their distortion and normal weights
    # (None keeps the masked ones) and whether the opacity resets.
    unmasked_lambda_dist: float | None = None
    unmasked_lambda_normal: float | None = None
    unmasked_opacity_reset: bool = False
    # ... and their dark-alpha weight: without masks a black opaque floater in front of a
    # black background renders as empty space does (docs/decisions.md).
    unmasked_lambda_dark_alpha: float = 0.1
    # ... and their surfel cap in place of ``densify.max_surfels`` (None keeps it): without
    # masks stage 1 also fits the ground out to the photos' edges.
    unmasked_max_surfels: int | None = None
    # After training: remove the surfels whose centre projects outside the training masks,
    # each dilated by ``hull_prune_dilate`` px, in at least ``hull_prune_views`` views
    # (``prune_outside_masks``); 0 keeps them all, as the paper does. Views without masks do
    # not vote.
    hull_prune_views: int = 0
    hull_prune_dilate: int = 1
    # Reporting (the loop reads losses back only at these intervals).
    log_every: int = 100
    preview_every: int = 2000
    checkpoint_every: int = 2000
    # ... and at least this often in wall time (a kill loses at most this much work).
    checkpoint_seconds: float = 60.0

    def __post_init__(self):
        check_fields(self, (
            ("iterations", self.iterations >= 1, ">= 1"),
            ("sh_degree", 0 <= self.sh_degree <= 3, "in [0, 3]"),
            ("sh_degree_interval", self.sh_degree_interval >= 1, ">= 1"),
            *((name, getattr(self, name) >= 0, ">= 0") for name in (
                "lr_position_init", "lr_position_final", "lr_sh_dc", "lr_sh_rest",
                "lr_opacity", "lr_scale", "lr_rotation", "lambda_dssim", "lambda_normal",
                "lambda_dist", "lambda_mask", "lambda_dark_alpha", "normal_from", "dist_from",
                "lr_position_delay_steps", "unmasked_lambda_dark_alpha")),
            ("init", self.init in INITS, f"one of {INITS}"),
            ("view_gains", self.view_gains in GAIN_MODES, f"one of {GAIN_MODES}"),
            ("lr_view_gain", self.lr_view_gain > 0, "> 0"),
            ("backdrop", self.backdrop in BACKDROPS, f"one of {BACKDROPS}"),
            ("dark_alpha_support", self.dark_alpha_support in DARK_ALPHA_SUPPORTS,
             f"one of {DARK_ALPHA_SUPPORTS}"),
            ("dark_alpha_margin", 0 <= self.dark_alpha_margin < float("inf"),
             "finite and >= 0 (object radii)"),
            ("hull_extent", self.hull_extent is None or self.hull_extent > 0, "> 0 or None"),
            ("normal_depth_differences",
             self.normal_depth_differences in losses.DEPTH_NORMAL_DIFFERENCES,
             f"one of {losses.DEPTH_NORMAL_DIFFERENCES}"),
            ("init_points", self.init_points >= 1, ">= 1"),
            ("unmasked_max_surfels", self.unmasked_max_surfels is None
             or self.unmasked_max_surfels >= 1, ">= 1 or None"),
            ("init_opacity", 0 < self.init_opacity < 1, "in (0, 1)"),
            ("hull_resolution", self.hull_resolution >= 2, ">= 2"),
            ("init_consistent_fraction", 0 <= self.init_consistent_fraction <= 1, "in [0, 1]"),
            ("init_consistent_top", 0 < self.init_consistent_top <= 1, "in (0, 1]"),
            ("init_scale_factor", self.init_scale_factor > 0, "> 0"),
            ("hull_prune_views", self.hull_prune_views >= 0, ">= 0 (0: no prune)"),
            ("hull_prune_dilate", self.hull_prune_dilate >= 0, ">= 0 (pixels)"),
            ("log_every", self.log_every >= 1, ">= 1"),
            ("preview_every", self.preview_every >= 1, ">= 1"),
            ("checkpoint_every", self.checkpoint_every >= 1, ">= 1"),
            ("checkpoint_seconds", self.checkpoint_seconds > 0, "> 0")))


def unmasked(config: GeometryConfig) -> GeometryConfig:
    """``config`` for training views without masks: its ``unmasked_*`` settings in place of
    the distortion, normal and dark-alpha weights, the opacity reset and the surfel cap
    (see the fields' comments; a None keeps the masked setting). Without the reset, the
    world-space prune of large surfels starts at the iteration of the first reset."""
    densify = config.densify
    if not config.unmasked_opacity_reset and densify.opacity_reset_interval > 0:
        # else nothing stops a surfel from growing into a sheet over the room's backdrop
        after = densify.world_prune_after
        densify = dataclasses.replace(densify, opacity_reset_interval=0, world_prune_after=(
            densify.opacity_reset_interval if after is None else after))
    if config.unmasked_max_surfels is not None:
        densify = dataclasses.replace(densify, max_surfels=config.unmasked_max_surfels)
    dist, normal = config.unmasked_lambda_dist, config.unmasked_lambda_normal
    return dataclasses.replace(config,
                               lambda_dist=config.lambda_dist if dist is None else dist,
                               lambda_normal=config.lambda_normal if normal is None else normal,
                               lambda_dark_alpha=config.unmasked_lambda_dark_alpha,
                               densify=densify)
