"""Stage 4's settings: ``MaterialConfig`` with its checks, the presets, and the settings
that segments labelled from chromaticity change (``label_source_overrides``)."""

from __future__ import annotations

import dataclasses
import math

from mi_shadowgs.config import LABEL_MAP_SOURCES

SPECULAR_MODES = ("auto", "on", "off")
REFINE_SCORES = ("segment", "irradiance", "albedo")
SETTLE_SCORES = ("segment", "irradiance")
LAMP_MODES = ("off", "auto")
LAMP_POSITION_SCORES = ("shadows", "photometric")
BACKDROP_SURFELS = ("skip", "fit")


@dataclasses.dataclass(frozen=True)
class MaterialConfig:
    """Stage-4 hyperparameters. Defaults are the paper's (Sec. V-A1) where it gives them; why
    each other default is what it is: docs/decisions.md, "Stage 4: material and light"."""

    # Adam steps of the warm-up and the main phase.
    iterations: int = 5000
    # Weight of the indirect light's squared magnitude (Eq. 18, lambda_ind2).
    lambda_ind2: float = 0.01
    # Weight pulling indirect SH that is negative at its surfel's normal back to 0; 0: off.
    lambda_ind_floor: float = 0.0
    # Weight of the indirect light's TV (Eq. 18, lambda_tv).
    lambda_tv: float = 0.01
    # Weight of the materials' TV (Eq. 18, lambda_brdf).
    lambda_brdf: float = 1.0
    # Weight of the roughness/metallic prior E[1 - rho + m] (Eq. 18, lambda_reg).
    lambda_reg: float = 0.001
    # Light grid directions; dw = 2 pi / n_directions.
    n_directions: int = 128
    # Degree of the per-surfel indirect SH.
    sh_degree: int = 2
    # Adam learning rate of the albedo (not in the paper; 3DGS-like magnitudes, as below).
    lr_albedo: float = 0.01
    # Adam learning rate of roughness and metallic.
    lr_material: float = 0.01
    # Adam learning rate of log L_dir.
    lr_light: float = 0.03
    # Adam learning rate of the indirect SH.
    lr_indirect: float = 0.002
    # Initial albedo of every surfel.
    albedo_init: float = 0.5
    # Initial roughness of every surfel.
    roughness_init: float = 0.9
    # Initial metallic of every surfel.
    metallic_init: float = 0.0
    # Initial radiance of every grid direction; 0: mean(target) / albedo_init, from the data.
    light_init: float = 0.0
    # Initial indirect radiance (the SH's DC term).
    indirect_init: float = 0.05
    # Steps before the lights are first pruned and the specular lobe decided on.
    warmup: int = 500
    # Drop the lights that carry little (``prune_threshold``).
    prune: bool = True
    # Lights below this share of the strongest light's irradiance are dropped (after merging).
    prune_threshold: float = 0.1
    # After the warm-up, prune again every this many steps.
    prune_every: int = 50
    # Lights closer than this (degrees) merge into one at their weighted mean; 0: the grid's.
    merge_angle_deg: float = 20.0
    # Shadow-map resolution while every grid direction is live (the warm-up).
    warmup_map_resolution: int = 128
    # Local searches of each light's direction, (radius, step) in degrees, or (radius, step,
    # shadow-map resolution of its candidates; default the visibility's); (): no refinement.
    refine_passes: tuple = ((8.0, 2.0), (2.0, 0.5))
    # The main phase's second refinement's passes; None: refine_passes; (): none.
    refine_again_passes: tuple | None = ((2.0, 0.5),)
    # Training views scored per candidate direction (evenly spaced).
    refine_views: int = 16
    # Only this many of the strongest lights are refined.
    refine_max_lights: int = 4
    # Equal-area directions of the first refinement's global pass over the hemisphere; 0: off.
    refine_global: int = 0
    # The global pass in the main phase's second refinement too (needs refine_global).
    refine_again_global: bool = False
    # Shadow-map resolution of the global pass's candidates.
    refine_global_map_resolution: int = 128
    # Training views scored in the global pass.
    refine_global_views: int = 8
    # How a candidate direction is scored: "segment", "irradiance" or "albedo" (``scoring``).
    refine_score: str = "segment"
    # Share of a pixel's blending weight its segment must hold for the "segment" score.
    refine_segment_purity: float = 0.9
    # A light carrying at least this share of the irradiance is never dropped; 0: no drops.
    drop_share: float = 0.25
    # A light is dropped when the views' error rises by less than this share without it.
    drop_gain: float = 0.1
    # How settling judges the lights: "segment" (a scale per segment) or "irradiance".
    settle_score: str = "segment"
    # Settle the warm-up's pruned lights before the first refinement too.
    settle_warmup: bool = True
    # Local lights: "auto" tests each refined light as a lamp (a position with 1/r^2
    # falloff) against a directional light and keeps what the views prefer; "off": every
    # light directional (the paper's light map).
    lamps: str = "off"
    # Candidate distances of a lamp from the scene centre, in scene-bound radii.
    lamp_distances: tuple = (1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0)
    # A lamp replaces a directional light only when it lowers the views' error by this share.
    lamp_min_gain: float = 0.02
    # A kept lamp's global scan: lamps in this many equal-area directions over the hemisphere
    # at each of ``lamp_scan_distances``; 0: no scan (the search starts along its direction).
    lamp_scan_directions: int = 128
    # The scan's distances from the scene centre, in scene-bound radii.
    lamp_scan_distances: tuple = (1.5, 2.0, 3.0, 4.0, 6.0)
    # Pattern searches of a lamp's position, coarse to fine: (direction step in degrees,
    # distance step as a share of the distance).
    lamp_passes: tuple = ((4.0, 0.16), (1.0, 0.04), (0.25, 0.01))
    # How lamp candidates are scored (as ``refine_score``): "auto" is "albedo" without the
    # lobe (each segment's albedo re-fitted: the falloff is not judged by the albedo fitted
    # under the light before), else "segment".
    lamp_score: str = "auto"
    # What places a kept lamp in its pattern searches: "shadows" (where the photos are in
    # the lamp's shadow against where its shadow maps put it) or "photometric" (lamp_score).
    lamp_position_score: str = "shadows"
    # A pixel is lit by the lamp when its photo, less the other lights and its segment's
    # median indirect light, is over this share of the lamp's unshadowed shading.
    lamp_lit_ratio: float = 0.5
    # Keep the albedo's TV while the segment constraint holds.
    albedo_tv_with_segments: bool = True
    # Hold the support-weighted albedo quantile at this value (no specular lobe); 0: off.
    albedo_scale: float = 0.0
    # The held quantile of the surfels' brightest albedo channel, weighted by support.
    albedo_scale_quantile: float = 0.95
    # Hold the albedo scale every this many steps (each a host read of the albedo).
    albedo_scale_every: int = 10
    # Steps of the normal phase after the main phase; 0: no normal phase (the paper's fit).
    normal_steps: int = 0
    # Adam learning rate of the shading normals.
    lr_normal: float = 0.03
    # Weight of the normal phase's pull toward stage 2's normals, mean(1 - n . n0).
    lambda_normal_prior: float = 0.3
    # Hold the shading normals of stage 2's planar segments in the normal phase.
    normal_hold_planar: bool = True
    # ``normal_steps`` on segments labelled from chromaticity (``label_source_overrides``).
    chromaticity_normal_steps: int = 0
    # ``refine_score`` on segments labelled from chromaticity.
    chromaticity_refine_score: str = "segment"
    # Weight of the per-surfel albedo detail's prior; 0: off (a segment's albedo is constant).
    detail_prior: float = 0.0
    # Bound of the albedo detail's log factor.
    detail_max: float = 1.0
    # Adam learning rate of the albedo detail.
    lr_detail: float = 0.01
    # Pixels this close to a fitted shadow's edge do not move the albedo detail.
    detail_edge_px: int = 1
    # The GGX lobe: "auto" (dropped after the warm-up when the scene looks diffuse), "on", "off".
    specular: str = "auto"
    # "auto" drops the lobe when every surfel's metallic is below this...
    auto_metallic_max: float = 0.1
    # ... and every surfel's roughness above this.
    auto_roughness_min: float = 0.6
    # False: V = 1 in training, rendering and relighting (paper Table 3's ablation).
    use_visibility: bool = True
    # False: no segment-wise albedo averaging (paper Table 3's ablation).
    segment_average: bool = True
    # Training views per Adam step.
    views_per_step: int = 1
    # Pixels with rendered alpha below this are not supervised.
    mask_alpha: float = 0.5
    # Views without masks: "skip" leaves out the surfels that stage 1 grew over a dim room
    # past the ground, and their pixels (``background.PastTheGround``); "fit" fits them.
    backdrop_surfels: str = "skip"
    # Read the loss back (history, progress bar) every this many steps.
    log_every: int = 100
    # Write a resumable checkpoint every this many steps...
    checkpoint_every: int = 1000
    # ... and at least this often in wall-time seconds.
    checkpoint_seconds: float = 60.0
    # Seed of the training views' order.
    seed: int = 0

    def __post_init__(self):
        if self.specular not in SPECULAR_MODES:
            raise ValueError(f"MaterialConfig.specular must be one of {SPECULAR_MODES}, got "
                             f"{self.specular!r}")
        if self.iterations < 0 or self.warmup < 0 or self.views_per_step < 1:
            raise ValueError(f"MaterialConfig: invalid iteration counts: {self}")
        if self.normal_steps < 0 or self.lr_normal <= 0 or self.lambda_normal_prior < 0:
            raise ValueError(f"MaterialConfig: normal_steps >= 0, lr_normal > 0 and "
                             f"lambda_normal_prior >= 0, got {self.normal_steps}, "
                             f"{self.lr_normal}, {self.lambda_normal_prior}")
        if (not all(_valid_pass(p) for p in self.refine_passes + (self.refine_again_passes or ()))
                or self.refine_views < 1 or self.refine_max_lights < 0):
            raise ValueError(f"MaterialConfig.refine_passes and refine_again_passes must be "
                             f"(radius, step) or (radius, step, map resolution) with 0 < step "
                             f"<= radius and an integer resolution >= 8, refine_views >= 1, "
                             f"refine_max_lights >= 0: {self.refine_passes}, "
                             f"{self.refine_again_passes}, {self.refine_views}, "
                             f"{self.refine_max_lights}")
        if (self.refine_global < 0 or self.refine_global_map_resolution < 1
                or self.refine_global_views < 1
                or not 0.0 <= self.drop_share < 1.0 or self.drop_gain < 0):
            raise ValueError(f"MaterialConfig: refine_global >= 0, "
                             f"refine_global_map_resolution >= 1, drop_share in [0, 1), "
                             f"drop_gain >= 0: {self.refine_global}, "
                             f"{self.refine_global_map_resolution}, {self.drop_share}, "
                             f"{self.drop_gain}")
        if self.refine_again_global and not self.refine_global:
            raise ValueError("MaterialConfig.refine_again_global needs the global pass: set "
                             "refine_global > 0 (it is 0)")
        if not 0.0 <= self.refine_segment_purity <= 1.0:
            raise ValueError(f"MaterialConfig.refine_segment_purity must be in [0, 1], got "
                             f"{self.refine_segment_purity}")
        if self.settle_score not in SETTLE_SCORES:
            raise ValueError(f"MaterialConfig.settle_score must be one of {SETTLE_SCORES}, got "
                             f"{self.settle_score!r}")
        if self.lamp_score not in ("auto", *REFINE_SCORES):
            raise ValueError(f"MaterialConfig.lamp_score must be one of "
                             f"{('auto', *REFINE_SCORES)}, got {self.lamp_score!r}")
        for name in ("refine_score", "chromaticity_refine_score", "lamp_score"):
            score = getattr(self, name)
            if score == "auto":
                continue
            if score not in REFINE_SCORES:
                raise ValueError(f"MaterialConfig.{name} must be one of {REFINE_SCORES}, got "
                                 f"{score!r}")
            if score == "albedo" and self.specular != "off":
                # the lobe's dielectric part does not scale with the albedo
                raise ValueError(f"MaterialConfig.{name} 'albedo' needs specular 'off', got "
                                 f"{self.specular!r}: with the lobe set {name} 'segment' too")
        if self.chromaticity_normal_steps < 0:
            raise ValueError(f"MaterialConfig.chromaticity_normal_steps must be >= 0, got "
                             f"{self.chromaticity_normal_steps}")
        if (not 0.0 <= self.albedo_scale <= 1.0 or not 0.0 < self.albedo_scale_quantile <= 1.0
                or self.albedo_scale_every < 1):
            raise ValueError(f"MaterialConfig: albedo_scale in [0, 1] (0 = off), "
                             f"albedo_scale_quantile in (0, 1], albedo_scale_every >= 1: "
                             f"{self.albedo_scale}, {self.albedo_scale_quantile}, "
                             f"{self.albedo_scale_every}")
        if not (0 <= self.detail_prior < math.inf and 0 < self.detail_max < math.inf and
                0 < self.lr_detail < math.inf and self.detail_edge_px >= 0):
            raise ValueError(f"MaterialConfig: detail_prior >= 0 (0 = off), detail_max > 0, "
                             f"lr_detail > 0, all finite, detail_edge_px >= 0: "
                             f"{self.detail_prior}, "
                             f"{self.detail_max}, {self.lr_detail}, {self.detail_edge_px}")
        if (self.lamps not in LAMP_MODES or not self.lamp_distances
                or any(not 1.0 < d < math.inf for d in self.lamp_distances)
                or not 0.0 <= self.lamp_min_gain < 1.0
                or any(len(p) != 2 or not 0.0 < p[0] < 45.0 or not 0.0 < p[1] < 1.0
                       for p in self.lamp_passes)):
            raise ValueError(f"MaterialConfig: lamps one of {LAMP_MODES}, lamp_distances > 1 "
                             f"(scene radii, finite), lamp_min_gain in [0, 1), lamp_passes "
                             f"(direction step in (0, 45) degrees, distance share in (0, 1)): "
                             f"{self.lamps!r}, {self.lamp_distances}, {self.lamp_min_gain}, "
                             f"{self.lamp_passes}")
        if (self.lamp_position_score not in LAMP_POSITION_SCORES
                or not 0.0 < self.lamp_lit_ratio < 1.0):
            raise ValueError(f"MaterialConfig: lamp_position_score one of "
                             f"{LAMP_POSITION_SCORES} and lamp_lit_ratio in (0, 1), got "
                             f"{self.lamp_position_score!r}, {self.lamp_lit_ratio}")
        if self.lamp_scan_directions < 0 or (self.lamp_scan_directions and (
                not self.lamp_scan_distances
                or any(not 1.0 < d < math.inf for d in self.lamp_scan_distances))):
            raise ValueError(f"MaterialConfig: lamp_scan_directions >= 0 (0 = no scan), and "
                             f"with a scan lamp_scan_distances > 1 (scene radii, finite): "
                             f"{self.lamp_scan_directions}, {self.lamp_scan_distances}")
        if self.backdrop_surfels not in BACKDROP_SURFELS:
            raise ValueError(f"MaterialConfig.backdrop_surfels must be one of "
                             f"{BACKDROP_SURFELS}, got {self.backdrop_surfels!r}")
        if not 0.0 <= self.prune_threshold < 1.0:
            raise ValueError(f"MaterialConfig.prune_threshold must be in [0, 1), got "
                             f"{self.prune_threshold}")

    def local_passes(self, again: bool) -> tuple:
        """The (radius, step) passes of the first refinement, or of the main phase's second
        (``again``); refine_passes () turns both off."""
        if not again or self.refine_again_passes is None or not self.refine_passes:
            return self.refine_passes
        return self.refine_again_passes


def _valid_pass(p) -> bool:
    """Whether ``p`` is a refinement pass: (radius, step[, map resolution])."""
    if len(p) not in (2, 3) or not 0.0 < p[1] <= p[0]:
        return False
    return len(p) == 2 or (float(p[2]).is_integer() and p[2] >= 8)


def lamp_scoring(config: MaterialConfig) -> str:
    """The score of lamp candidates: ``lamp_score``, with "auto" resolved."""
    if config.lamp_score != "auto":
        return config.lamp_score
    return "albedo" if config.specular == "off" else "segment"


def label_source_overrides(config: MaterialConfig, source: str) -> dict:
    """The settings that change ``config`` for segments labelled from ``source`` (one of
    stage 2's ``LABEL_MAP_SOURCES``): on chromaticity ones its ``chromaticity_*`` settings
    (see them), as {field: value} with only the values that differ."""
    if source not in LABEL_MAP_SOURCES:
        raise ValueError(f"label source must be one of {LABEL_MAP_SOURCES}, got {source!r}")
    if source == "material":
        return {}
    wanted = {"normal_steps": config.chromaticity_normal_steps,
              "refine_score": config.chromaticity_refine_score}
    return {k: v for k, v in wanted.items() if getattr(config, k) != v}
