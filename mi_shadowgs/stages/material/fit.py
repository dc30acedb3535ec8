"""Stage 4: PBR material and light decomposition on fixed surfels (paper Sec. IV-C2).

Per-surfel albedo, roughness and metallic, a white directional light map L_dir over the
128-direction grid and an indirect light (per-surfel RGB SH of degree 2) are fitted to the
training images by Adam on the loss of Eq. 18:

    L = L_rend + l_ind2 |L_ind|^2 + l_tv TV(L_ind) + l_brdf TV(a, rho, m) + l_reg E[1 - rho + m]

with deferred, image-space shading of Eq. 17 (``shading``) and the pixelwise visibility
V [H, W, L] of ``visibility`` (shadow maps of the surfels' own depth, rendered once per
direction and shared by every view; the view points are the surfels' rasterized expected
depth and normals). After each step the albedo is replaced by its mean over the surfel's
segment (the hard constraint; the "segment" channel is an integer id per surfel).
``cpu-small`` and ``cpu-medium`` then leave the albedo's TV out (with the constraint it acts
only across segment borders, where it merged the segments' colours) and hold the albedo x
light scale, which the images leave free, by rescaling albedo, light and indirect light
together (``hold_albedo_scale``): otherwise the albedo drifted to its box at 1.

Only what the scene needs is modelled: after ``warmup`` steps the grid directions are
grouped into lights (``merge_directions``) and the lights carrying less than
``prune_threshold`` times the strongest one's irradiance are dropped (``prune_lights``; no
shadow maps, no shading for them; their L_dir is 0 from then on), and with
``specular="auto"`` the GGX lobe is switched off when the fitted parameters say the scene is
diffuse (every surfel's metallic below ``auto_metallic_max`` and roughness above
``auto_roughness_min`` at the end of the warm-up; the lobe then costs nothing and metallic
is fixed at 0). ``cpu-small`` and ``cpu-medium`` model no lobe at all (``specular="off"``):
at their resolution and step count the fitted lobe was noise on every scene (``PRESETS``).

Where the light is: the grid's neighbouring directions that share a light merge into one at
their energy-weighted direction (``merge_directions``), which lands a few degrees off, and
``refine_directions`` then searches each light's direction on a local grid, scoring a
candidate by the training views' squared error with its shadow map rendered and its
irradiance re-fitted in closed form (shadows are the sharpest cue; gradients through
n . l alone moved the default scene's lights 9 degrees the wrong way); ``refine_score``
says what else is re-fitted with it (cpu-small: each segment's albedo, so that the
materials fitted under the current lights do not hold a light where they were fitted).
Measured on the default scene: light directions ~4-6 -> < 1 degree off, shadow IoU 0.71 ->
0.81. The first refinement can start each light with a global pass over the hemisphere
(``refine_global``, off by default: see there), so a light merged into the wrong cell is
found again; after each refinement the lights that met merge and those that carry little
irradiance and explain little of the views are dropped (``settle_lights``: backward
elimination with a joint non-negative least-squares re-fit of the others' irradiance).

Where the normals are (not in the paper): stage 1 fits colours, not shading, so its normals
on parts a few pixels across are smooth, and the attached shadows on their far sides go.
With ``normal_steps`` > 0 a last phase holds everything fitted and moves each surfel's
shading normal to explain the views' shading, pulled toward stage 2's normal
(``normal_step``); relighting and evaluation shade with them.

Where a segment is textured (not in the paper; off in every preset): with ``detail_prior``
> 0 each surfel's albedo is its segment's times a bounded per-surfel factor, fitted from the
second refinement on, away from the fitted shadows' edges (``start_detail``); the result's
albedo channel holds the product.

Pure functions over Dr.Jit arrays plus one loop (``fit_material``); no I/O here.
"""

from __future__ import annotations

import dataclasses
import math
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.config import LABEL_MAP_SOURCES, get_preset
from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.brdf import ROUGHNESS_MIN
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import light_grid, nearest_grid_index, solid_angle
from mi_shadowgs.core.raster import RasterConfig
from mi_shadowgs.core.surfels import SH_C0, Surfels, eval_sh
from mi_shadowgs.stages.visibility.shadow_maps import (
    MapCache,
    SceneBounds,
    VisibilityConfig,
)

SPECULAR_MODES = ("auto", "on", "off")
# The per-surfel albedo detail, log factor [N, 3] (``MaterialConfig.detail_prior``); only
# while fitting: the result carries the detailed albedo in its "albedo" channel.
DETAIL_CHANNEL = "albedo_detail"
DEFAULT_RASTER = RasterConfig()
DEFAULT_VISIBILITY = VisibilityConfig()


REFINE_SCORES = ("segment", "irradiance", "albedo")
SETTLE_SCORES = ("segment", "irradiance")


@dataclasses.dataclass(frozen=True)
class MaterialConfig:
    """Stage-4 hyperparameters; defaults are the paper's (Sec. V-A1) where it gives them."""

    iterations: int = 5000
    lambda_ind2: float = 0.01
    # A surfel whose indirect SH is negative at its normal is clamped to no indirect light
    # and gets no gradient from the render: it could never light up again. This weight
    # pulls such values back to 0 (mean of min(SH(n), 0)^2 over the surfels), where the
    # render's gradient reaches them. 0: off (the paper's fit). At cpu-small such surfels
    # are 2-5% of the default scene's and the hotdog's, 37% of the ficus's; at 1 they fall
    # to 0.2-2.8%, but shadow IoU moves by -0.004 to +0.003 on the twelve rows (mean
    # +0.0005, inside the runs' spread; BENCHMARKS.md, "Session 36: surfels with no
    # indirect light"), so it stays off.
    lambda_ind_floor: float = 0.0
    lambda_tv: float = 0.01
    lambda_brdf: float = 1.0
    lambda_reg: float = 0.001
    n_directions: int = 128  # light grid; dw = 2 pi / n_directions
    sh_degree: int = 2  # indirect light
    # Adam learning rates (not in the paper; 3DGS-like magnitudes).
    lr_albedo: float = 0.01
    lr_material: float = 0.01  # roughness and metallic
    lr_light: float = 0.03  # on log L_dir
    lr_indirect: float = 0.002
    albedo_init: float = 0.5
    roughness_init: float = 0.9
    metallic_init: float = 0.0
    # Initial radiance of every grid direction; 0 = from the data: a uniform sky of
    # radiance L gives an unshadowed Lambertian surface the radiance a L, so
    # L = mean(target) / albedo_init (keeps the albedo away from its bounds at the start).
    light_init: float = 0.0
    indirect_init: float = 0.05  # initial indirect radiance (SH DC)
    # Model only what the scene needs.
    warmup: int = 500  # steps before pruning directions and deciding on the specular lobe
    prune: bool = True
    # Drop lights carrying less irradiance than this times the strongest light's, judged
    # after the directions closer than merge_angle_deg are grouped into lights
    # (prune_lights). Judged per grid direction (L_dir < this * max L_dir, the paper's map)
    # a light the warm-up spreads over many dim cells was dropped whole: the weaker light
    # of the low pair (a third of the irradiance) on bunny and toy train (issue 15).
    prune_threshold: float = 0.1
    prune_every: int = 50  # after the warm-up, prune again every this many steps
    # At each pruning, lights closer than this merge into one at their weighted mean
    # direction (merge_directions); 0 keeps the paper's fixed grid directions (and prunes
    # each direction on its own).
    merge_angle_deg: float = 20.0
    # Shadow-map size while all grid directions are live (the warm-up): the light is still
    # a blur there, so coarse maps suffice; the survivors' maps are then re-rendered at the
    # visibility config's resolution.
    warmup_map_resolution: int = 128
    # Light-direction refinement (not in the paper): after the warm-up's pruning and merging,
    # and again halfway through the main phase, each light's direction is searched on a
    # local grid (``refine_passes``: (radius, step) in degrees, coarse to fine) around its
    # current direction. A candidate's shadow map is rendered and it is scored by the
    # training views' squared error with that light's irradiance re-fitted in closed form.
    # The grid spacing (~13 degrees at 128 directions) leaves merged lights a few degrees
    # off, and shadows are the sharpest cue to where a light is. () = off.
    refine_passes: tuple = ((8.0, 2.0), (2.0, 0.5))
    # The passes of the main phase's second refinement (None: refine_passes; (): no second
    # refinement; refine_passes () turns both off). The first leaves each light within a
    # fine step or two of its best direction: on the twelve table rows the second one moved
    # lights by 0-1 degree, and without its (8, 2) pass (~100 shadow maps of 512^2) 11 rows
    # fit bit-identically and hotdog-tuned's light lands 0.1 degree further off (shadow IoU
    # 0.478 -> 0.469; BENCHMARKS.md, "Session 16").
    refine_again_passes: tuple | None = ((2.0, 0.5),)
    refine_views: int = 16  # training views scored per candidate (evenly spaced)
    # Only the strongest lights are refined: each costs ~100 shadow maps, and a fit whose
    # light has not collapsed to a few directions (the w/o-segmentation ablation kept 7-9)
    # would spend minutes moving lights that cast faint shadows.
    refine_max_lights: int = 4
    # Lights anywhere on the hemisphere (not in the paper): the first refinement (end of the
    # warm-up) starts each light with a global pass over ``refine_global`` equal-area
    # directions (plus its own), scored as above with maps at
    # ``refine_global_map_resolution``. The local passes alone search 8 degrees around the
    # merged grid light, so a light merged into the wrong cell (armadillo: a 25 degree light
    # fitted at 8, 17 degrees off) was never recovered. 0 = off (the paper has no such
    # pass). cpu-small turns it on (128): with the per-segment scores and settling it
    # recovers ficus-low's strong light (7.4 -> 0.4 deg) and the sweep's s4 weak light
    # (7.9 -> 1.4) and leaves default-low at 0.2/0.3 deg (before those scores it moved
    # default-low's 20 degree light from 6.5 to 16.8 degrees off; BENCHMARKS.md, issue 15).
    refine_global: int = 0
    # The global pass in the main phase's second refinement too (each light's, followed by
    # the first refinement's local passes: from a grid cell away the second's fine pass
    # alone does not reach). The warm-up's materials can leave a light in another basin of
    # the score than the later ones: on hotdog-low the weak light ended 14 deg off in two
    # of four view orders (``seed``), light cosine 0.868, because at step 400 the second
    # refinement's (2, 0.5) pass could not reach the direction its own score preferred, 12
    # deg away (BENCHMARKS.md, "Light directions under other view orders"). Needs
    # ``refine_global``.
    refine_again_global: bool = False
    refine_global_map_resolution: int = 128
    # Views scored in the global pass (every other of the refinement's): it scores 129
    # candidates, the cost of ~3 local passes, and only has to land within a grid cell.
    refine_global_views: int = 8
    # How a candidate direction is scored (``_candidate_scores``). "irradiance": the views'
    # squared error with the candidate's irradiance re-fitted and everything else fixed.
    # But the albedo was fitted under the current light, so that score favours the current
    # direction: on the default scene under the low pair, the 20 degree light sat at 27
    # degrees, where the albedo had settled, and the score along its azimuth was lowest at
    # 24-26. "segment": per material segment s, what the light has to explain (the target
    # minus the other lights and the indirect term) is fitted as b_s B (B the candidate's
    # shading, b_s >= 0 free per segment), so a segment's albedo scale drops out of the
    # light's part and what is left is the pattern of its shading and shadows; the same
    # model and views put its minimum at 20.0 (BENCHMARKS.md, "Light directions scored per
    # segment"). The other lights keep their scale: freeing it too let a light near the
    # truth explain everything, and a light split over two grid cells never merged. The
    # moved light's irradiance is still the global least-squares fit.
    # "albedo" (needs specular "off"): per segment and colour channel the albedo a_sc is
    # re-fitted with the candidate, t ~ a_sc (X_c + E B), X the other lights' shading at
    # their irradiance, B the candidate's, E its irradiance (one for all segments, searched
    # in 1-D). Neither the albedo nor the per-surfel indirect light fitted so far enters:
    # both were fitted under the current lights and hold their errors. On the light sweep's
    # default scene two 15 deg lights ended too low (s6 at 3.8 deg, 11.3 off; s0 3.0 off):
    # the block's top against its sides (27-89% of the sides' light is bounced off the base,
    # 3% of the top's; the indirect term under lambda_ind2 does not carry it) voted for a
    # flat light, its error +58 from 0 to 20 deg against the base's +0.1. Stage 4 refitted
    # with "albedo": s6 2.3 deg off (shadow IoU 0.770 -> 0.938), s0 1.0; the twelve table
    # rows within -0.022..0 shadow IoU (BENCHMARKS.md, "The sweep's grazing lights").
    refine_score: str = "segment"
    # Pixels whose largest segment carries less than this share of their blending weight
    # (silhouettes between segments) are left out of the "segment" score: no one segment's
    # scale describes them.
    refine_segment_purity: float = 0.9
    # Model only what the scene needs (not in the paper): after each refinement, a light
    # carrying less than ``drop_share`` of the fitted irradiance is dropped when the training
    # views' squared error (the other lights' irradiance re-fitted by non-negative least
    # squares) rises by less than ``drop_gain`` times that error with it.
    # Glossy highlights and inter-reflections were otherwise explained by extra weak
    # directional lights (hotdog: 13 kept instead of 2; toy train: a spurious third light
    # with 0.19 of the irradiance). drop_share = 0: off. drop_gain 0.05 -> 0.1 (session 35):
    # on the default scene a grazing light behind the object (elevation ~2 deg, 7-9% of the
    # irradiance) was kept at some seeds; at 0.1 it goes (shadow IoU +0.018 / +0.019 on
    # two such fits, light cosine 0.992 -> 0.9997), and the twelve table rows' refits that
    # kept two lights are unchanged (BENCHMARKS.md, "Session 35: the grazing third light").
    drop_share: float = 0.25
    drop_gain: float = 0.1
    # How the lights a settling keeps are judged. "irradiance": the views' squared error
    # with the lights' irradiance re-fitted, the albedo fixed. "segment": each material
    # segment also takes its own scale of the direct light (as refine_score "segment"), so
    # that the albedo fitted under the current lights does not decide between two of them.
    # The kept lights' irradiance is the global fit either way. On the default scene on a
    # textured mat the warm-up's settling kept a weak-light candidate at 12 deg elevation
    # over one at 30 (truth 35) and the light ended 23 deg off; "segment" kept the right one
    # (0.4 deg, shadow IoU 0.769 -> 0.845), with four other rows unchanged
    # (BENCHMARKS.md, "Settling judged per segment").
    settle_score: str = "segment"
    # Settle the warm-up's pruned lights before the first refinement too: the pruning now
    # keeps every light that carries irradiance (prune_lights), spurious ones included
    # (toy train under the low pair: 8 lights of >= 0.1 the strongest, among them one 24
    # degrees from the strong light with 0.30 of it, and the weak light split over 3 cells),
    # and the refinement spends ~100 shadow maps on each of the strongest 4. Settled first
    # (the warm-up's materials), toy train kept the two true lights (2 and 11 degrees off).
    settle_warmup: bool = True
    # The albedo's TV term (Eq. 18's L_brdf) while the segment constraint holds. The albedo
    # is then constant within each segment, so its TV acts only across segment borders,
    # where it pulls neighbouring segments' colours together (an L1 TV: the same pull
    # whatever the difference). At 128^2, where borders are a large share of the pixels,
    # it won: toy train's five object segments (red, yellow, blue, green, orange) all ended
    # at one albedo, [0.85, 0.64, 0.73] at step 250, and the colour went into the
    # per-surfel indirect term. False: the albedo TV applies only without the segment
    # constraint (the w/o-segmentation ablation).
    albedo_tv_with_segments: bool = True
    # The albedo x light scale (not in the paper). The images fix only the product of albedo
    # and light (and of albedo and indirect light); the loss's other terms are not
    # scale-free, and the indirect light's fixed step size is not either. So the fit drifts
    # along that product: up to the albedo's box at 1 with the albedo TV on (default scene:
    # every segment at 0.97-0.99 in every channel at step 450), down without it (0.5 ->
    # 0.19 by step 600, the light 4x too bright and still growing). Every
    # ``albedo_scale_every`` steps the albedo is scaled so that the support-weighted
    # ``albedo_scale_quantile`` of its brightest channel is ``albedo_scale``, the light and
    # the indirect light by the inverse: the diffuse image is unchanged. Weighted by what
    # the views see (``surfel_support``): on the ficus a segment under the base, which no
    # view supervises, ran to 0.9 while the rest fell to 0.01 when the largest albedo was
    # held instead. Only without the specular lobe (its dielectric part does not scale with
    # the albedo). 0 = off (the paper's fit).
    # The quantile leaves out the brightest 5% of the support: small segments that take
    # little of the direct light in the model can run to the box at 1. On the ficus at
    # another stage-1 seed two such segments (around the pot; 0.12-0.15 of the lights'
    # irradiance against the base's 0.66) held 1.65% of the support: at 0.99 they set the
    # scale, the base fell to 0.135 and the light rose 7x (albedo 18.0 -> 27.9 dB, relight
    # 23.0 -> 29.1 dB at 0.95).
    # The twelve table rows at 0.95: shadow IoU within 0.004 but the ficus's two -0.02,
    # albedo and relight +0.06 / +0.10 dB on the mean (BENCHMARKS.md, "Session 30").
    albedo_scale: float = 0.0
    albedo_scale_quantile: float = 0.95  # of the brightest channel, weighted by support
    albedo_scale_every: int = 10  # steps (each a host read of the albedo)
    # Shading normals refined by the images (not in the paper): after the main phase, with
    # the lights, materials and indirect light held, ``normal_steps`` more steps fit each
    # surfel's shading normal (``shading.SHADING_NORMAL_CHANNEL``, started from stage 2's)
    # to the training views, pulled toward its start by ``lambda_normal_prior`` x mean(1 -
    # n . n0). Stage 1 fits appearance with view-dependent colour, so the hard lights'
    # shading, which pins where n . l changes sign, never reaches its normals: parts a few
    # pixels across come out as a smooth loaf (the hotdog's sausage and bun 20-35 deg off at
    # 128^2), and the attached shadows on their far sides are lost. The geometry (coverage,
    # depth, the shadow maps' occluders) is left as it is. 0 = off (the paper's fit).
    normal_steps: int = 0
    lr_normal: float = 0.03
    lambda_normal_prior: float = 0.3
    # Hold the normals stage 2 made flat (planar segments' inliers: their shading normal is
    # their plane's, not their rotation's): the plane's normal is already what the images
    # ask of them, and the phase would spend the base's one-light regions on explaining
    # what the normals cannot (indirect light, aliasing).
    normal_hold_planar: bool = True
    # On segments from chromaticity (stage 2 without material ids, as for a capture), these
    # replace ``normal_steps`` and ``refine_score`` (``label_source_overrides``). Such a
    # segment can hold several materials, or split a printed mat by its print, so its one
    # albedo is wrong in places; both settings read it as right. The normal phase turned the
    # error into tilted normals (speckled false shadows on a textured mat, a false shadow
    # over a sphere's lit cap), and the "albedo" score, which re-fits each segment's albedo
    # with the candidate, set the weak light 7-12 deg off. The default scene on a textured
    # mat, shadow IoU: from photos only 0.738 (normal phase, "albedo") -> 0.771 (no phase)
    # -> 0.812 (no phase, "segment"); from ground-truth cameras with chromaticity segments
    # 0.780 -> 0.851 (no phase). The plain default scene with chromaticity segments: 0.908
    # -> 0.911 (no phase). Material-id segments (the table's) keep both. BENCHMARKS.md,
    # "Session 44: the photo path back inside issue 17's bound".
    chromaticity_normal_steps: int = 0
    chromaticity_refine_score: str = "segment"
    # A per-surfel albedo detail (not in the paper): from the main phase's second
    # refinement on, each surfel's albedo is its segment's times exp(d), d [N, 3] held
    # zero-mean within the segment and within +-detail_max, pulled to 0 by detail_prior x
    # the mean over supervised pixels of |splat(d)|^2. The segment-constant albedo cannot
    # hold a textured base's print, which then went into the per-surfel indirect light
    # (BENCHMARKS.md, "Session 40"). With detail_edge_px > 0 the pixels within that many
    # pixels of a fitted shadow's edge do not move d: the shading's errors are largest
    # there, and they are not texture (1 px: the plain scene's albedo +1.0 dB over none,
    # where 2 px closed the whole of a thin occluder's shadow). 0: off (the paper's hard
    # constraint), in every preset: on the default scene on a textured mat 0.1 took
    # relighting 19.0 -> 25.8 dB and albedo 13.9 -> 18.1 dB, but on the plain default
    # scene it cost 3.2 dB of albedo for +0.2 dB of relighting (BENCHMARKS.md, "Session
    # 43"); ``run --albedo-detail W`` sets it.
    detail_prior: float = 0.0
    detail_max: float = 1.0
    lr_detail: float = 0.01
    detail_edge_px: int = 1
    specular: str = "auto"  # "auto" | "on" | "off"
    auto_metallic_max: float = 0.1
    auto_roughness_min: float = 0.6
    # Ablations (paper Table 3).
    use_visibility: bool = True  # False: V = 1 (training, rendering and relighting)
    segment_average: bool = True  # False: no segment-wise albedo averaging
    views_per_step: int = 1
    mask_alpha: float = 0.5  # pixels with rendered alpha below this are not supervised
    log_every: int = 100  # host reads of the loss (progress bar) every this many steps
    # Resumable checkpoints: every so many steps and at least this often in wall time.
    checkpoint_every: int = 1000
    checkpoint_seconds: float = 60.0
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
        if any(len(p) != 2 or not 0.0 < p[1] <= p[0]
               for p in self.refine_passes + (self.refine_again_passes or ())) or \
                self.refine_views < 1 or self.refine_max_lights < 0:
            raise ValueError(f"MaterialConfig.refine_passes and refine_again_passes must be "
                             f"(radius, step) pairs with 0 < step <= radius, refine_views >= "
                             f"1, refine_max_lights >= 0: {self.refine_passes}, "
                             f"{self.refine_again_passes}, {self.refine_views}, "
                             f"{self.refine_max_lights}")
        if self.refine_global < 0 or self.refine_global_map_resolution < 1 or \
                self.refine_global_views < 1 or \
                not 0.0 <= self.drop_share < 1.0 or self.drop_gain < 0:
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
        for name in ("refine_score", "chromaticity_refine_score"):
            score = getattr(self, name)
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
        if not 0.0 <= self.albedo_scale <= 1.0 or not 0.0 < self.albedo_scale_quantile <= 1.0 \
                or self.albedo_scale_every < 1:
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
        if not 0.0 <= self.prune_threshold < 1.0:
            raise ValueError(f"MaterialConfig.prune_threshold must be in [0, 1), got "
                             f"{self.prune_threshold}")

    def local_passes(self, again: bool) -> tuple:
        """The (radius, step) passes of the first refinement, or of the main phase's second
        (``again``); refine_passes () turns both off."""
        if not again or self.refine_again_passes is None or not self.refine_passes:
            return self.refine_passes
        return self.refine_again_passes


PRESETS = {
    "paper": MaterialConfig(),
    # Ground-truth-like geometry converges far sooner; a couple of minutes on 2 cores.
    # lambda_ind2 = 1: at the paper's 0.01 the per-surfel indirect SH explained ~30% of the
    # default scene's radiance (its true indirect share is ~2%), which darkened the fitted
    # light by as much and made relit views 1.5x too bright (relight PSNR 16.6 vs 25.8 dB).
    # specular "off": at 128^2 and 600 steps the per-surfel GGX parameters are not
    # identifiable. On all twelve table rows the fit ended with the same spread (metallic
    # p99 0.17-0.24, roughness p1 0.45-0.57, the extremes at the clamps), whatever the
    # materials, so "auto" never dropped the lobe, and the noisy lobe cost every
    # relighting and held spurious lights. Stage 4 refitted on the twelve rows with the
    # lobe off: relight +0.4 to +5.2 dB on every row (mean 26.10 -> 27.86 dB), the ficus's
    # third light gone under both pairs (ficus-low light cosine 0.781 -> 0.999), shadow IoU
    # -0.013 to +0.014 (mean 0.681 -> 0.680), albedo within 0.4 dB except toy train-tuned
    # (-5.0 dB by the per-region metric, but +6.1 dB with one global scale per channel: the
    # lobe had left its segment albedos grey); the glossy hotdog's weak light under the
    # low pair 7.2 -> 11.3 deg off. BENCHMARKS.md, "The specular lobe off in cpu-small".
    # albedo_tv_with_segments False and the albedo scale held at 0.9: see the fields above;
    # BENCHMARKS.md, "Colour in the albedo". refine_score "albedo": see the field.
    "cpu-small": MaterialConfig(iterations=600, warmup=200, lr_albedo=0.03, lr_light=0.1,
                                lambda_ind2=1.0, log_every=50, refine_global=128,
                                refine_again_global=True,
                                specular="off", albedo_tv_with_segments=False,
                                albedo_scale=0.9, refine_score="albedo",
                                # Stages 3-5 refitted on the twelve table rows' stages 1-2,
                                # off -> on: shadow IoU mean 0.725 -> 0.745 (hotdog +0.03 /
                                # +0.04, ficus +0.06 / +0.02, toy train-low +0.04,
                                # default-tuned -0.007), relight mean 29.56 -> 29.56 dB;
                                # 8.5 s of `make demo`'s stage 4. Prior 0.1, planes free: 0.755
                                # but relight 28.17 dB (the base's normals drifted, default
                                # 0.38 -> 2.89 deg median error). BENCHMARKS.md, "Session
                                # 27: stage 4 refines the shading normals".
                                normal_steps=1500),
}
PRESETS["cpu-medium"] = PRESETS["gpu-large"] = PRESETS["cpu-small"]


def get_config(name: str) -> MaterialConfig:
    return get_preset(PRESETS, name, "material")


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


# -- model ---------------------------------------------------------------------------------
@dataclasses.dataclass
class LightModel:
    """The fitted white light.

    ``radiance`` is L_dir over the grid (0 for pruned directions), the paper's light map; the
    K lights that carry it sit at ``directions`` (grid directions, or merged neighbours at
    their energy-weighted mean direction; see ``merge_directions``) with ``weights``
    (irradiance L dw). ``active`` are the grid cells the lights fall in.
    """

    radiance: np.ndarray  # [n_directions] white radiance per grid direction
    active: np.ndarray  # [K] grid index of each light
    directions: np.ndarray | None = None  # [K, 3] unit; None: the grid directions
    weights: np.ndarray | None = None  # [K] irradiance; None: radiance[active] * dw

    def light_set(self, n_directions: int | None = None) -> shading.LightSet:
        n = len(self.radiance) if n_directions is None else n_directions
        dirs = light_grid(n)[self.active] if self.directions is None else self.directions
        w = self.radiance[self.active] * solid_angle(n) if self.weights is None else \
            self.weights
        w = np.asarray(w, np.float32)
        return shading.LightSet(np.asarray(dirs, np.float64), mi.Color3f(w, w, w))


@dataclasses.dataclass
class MaterialResult:
    surfels: Surfels  # input geometry plus albedo/roughness/metallic/indirect_sh channels
    light: LightModel
    specular: bool  # whether the GGX lobe is modelled
    use_visibility: bool
    history: list  # (step, loss) read every log_every steps
    timings: dict  # seconds: prepare, warmup, main, per-step medians
    # What the light decisions did (``MaterialState.light_log``): where a light was dropped.
    light_log: list = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class MaterialState:
    """Everything a checkpoint of ``fit_material`` needs to continue it exactly.

    The shadow maps are not saved: they follow from ``directions`` (each map is rendered on
    its own, so re-rendering the survivors equals the maps the fit gathered them from), at
    the warm-up resolution up to the end of the warm-up and at the full one after it.
    """

    step: int  # finished iterations
    opt: mi.ad.Adam  # the fitted channels and log L_dir, with their Adam state
    # name -> mi.TensorXf [N, C]: all four (those not in opt keep their value), and the
    # shading normals [N, 3] from the normal phase on
    channels: dict
    directions: np.ndarray  # [K, 3] the lights: the grid, then pruned, merged, refined
    specular: bool  # whether the GGX lobe is still modelled
    rng: np.random.Generator  # the training views' order
    loss_sum: mi.Float  # [1] loss summed since the last history entry
    history: list
    timings: dict  # seconds: "prepare_s", finished phases, "phase_s" into the current one
    # A refinement of step ``step`` (not finished) that a checkpoint interrupted.
    refine: Refinement | None = None
    # The lights after each decision on them, in order: dicts of "step", "event" ("prune",
    # "refine", "settle"), "directions" [K][3] and "irradiance" [K] (JSON; ``log_lights``).
    # A light lost on the way shows where (issue 15: the low pair's weaker light was gone
    # at the warm-up's pruning, before any refinement or settling saw it).
    light_log: list = dataclasses.field(default_factory=list)
    # The lights' directions [K, 3] when the albedo detail joined, whose shadows' edges its
    # gates follow (``detail_gates``); None before.
    detail_directions: np.ndarray | None = None

    def log_lights(self, event: str, dw: float) -> None:
        """Record the current lights (directions, irradiance L_dir dw) after ``event``."""
        irr = np.exp(self.opt["log_light"].numpy().astype(np.float64)) * dw
        self.light_log.append({"step": self.step, "event": event,
                               "directions": np.round(self.directions, 6).tolist(),
                               "irradiance": np.round(irr, 6).tolist()})

    def to_checkpoint(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, JSON meta) for ``mi_shadowgs.io.checkpoint.save_checkpoint``."""
        from mi_shadowgs.core.optim import adam_to_numpy

        arrays = adam_to_numpy(self.opt, "adam/")
        arrays.update({f"channel/{k}": np.asarray(v.numpy(), np.float32)
                       for k, v in self.channels.items()})
        arrays["directions"] = np.asarray(self.directions, np.float64)
        arrays["loss_sum"] = np.asarray(self.loss_sum.numpy(), np.float32)
        if self.detail_directions is not None:
            arrays["detail/directions"] = self.detail_directions
        if self.refine is not None:
            arrays.update({"refine/dirs": self.refine.dirs,
                           "refine/irradiance": self.refine.irradiance,
                           "refine/lights": self.refine.lights,
                           "refine/done": np.array([self.refine.done]),
                           "refine/global": np.array([int(self.refine.global_pass)]),
                           "refine/again": np.array([int(self.refine.again)])})
        return arrays, {"step": self.step, "specular": self.specular,
                        "rng": self.rng.bit_generator.state, "history": self.history,
                        "timings": self.timings, "light_log": self.light_log}

    @staticmethod
    def from_checkpoint(arrays: dict[str, np.ndarray], meta: dict) -> MaterialState:
        from mi_shadowgs.core.optim import adam_from_numpy

        opt = mi.ad.Adam(lr=0.0)
        adam_from_numpy(opt, arrays, "adam/")
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["rng"]
        channels = {k[len("channel/"):]: mi.TensorXf(a) for k, a in arrays.items()
                    if k.startswith("channel/")}
        refine = Refinement(arrays["refine/dirs"], arrays["refine/irradiance"],
                            arrays["refine/lights"], int(arrays["refine/done"][0]),
                            bool(arrays.get("refine/global", [0])[0]),
                            bool(arrays.get("refine/again", [0])[0])) \
            if "refine/dirs" in arrays else None
        return MaterialState(int(meta["step"]), opt, channels, arrays["directions"],
                             bool(meta["specular"]), rng, mi.Float(arrays["loss_sum"]),
                             [(int(i), float(x)) for i, x in meta["history"]],
                             dict(meta["timings"]), refine, list(meta.get("light_log", [])),
                             arrays.get("detail/directions"))


def init_channels(surfels: Surfels, config: MaterialConfig) -> dict[str, mi.TensorXf]:
    """Initial material and indirect channels [N, C]."""
    n = surfels.count
    k = (config.sh_degree + 1) ** 2
    sh = np.zeros((n, 3 * k), np.float32)
    sh[:, :3] = config.indirect_init / SH_C0
    return {"albedo": mi.TensorXf(np.full((n, 3), config.albedo_init, np.float32)),
            "roughness": mi.TensorXf(np.full((n, 1), config.roughness_init, np.float32)),
            "metallic": mi.TensorXf(np.full((n, 1), config.metallic_init, np.float32)),
            shading.INDIRECT_CHANNEL: mi.TensorXf(sh)}


def segment_ids(surfels: Surfels) -> mi.UInt32:
    """The per-surfel integer "segment" channel as UInt32 [N]; clear errors otherwise."""
    if "segment" not in surfels.channels:
        raise ValueError("stage 4: the surfels have no 'segment' channel (run segmentation, "
                         "or give every surfel segment 0)")
    seg = np.asarray(surfels.channels["segment"].numpy()).reshape(-1)
    if len(seg) != surfels.count or not np.all(np.isfinite(seg)) or np.any(seg < 0) or \
            np.any(seg != np.round(seg)):
        raise ValueError("stage 4: channel 'segment' must hold one non-negative integer per "
                         "surfel")
    return mi.UInt32(seg.astype(np.uint32))


def segment_average(values: mi.TensorXf, seg: mi.UInt32, n_segments: int) -> mi.TensorXf:
    """Replace each row of ``values`` [N, C] by the mean over its segment (``seg`` [N])."""
    n, c = values.shape
    counts = dr.zeros(mi.Float, n_segments)
    dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.Float(1.0), seg)
    out = []
    for k in range(c):
        col = dr.gather(mi.Float, values.array, dr.arange(mi.UInt32, n) * c + k)
        sums = dr.zeros(mi.Float, n_segments)
        dr.scatter_reduce(dr.ReduceOp.Add, sums, col, seg)
        mean = sums / dr.maximum(counts, 1.0)
        out.append(dr.gather(mi.Float, mean, seg))
    flat = dr.zeros(mi.Float, n * c)
    for k in range(c):
        dr.scatter(flat, out[k], dr.arange(mi.UInt32, n) * c + k)
    return mi.TensorXf(flat, (n, c))


# -- per-view training data ----------------------------------------------------------------
@dataclasses.dataclass
class TrainView:
    camera: Camera
    pairs: shading.SplatPairs
    geom: shading.PixelGeometry
    weight: mi.Float  # [H * W] 1 on supervised pixels
    target: mi.Color3f  # [H * W]
    inv_count: mi.Float  # 1 / supervised pixels, opaque: a literal would recompile per view
    # [H * W] the segment holding at least refine_segment_purity of each pixel's blending
    # weight; n_segments where none does (mixed pixels, and pixels nothing covers)
    segment: mi.UInt32
    n_segments: int
    # [N] each surfel's normal facing this view's camera: where its indirect SH is evaluated
    surfel_normal: mi.Vector3f
    # [H * W] 1 where the albedo detail takes gradients (``detail_gates``); None: everywhere
    detail_gate: mi.Float | None = None


def prepare_view(surfels: Surfels, camera: Camera, image: np.ndarray, mask: np.ndarray,
                 config: MaterialConfig, raster: RasterConfig = DEFAULT_RASTER,
                 receiver_band: float = 0.0) -> TrainView:
    """Pairs, geometry buffers and the target of one view (computed once: fixed geometry);
    ``receiver_band``: ``VisibilityConfig.receiver_band``."""
    h, w = camera.height, camera.width
    img = np.asarray(image, np.float32).reshape(h * w, -1)[:, :3]
    if receiver_band > 0:  # one pair list for the shading and the receivers
        with_depth = shading.splat_pairs_with_depth(surfels, camera, raster)
        pairs = shading.SplatPairs(*with_depth[:3], h, w)
    else:
        with_depth, pairs = None, shading.splat_pairs(surfels, camera, raster)
    geom = shading.pixel_geometry(surfels, camera, raster, receiver_band, with_depth)
    sup = np.asarray(mask, bool).reshape(-1) & (geom.alpha.numpy() >= config.mask_alpha)
    weight = mi.Float(sup.astype(np.float32))
    target = mi.Color3f(*(img[:, c] for c in range(3)))
    inv = dr.opaque(mi.Float, 1.0 / float(max(sup.sum(), 1)))
    seg, n_seg = pixel_segments(surfels, pairs, config.refine_segment_purity)
    return TrainView(camera, pairs, geom, weight, target, inv, seg, n_seg,
                     shading.facing_normals(surfels, camera))


def pixel_segments(surfels: Surfels, pairs: shading.SplatPairs, purity: float
                   ) -> tuple[mi.UInt32, int]:
    """(segment [H * W], segment count S): per pixel, the segment that carries at least
    ``purity`` of its blending weight, else S (mixed, or empty); all 0 (S = 1) without a
    "segment" channel."""
    npix = pairs.height * pairs.width
    if "segment" not in surfels.channels:
        return dr.zeros(mi.UInt32, npix), 1
    seg = segment_ids(surfels)
    n_seg = int(dr.max(seg)[0]) + 1 if dr.width(seg) else 1
    weight = dr.zeros(mi.Float, npix * n_seg)  # [H * W * S]
    dr.scatter_reduce(dr.ReduceOp.Add, weight, pairs.weight,
                      pairs.pix * n_seg + dr.gather(mi.UInt32, seg, pairs.sid))
    w = weight.numpy().reshape(npix, n_seg)
    top = w.argmax(1)
    pure = w[np.arange(npix), top] >= purity * np.maximum(w.sum(1), 1e-30)
    return mi.UInt32(np.where(pure, top, n_seg).astype(np.uint32)), n_seg


def detailed_albedo(albedo: mi.TensorXf, detail: mi.TensorXf) -> mi.TensorXf:
    """The albedo [N, 3] times exp(detail) [N, 3], in [0, 1]."""
    return mi.TensorXf(dr.clip(albedo.array * dr.exp(detail.array), 0.0, 1.0), albedo.shape)


def _albedo_image(pairs: shading.SplatPairs, channels: dict, gate: mi.Float | None):
    """The blended albedo [H * W * 3], with the detail where ``channels`` has it; the detail
    takes gradients only where ``gate`` [H * W] is 1."""
    if DETAIL_CHANNEL not in channels:
        return shading.splat(pairs, channels["albedo"])
    d = channels[DETAIL_CHANNEL]
    a = shading.splat(pairs, detailed_albedo(channels["albedo"], d))
    if gate is None:
        return a
    held = shading.splat(pairs, detailed_albedo(channels["albedo"],
                                                mi.TensorXf(dr.detach(d.array), d.shape)))
    return dr.select(dr.repeat(gate, 3) > 0, a, held)


def view_maps(pairs: shading.SplatPairs, channels: dict[str, mi.TensorXf],
              surfel_normal: mi.Vector3f, with_specular: bool = True,
              detail_gate: mi.Float | None = None):
    """Per-pixel albedo [Color3f], roughness, metallic and indirect radiance of a view (the
    indirect SH, of the degree its channel holds, evaluated per surfel at ``surfel_normal``
    [N] (``shading.facing_normals``), then blended). The albedo is blended (it carries the
    pixel's coverage, as the photo's premultiplied colour does); roughness, metallic and the
    indirect irradiance are the covering surface's own (``shading.per_surface``). Without
    the specular lobe the metallic channel is held at 0 and the diffuse shading never reads
    the roughness: both are zero images, not splats."""
    a = _albedo_image(pairs, channels, detail_gate)
    albedo = mi.Color3f(*(shading.channel(a, 3, c) for c in range(3)))
    cover = pairs.coverage
    if with_specular:
        rough = shading.per_surface(shading.splat(pairs, channels["roughness"]), cover)
        metal = shading.per_surface(shading.splat(pairs, channels["metallic"]), cover)
    else:
        rough = metal = dr.zeros(mi.Float, pairs.height * pairs.width)
    ind = None
    if shading.INDIRECT_CHANNEL in channels:
        irr = eval_sh(channels[shading.INDIRECT_CHANNEL], surfel_normal, offset=0.0)
        flat = shading.per_surface(shading.splat(pairs, irr), cover)
        ind = mi.Color3f(*(shading.channel(flat, 3, c) for c in range(3)))
    return albedo, rough, metal, ind


def _tv(x: mi.Float, weight: mi.Float, h: int, w: int) -> mi.Float:
    """Sum of |forward differences| of an [H * W] image where both pixels are supervised."""
    idx = dr.arange(mi.UInt32, h * w)
    col = idx % w
    right = dr.minimum(idx + 1, h * w - 1)
    down = dr.minimum(idx + w, h * w - 1)
    okr = (col < w - 1) & (dr.gather(mi.Float, weight, right) > 0)
    okd = (idx + w < h * w) & (dr.gather(mi.Float, weight, down) > 0)
    dx = dr.select(okr, dr.abs(dr.gather(mi.Float, x, right) - x), 0.0)
    dy = dr.select(okd, dr.abs(dr.gather(mi.Float, x, down) - x), 0.0)
    return dr.sum((dx + dy) * weight)


def indirect_floor_penalty(indirect_sh: mi.TensorXf, surfel_normal: mi.Vector3f) -> mi.Float:
    """mean over surfels and channels of min(SH(n), 0)^2, the indirect SH [N, K*3] at each
    surfel's normal [N] unclamped: zero wherever the render's clamp lets gradients through,
    and pulling the clamped ones back up to it (``MaterialConfig.lambda_ind_floor``)."""
    raw = eval_sh(indirect_sh, surfel_normal, offset=0.0, floor=None)
    return dr.mean(dr.square(dr.minimum(raw.array, 0.0)))


def view_loss(view: TrainView, channels: dict[str, mi.TensorXf], lights: shading.LightSet,
              vis: mi.Float | None, config: MaterialConfig, with_specular: bool,
              maps: tuple | None = None) -> mi.Float:
    """Eq. 18 for one view (means over its supervised pixels); ``maps``: the view's
    ``view_maps`` of ``channels`` when already made (the normal phase holds them)."""
    h, w = view.pairs.height, view.pairs.width
    albedo, rough, metal, ind = maps if maps is not None else \
        view_maps(view.pairs, channels, view.surfel_normal, with_specular, view.detail_gate)
    rgb = shading.shade(view.geom, albedo, rough, metal, lights, vis, ind, with_specular)
    wgt = view.weight
    inv = view.inv_count
    l_rend = dr.sum((dr.abs(rgb.x - view.target.x) + dr.abs(rgb.y - view.target.y)
                     + dr.abs(rgb.z - view.target.z)) * wgt) * (inv / 3.0)
    loss = l_rend
    if ind is not None:
        loss += config.lambda_ind2 * dr.sum(dr.squared_norm(ind) * wgt) * (inv / 3.0)
        if config.lambda_ind_floor > 0:
            loss += config.lambda_ind_floor * indirect_floor_penalty(
                channels[shading.INDIRECT_CHANNEL], view.surfel_normal)
        loss += config.lambda_tv * sum(_tv(ind[c], wgt, h, w) for c in range(3)) * (inv / 3.0)
    if DETAIL_CHANNEL in channels and maps is None and config.detail_prior > 0:
        d = shading.splat(view.pairs, channels[DETAIL_CHANNEL])  # [H * W * 3]
        loss += config.detail_prior * dr.sum(
            sum(dr.square(shading.channel(d, 3, c)) for c in range(3)) * wgt) * (inv / 3.0)
    tv_mat = mi.Float(0.0)
    if config.albedo_tv_with_segments or not config.segment_average:
        tv_mat += sum(_tv(albedo[c], wgt, h, w) for c in range(3)) / 3.0
    if with_specular:
        tv_mat += _tv(rough, wgt, h, w) + _tv(metal, wgt, h, w)
        loss += config.lambda_reg * dr.sum((1.0 - rough + metal) * wgt) * inv
    loss += config.lambda_brdf * tv_mat * inv
    return loss


def subset_maps(maps, keep: np.ndarray):
    """The shadow maps of the kept directions (no re-rendering: a gather of the texels)."""
    import dataclasses as dc

    idx = np.flatnonzero(keep)
    r2 = maps.resolution * maps.resolution
    tex = (idx[:, None] * r2 + np.arange(r2)[None]).reshape(-1).astype(np.uint32)
    depth = dr.gather(mi.Float, maps.depth, mi.UInt32(tex))
    alpha = None if maps.alpha is None else dr.gather(mi.Float, maps.alpha, mi.UInt32(tex))
    dr.eval(depth, alpha)
    return dc.replace(maps, directions=maps.directions[idx],
                      cameras=[maps.cameras[i] for i in idx], depth=depth, alpha=alpha)


def _clamp_channels(ch: dict, seg, n_seg: int, config: MaterialConfig, with_specular: bool):
    """Projection after a step: the box constraints, then the segment averaging."""
    a = mi.TensorXf(dr.clip(ch["albedo"].array, 0.0, 1.0), ch["albedo"].shape)
    if config.segment_average:
        a = segment_average(a, seg, n_seg)
    ch["albedo"] = a
    if DETAIL_CHANNEL in ch:  # zero-mean per segment: the segment's albedo keeps its scale
        d = ch[DETAIL_CHANNEL]
        d = mi.TensorXf(d.array - segment_average(d, seg, n_seg).array, d.shape)
        ch[DETAIL_CHANNEL] = mi.TensorXf(dr.clip(d.array, -config.detail_max,
                                                 config.detail_max), d.shape)
    if with_specular:
        ch["roughness"] = mi.TensorXf(dr.clip(ch["roughness"].array, ROUGHNESS_MIN, 1.0),
                                      ch["roughness"].shape)
        ch["metallic"] = mi.TensorXf(dr.clip(ch["metallic"].array, 0.0, 1.0),
                                     ch["metallic"].shape)


def surfel_support(views: list[TrainView], n: int) -> np.ndarray:
    """Each surfel's blending weight summed over the supervised pixels of ``views`` [N]."""
    sup = dr.zeros(mi.Float, n)
    for v in views:
        w = v.pairs.weight * dr.gather(mi.Float, v.weight, v.pairs.pix)
        dr.scatter_reduce(dr.ReduceOp.Add, sup, w, v.pairs.sid)
    return sup.numpy().astype(np.float64)


def albedo_scale_factor(albedo: np.ndarray, support: np.ndarray, config: MaterialConfig
                        ) -> float:
    """The factor c that brings the support-weighted ``albedo_scale_quantile`` of the
    surfels' brightest channel (``albedo`` [N, 3]) to ``albedo_scale``. Weighted by what the
    views see: a segment under the base, with no supervised pixel, drifts freely under Adam
    and must not set the scale."""
    top = np.asarray(albedo, np.float64).reshape(len(support), -1).max(axis=1)  # [N]
    order = np.argsort(top)
    cum = np.cumsum(support[order])
    if cum[-1] <= 0:
        return 1.0
    k = min(int(np.searchsorted(cum, config.albedo_scale_quantile * cum[-1])), len(top) - 1)
    return config.albedo_scale / max(float(top[order[k]]), 1e-6)


def hold_albedo_scale(ch: dict, opt, c: float) -> None:
    """Scale the albedo by ``c``, the light (``opt["log_light"]``) and the indirect light by
    1 / c: diffuse shading a (E + ind) is unchanged. ``c`` enters as an opaque scalar: as a
    literal it changed the source of the next step's kernels every time, and each was
    compiled again (a stage-4 fit 102 s against 66 s without the holds)."""
    if c == 1.0:
        return
    a = ch["albedo"]
    ch["albedo"] = mi.TensorXf(a.array * jit.opaque(c), a.shape)
    ind = ch.get(shading.INDIRECT_CHANNEL)
    if ind is not None:
        ch[shading.INDIRECT_CHANNEL] = mi.TensorXf(ind.array * jit.opaque(1.0 / c), ind.shape)
    opt["log_light"] = dr.detach(opt["log_light"]) - jit.opaque(math.log(c))


def prune_lights(dirs: np.ndarray, radiance: np.ndarray, config: MaterialConfig
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Group the directions into lights (``merge_directions``), then drop the lights that
    carry less than ``prune_threshold`` times the strongest light's irradiance.

    Lights are judged after grouping, by what they carry: a light the warm-up localizes
    poorly is spread over many grid cells, each dim (bunny under the low pair: the true
    60 degree light, a third of the irradiance, was 13 cells within 25 degrees of it, the
    brightest at 0.07 of the strong light's single bright cell, so a per-direction
    threshold of 0.1 dropped all of it; merged first, those cells are one light at 1.8
    degrees from the truth with 0.16 of the strongest light's irradiance).

    ``dirs`` [K, 3], ``radiance`` [K] (L_dir). Returns (directions [K'], radiance [K'],
    index [K'] of the kept input lights, or None when some merged: new directions).
    """
    dirs = np.asarray(dirs, np.float64)
    light = np.asarray(radiance, np.float64)
    idx = np.arange(len(dirs))
    if config.merge_angle_deg > 0 and len(dirs) > 1:
        merged, light_m = merge_directions(dirs, light, config.merge_angle_deg)
        if len(merged) < len(dirs):
            dirs, light, idx = merged, light_m, None
    keep = light >= config.prune_threshold * light.max()
    if not keep.all():
        dirs, light = dirs[keep], light[keep]
        idx = None if idx is None else idx[keep]
    return dirs, light, idx


def _prune(opt, dirs: np.ndarray, maps, config: MaterialConfig, render_maps):
    """``prune_lights`` on the optimiser's L_dir: the kept lights' maps are a subset of
    ``maps``, or rendered anew where lights merged. Returns (dirs, maps)."""
    if len(dirs) <= 1:
        return dirs, maps
    light = np.exp(opt["log_light"].numpy().astype(np.float64))
    new_dirs, light, idx = prune_lights(dirs, light, config)
    if idx is None:
        maps = render_maps(new_dirs)
    elif len(idx) < len(dirs) and maps is not None:
        keep = np.zeros(len(dirs), bool)
        keep[idx] = True
        maps = subset_maps(maps, keep)
    if len(light) != dr.width(opt["log_light"]):
        opt["log_light"] = mi.Float(np.log(light).astype(np.float32))
        opt.set_learning_rate({"log_light": config.lr_light})
    return new_dirs, maps


_LIGHT_KEYS = ("log_light",)


def _refine(views, state: MaterialState, maps, render_maps, config: MaterialConfig,
            on_unit, global_pass: bool = False) -> np.ndarray:
    """``refine_directions`` on the optimiser's current state, or the rest of
    ``state.refine`` when a checkpoint was written inside it; sets the refitted light and
    returns the directions."""
    dw = solid_angle(config.n_directions)
    opt = state.opt
    cur = dict(state.channels)
    for key in opt.keys():
        if key not in _LIGHT_KEYS:
            cur[key] = opt[key]
    if state.refine is None:
        irr = np.exp(opt["log_light"].numpy().astype(np.float64)) * dw
        # the end of the warm-up (global_pass) or the main phase's second refinement
        state.refine = Refinement.start(state.directions, irr, config,
                                        global_pass or config.refine_again_global,
                                        again=not global_pass)
    else:
        maps = render_maps(state.refine.dirs)
    state.refine.run(views, cur, maps, render_maps, config, state.specular, on_unit)
    dirs, irr = state.refine.dirs, state.refine.irradiance
    state.refine = None
    opt["log_light"] = mi.Float(np.log(np.maximum(irr / dw, 1e-12)).astype(np.float32))
    opt.set_learning_rate({"log_light": config.lr_light})
    return dirs


def merge_directions(dirs: np.ndarray, energy: np.ndarray, max_angle_deg: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Merge lights closer than ``max_angle_deg`` into one at their energy-weighted mean.

    A directional light between grid directions is fitted as a few neighbouring grid lights
    whose shadows are copies offset by the grid spacing (~13 degrees at 128 directions);
    one light at their weighted mean direction casts the single, sharp shadow the data
    shows. Greedy from the strongest light. Returns (directions [K', 3], energy [K']).
    """
    dirs = np.asarray(dirs, np.float64)
    energy = np.asarray(energy, np.float64)
    cos_max = math.cos(math.radians(max_angle_deg))
    order = np.argsort(-energy)
    centres: list[np.ndarray] = []
    members: list[list[int]] = []
    for i in order:
        best = -1
        for c, centre in enumerate(centres):
            if dirs[i] @ centre >= cos_max and (best < 0 or dirs[i] @ centre >
                                                 dirs[i] @ centres[best]):
                best = c
        if best < 0:
            centres.append(dirs[i])
            members.append([i])
        else:
            members[best].append(i)
    out_d, out_e = [], []
    for idx in members:
        e = energy[idx]
        d = (dirs[idx] * e[:, None]).sum(0)
        out_d.append(d / np.linalg.norm(d))
        out_e.append(e.sum())
    return np.array(out_d), np.array(out_e)


def candidate_directions(direction: np.ndarray, radius_deg: float, step_deg: float
                         ) -> np.ndarray:
    """Unit directions [C, 3] on a square grid of ``step_deg`` in the tangent plane of
    ``direction`` [3] (gnomonic), within ``radius_deg`` of it and above the horizon (y > 0);
    the first is ``direction`` itself."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    t1 = np.cross(d, [0.0, 1.0, 0.0] if abs(d[1]) < 0.99 else [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(d, t1)
    k = int(math.floor(radius_deg / step_deg + 1e-9))
    out = [d]
    for i in range(-k, k + 1):
        for j in range(-k, k + 1):
            if (i or j) and math.hypot(i, j) * step_deg <= radius_deg + 1e-9:
                c = d + math.tan(math.radians(i * step_deg)) * t1 + \
                    math.tan(math.radians(j * step_deg)) * t2
                out.append(c / np.linalg.norm(c))
    out = np.array(out)
    keep = out[:, 1] > 0.0
    keep[0] = True  # the current direction stays a candidate even at the horizon
    return out[keep]


def _view_direct(v: TrainView, channels: dict, config: MaterialConfig, maps, dirs,
                 with_specular: bool):
    """A view's materials (albedo, roughness, metallic, indirect or None), its direct
    shading per light of ``dirs`` [P * K] pixel-major and that visibility [P * K] (from
    ``maps``; None without)."""
    albedo, rough, metal, ind = view_maps(v.pairs, channels, v.surfel_normal, with_specular)
    vis = None if maps is None else \
        maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint)
    per = shading.direct_per_light(v.geom, albedo, rough, metal, dirs, vis, with_specular)
    # [P * K] both, in one kernel: their readers (per channel, per sum, the albedo score's
    # unit-albedo shading) would each recompute the lookups
    dr.eval(per, vis)
    return albedo, rough, metal, ind, per, vis


def _candidate_scores(views: list[TrainView], channels: dict, lights: shading.LightSet, maps,
                      k: int, cand_maps, config: MaterialConfig, with_specular: bool
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(squared error [C], fitted irradiance [C]) of the views when light ``k`` moves to
    each candidate direction of ``cand_maps``, its irradiance re-fitted by least squares
    with the fitted materials. The error is that of ``config.refine_score``: with that one
    irradiance re-fitted ("irradiance"), with the light's scale re-fitted per segment
    ("segment", ``segment_errors``), or with each segment's albedo re-fitted per channel
    ("albedo", ``albedo_errors``)."""
    n_cand = cand_maps.count
    s_rb = dr.zeros(mi.Float64, n_cand)  # summed in Dr.Jit, read once at the end
    s_bb = dr.zeros(mi.Float64, n_cand)
    s_rr = mi.Float64(0.0)
    n_seg = max(v.n_segments for v in views) if views else 1
    seg_sums = _SegmentSums(n_cand, n_seg) if config.refine_score != "irradiance" else None
    alb_sums = _AlbedoSums(n_cand, n_seg) if config.refine_score == "albedo" else None
    with dr.suspend_grad():
        for v in views:
            albedo, rough, metal, ind, per, vis_k = _view_direct(
                v, channels, config, maps, lights.directions, with_specular)
            npix = dr.width(v.geom.alpha)
            kk = lights.count
            li = dr.arange(mi.UInt32, npix * kk) % kk
            e = dr.gather(mi.Color3f, lights.weights, li)
            others = dr.select(li == k, 0.0, 1.0) * e * per
            rest = mi.Color3f(*(dr.block_reduce(dr.ReduceOp.Add, others[c], kk)
                                for c in range(3)))
            if ind is not None:
                rest = rest + (1.0 - metal) * albedo * ind
            resid = (v.target - rest) * v.weight  # [P], what light k has to explain
            vis = cand_maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint)
            if alb_sums is not None:
                dr.eval(vis)  # [P * C]: read by both shadings below
            b = shading.direct_per_light(v.geom, albedo, rough, metal, cand_maps.directions,
                                         vis, with_specular)  # [P * C] pixel-major
            dr.eval(b)  # once: r.b and b.b below would each recompute the lookups
            pi = dr.arange(mi.UInt32, npix * n_cand) // n_cand
            r = dr.gather(mi.Color3f, resid, pi)
            b = b * dr.gather(mi.Float, v.weight, pi)
            # Candidate-major for the per-candidate sums over pixels.
            cm = dr.arange(mi.UInt32, npix * n_cand)
            src = (cm % npix) * n_cand + cm // npix
            rb = dr.gather(mi.Float, dr.sum(r * b), src)
            bb = dr.gather(mi.Float, dr.squared_norm(b), src)
            s_rb += mi.Float64(dr.block_reduce(dr.ReduceOp.Add, rb, npix))
            s_bb += mi.Float64(dr.block_reduce(dr.ReduceOp.Add, bb, npix))
            s_rr += mi.Float64(dr.sum(dr.squared_norm(resid)))
            if seg_sums is not None:
                seg_sums.add(v, resid, rb, bb)
            if alb_sums is not None:
                _add_albedo_sums(alb_sums, v, lights, vis_k, k, cand_maps.directions, vis)
            dr.eval(s_rb, s_bb, s_rr)  # one kernel per view, not one growing graph
    s_rb, s_bb = s_rb.numpy(), s_bb.numpy()
    s_rr = float(s_rr.numpy()[0])
    irr = np.where(s_bb > 0, np.maximum(s_rb, 0.0) / np.maximum(s_bb, 1e-30), 0.0)
    err = s_rr - 2.0 * irr * s_rb + irr * irr * s_bb
    if seg_sums is not None:
        err = segment_errors(*seg_sums.read())
    if alb_sums is not None:
        weights = np.asarray(lights.weights.numpy(), np.float64).reshape(3, -1).mean(0)
        err_a, e_a = albedo_errors(*alb_sums.read(), max(float(weights.sum()), 1e-12))
        if e_a[np.argmin(err_a)] >= ALBEDO_MIN_SHARE * weights[k]:
            err = err_a
    return err, irr


def _add_albedo_sums(sums: _AlbedoSums, v: TrainView, lights: shading.LightSet,
                     vis: mi.Float | None, k: int, cand_dirs: np.ndarray, cand_vis: mi.Float
                     ) -> None:
    """One view's sums of ``albedo_errors`` (no lobe): the target, the other lights' shading
    X at unit albedo (``vis`` [P * K] the lights' visibility, None: V = 1) and the
    candidates' B (``cand_vis`` [P * C] theirs). Only the target, the geometry, the shadow
    maps and the lights enter, not the fitted materials."""
    npix = dr.width(v.geom.alpha)
    zero = dr.zeros(mi.Float, npix)
    # a unit albedo splatted as the model's albedo is: the pixel's coverage (a silhouette
    # pixel's target is the blend with what lies behind)
    white = mi.Color3f(v.geom.alpha, v.geom.alpha, v.geom.alpha)
    per = shading.direct_per_light(v.geom, white, zero, zero, lights.directions, vis, False)
    kk = lights.count
    li = dr.arange(mi.UInt32, npix * kk) % kk
    others = dr.select(li == k, 0.0, 1.0) * dr.gather(mi.Color3f, lights.weights, li) * per
    x = mi.Color3f(*(dr.block_reduce(dr.ReduceOp.Add, others[c], kk) for c in range(3)))
    b = shading.direct_per_light(v.geom, white, zero, zero, cand_dirs, cand_vis, False)
    dr.eval(x, b)  # [P], [P * C] pixel-major (b grey)
    sums.add(v, v.target * v.weight, x * v.weight, b[0])


class _SegmentSums:
    """The per-(candidate, segment) sums of ``segment_errors``, accumulated over views."""

    def __init__(self, n_cand: int, n_seg: int):
        # one bin more than the segments: the mixed pixels (TrainView.segment), dropped
        self.n_cand, self.n_seg = n_cand, n_seg + 1
        self.rr = dr.zeros(mi.Float64, self.n_seg)  # [S + 1] r.r
        # [C * (S + 1)] (candidate-major): r.B, B.B
        self.rb = dr.zeros(mi.Float64, n_cand * self.n_seg)
        self.bb = dr.zeros(mi.Float64, n_cand * self.n_seg)

    def add(self, v: TrainView, resid: mi.Color3f, rb: mi.Float, bb: mi.Float) -> None:
        """One view: the residual ``resid`` [P] that the light has to explain, and r.B_c and
        B_c.B_c [C * P] candidate-major (pixel weights applied)."""
        npix = dr.width(v.weight)
        seg = dr.select(v.segment >= v.n_segments, self.n_seg - 1, v.segment)  # [P]
        dr.scatter_reduce(dr.ReduceOp.Add, self.rr, mi.Float64(dr.squared_norm(resid)), seg)
        cm = dr.arange(mi.UInt32, npix * self.n_cand)  # candidate-major: c * P + p
        idx = (cm // npix) * self.n_seg + dr.gather(mi.UInt32, seg, cm % npix)
        dr.scatter_reduce(dr.ReduceOp.Add, self.rb, mi.Float64(rb), idx)
        dr.scatter_reduce(dr.ReduceOp.Add, self.bb, mi.Float64(bb), idx)
        dr.eval(self.rr, self.rb, self.bb)

    def read(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        shape = (self.n_cand, self.n_seg)
        return (self.rr.numpy()[:-1], self.rb.numpy().reshape(shape)[:, :-1],
                self.bb.numpy().reshape(shape)[:, :-1])


class _AlbedoSums:
    """The sums of ``albedo_errors`` over the views, per segment (and candidate) and colour
    channel; mixed pixels (``TrainView.segment`` = S) go to a last bin, dropped."""

    def __init__(self, n_cand: int, n_seg: int):
        self.n_cand, self.n_seg = n_cand, n_seg + 1
        # [(S + 1) * 3]: t.t, t.X, X.X
        self.tt, self.tx, self.xx = (dr.zeros(mi.Float64, self.n_seg * 3) for _ in range(3))
        # [C * (S + 1) * 3]: t.B, X.B; [C * (S + 1)]: B.B
        self.tb, self.xb = (dr.zeros(mi.Float64, n_cand * self.n_seg * 3) for _ in range(2))
        self.bb = dr.zeros(mi.Float64, n_cand * self.n_seg)

    def add(self, v: TrainView, t: mi.Color3f, x: mi.Color3f, b: mi.Float) -> None:
        """One view: target ``t`` [P] and other lights' shading ``x`` [P] (supervised pixels,
        else 0), the candidates' shading ``b`` [P * C] pixel-major (any pixel)."""
        npix, nc = dr.width(v.weight), self.n_cand
        seg = dr.select(v.segment >= v.n_segments, self.n_seg - 1, v.segment)  # [P]
        pi = dr.arange(mi.UInt32, npix * nc) // nc
        ci = dr.arange(mi.UInt32, npix * nc) % nc
        cs = ci * self.n_seg + dr.gather(mi.UInt32, seg, pi)  # [P * C] (candidate, segment)
        b = b * dr.gather(mi.Float, v.weight, pi)
        dr.scatter_reduce(dr.ReduceOp.Add, self.bb, mi.Float64(b * b), cs)
        for c in range(3):
            dr.scatter_reduce(dr.ReduceOp.Add, self.tt, mi.Float64(t[c] * t[c]), seg * 3 + c)
            dr.scatter_reduce(dr.ReduceOp.Add, self.tx, mi.Float64(t[c] * x[c]), seg * 3 + c)
            dr.scatter_reduce(dr.ReduceOp.Add, self.xx, mi.Float64(x[c] * x[c]), seg * 3 + c)
            dr.scatter_reduce(dr.ReduceOp.Add, self.tb,
                              mi.Float64(dr.gather(mi.Float, t[c], pi) * b), cs * 3 + c)
            dr.scatter_reduce(dr.ReduceOp.Add, self.xb,
                              mi.Float64(dr.gather(mi.Float, x[c], pi) * b), cs * 3 + c)
        dr.eval(self.tt, self.tx, self.xx, self.tb, self.xb, self.bb)

    def read(self) -> tuple[np.ndarray, ...]:
        """tt, tx, xx [S, 3]; tb, xb [C, S, 3]; bb [C, S] (the mixed bin dropped)."""
        s3, c3 = (self.n_seg, 3), (self.n_cand, self.n_seg, 3)
        return (self.tt.numpy().reshape(s3)[:-1], self.tx.numpy().reshape(s3)[:-1],
                self.xx.numpy().reshape(s3)[:-1], self.tb.numpy().reshape(c3)[:, :-1],
                self.xb.numpy().reshape(c3)[:, :-1],
                self.bb.numpy().reshape(self.n_cand, self.n_seg)[:, :-1])


# The 1-D search of albedo_errors: E over [1e-3, 1e3] x the lights' total irradiance on a
# log grid (steps of 5.9%), then a finer grid over the best cell's neighbours (steps of
# 0.29%). With the albedo free the other lights' scale is free too, relative to E: at the
# top of the range they are all but gone, so a light split over two grid cells (the
# warm-up's) is scored as if it were the only one.
ALBEDO_SEARCH = (241, 41, 1e-3, 1e3)
# Under "albedo", the moved light's irradiance at the best candidate, below this share of
# its current irradiance, means the other lights explain the views once the albedo is
# re-fitted, and the score is flat: then the "segment" score decides. Once one half of a
# light split over two grid cells is at the truth, the other half's best E was 0.03 of its
# 1.07, and the "albedo" score alone moved it 11 deg away; the two merged 5.8 deg off
# (tests/test_light_fit.py, the grid-cell boundary). The "segment" score, with the fitted
# albedo, has that half's energy left to place. On the sweep's s6 the weak light's best E
# was ~0.9 of its own. Without other lights' shading (X = 0) nothing else explains the views
# and E is inf (``albedo_errors``): the albedo score holds.
ALBEDO_MIN_SHARE = 0.25


def albedo_errors(tt: np.ndarray, tx: np.ndarray, xx: np.ndarray, tb: np.ndarray,
                  xb: np.ndarray, bb: np.ndarray, scale: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Squared error [C] and irradiance E [C] of each candidate when every segment s and
    channel c takes its own albedo a_sc >= 0 in t ~ a_sc (X_c + E B) (``refine_score``
    "albedo"): per (s, c) the least-squares a_sc leaves tt - (tX + E tB)^2 / |X + E B|^2,
    summed; E >= 0, one per candidate, is searched on ``ALBEDO_SEARCH``'s grids around
    ``scale``. Sums as ``_AlbedoSums.read``.

    Where X is 0 on every supervised pixel (one light, or the others dark) the albedo
    absorbs E: the error is the same at every E, and E is inf (unbounded) for all."""
    def err(e: np.ndarray) -> np.ndarray:  # e [C, G] -> [C, G]
        e4 = e[:, :, None, None]
        num = tx[None, None] + e4 * tb[:, None]
        den = xx[None, None] + 2.0 * e4 * xb[:, None] + e4 * e4 * bb[:, None, :, None]
        gain = np.where(den > 0, np.maximum(num, 0.0) ** 2 / np.where(den > 0, den, 1.0), 0.0)
        return (tt[None, None] - gain).sum((2, 3))

    if not (np.any(tx) or np.any(xx) or np.any(xb)):
        # t ~ a_sc E B: flat in E up to round-off. The search's argmin was round-off's
        # choice (0.18 or 164 of a one-light test's 1.5 as a float atomic's order on two
        # threads changed one pixel's last bit), and with it ALBEDO_MIN_SHARE's branch.
        return err(np.full((len(tb), 1), float(scale)))[:, 0], np.full(len(tb), np.inf)
    n_coarse, n_fine, lo_e, hi_e = ALBEDO_SEARCH
    grid = scale * np.geomspace(lo_e, hi_e, n_coarse)
    coarse = err(np.broadcast_to(grid, (len(tb), n_coarse)))
    j = np.argmin(coarse, 1)
    lo, hi = grid[np.maximum(j - 1, 0)], grid[np.minimum(j + 1, n_coarse - 1)]
    fine_e = np.geomspace(lo, hi, n_fine, axis=1)  # [C, F]
    fine = err(fine_e)
    i = np.argmin(fine, 1)
    rows = np.arange(len(tb))
    return fine[rows, i], fine_e[rows, i]


def segment_errors(rr: np.ndarray, rb: np.ndarray, bb: np.ndarray) -> np.ndarray:
    """Squared error [C] of the views when, in each segment s, the residual r = t - R that
    the moved light has to explain is fitted by least squares as b_s B_c, b_s >= 0
    (``MaterialConfig.refine_score`` "segment").

    Sums over the segment's supervised pixels and colour channels: ``rr`` [S] of r.r;
    ``rb``, ``bb`` [C, S] of r.B_c and B_c.B_c. A segment where B_c is zero (all in shadow)
    keeps its whole residual.
    """
    gain = np.where(bb > 0, np.maximum(rb, 0.0) ** 2 / np.where(bb > 0, bb, 1.0), 0.0)
    return (rr[None] - gain).sum(1)


def light_normal_equations(views: list[TrainView], channels: dict, dirs: np.ndarray, maps,
                           config: MaterialConfig, with_specular: bool,
                           per_segment: bool = False):
    """Least squares of the views in the lights' irradiance e [K] (albedo, materials and
    indirect light fixed): the squared error is rr - 2 e . h + e^T G e. Returns (G [K, K],
    h [K], rr), float64; rr is the squared direct signal (target minus indirect).
    ``per_segment``: the same sums per material segment, over the pixels that one segment
    holds (``TrainView.segment``): G [S, K, K], h [S, K], rr [S]."""
    k = len(dirs)
    n_seg = max(v.n_segments for v in views) if per_segment else 1
    gram, h, rr = np.zeros((n_seg, k, k)), np.zeros((n_seg, k)), np.zeros(n_seg)
    with dr.suspend_grad():
        for v in views:
            albedo, rough, metal, ind, per, _ = _view_direct(v, channels, config, maps, dirs,
                                                             with_specular)  # per: [P * K]
            resid = v.target - (1.0 - metal) * albedo * ind if ind is not None else v.target
            wgt = np.asarray(v.weight.numpy(), np.float64)  # [P]
            b = np.stack([np.asarray(per[c], np.float64).reshape(-1, k) for c in range(3)])
            r = np.stack([np.asarray(resid[c], np.float64) for c in range(3)])  # [3, P]
            b *= wgt[None, :, None]  # [3, P, K]
            r *= wgt[None]
            seg = v.segment.numpy() if per_segment else None  # [P]
            for s_id in range(n_seg):
                bs, rs = b, r
                if seg is not None:  # mixed pixels (seg == v.n_segments) are in no segment
                    on = seg == s_id
                    bs, rs = b[:, on], r[:, on]
                gram[s_id] += np.einsum("cpk,cpj->kj", bs, bs)
                h[s_id] += np.einsum("cpk,cp->k", bs, rs)
                rr[s_id] += float(np.sum(rs * rs))
    if not per_segment:
        return gram[0], h[0], float(rr[0])
    return gram, h, rr


# segment_nnls's alternations of the light and the segments' scales; each lowers the error,
# and a fixed count (not a tolerance) keeps the light drops the same on every machine.
SEGMENT_NNLS_ALTERNATIONS = 20


def segment_nnls(gram: np.ndarray, h: np.ndarray, keep: np.ndarray,
                 iterations: int = SEGMENT_NNLS_ALTERNATIONS) -> tuple[np.ndarray, float]:
    """argmin over e >= 0 (0 off ``keep``) and one scale c_s >= 0 per segment of
    sum_s c_s^2 e^T G_s e - 2 c_s e . h_s (``gram`` [S, K, K], ``h`` [S, K]), by
    alternating the two (each step lowers it); returns (e, that minimum). e's scale is
    arbitrary (traded with the c_s)."""
    c = np.ones(len(h))
    e, err = np.zeros(h.shape[1]), 0.0
    for _ in range(iterations):
        e, _ = nnls_irradiance(np.einsum("s,skj->kj", c * c, gram), np.einsum("s,sk->k", c, h),
                               keep)
        q = np.einsum("k,skj,j->s", e, gram, e)  # [S]
        p = h @ e  # [S]
        c = np.where(q > 0, np.maximum(p, 0.0) / np.where(q > 0, q, 1.0), 0.0)
        err = float(np.sum(c * c * q - 2.0 * c * p))
    return e, err


def nnls_irradiance(gram: np.ndarray, h: np.ndarray, keep: np.ndarray
                    ) -> tuple[np.ndarray, float]:
    """argmin_{e >= 0, e = 0 off ``keep``} of e^T G e - 2 e . h, and that minimum."""
    from scipy.optimize import nnls

    e = np.zeros(len(h))
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return e, 0.0
    g = gram[np.ix_(idx, idx)]
    # A relative ridge keeps the factorization defined for lights with identical images.
    g = g + np.eye(len(idx)) * (1e-9 * max(float(np.trace(g)) / len(idx), 1e-30))
    chol = np.linalg.cholesky(g)  # g = chol chol^T
    e[idx] = nnls(chol.T, np.linalg.solve(chol, h[idx]))[0]
    return e, float(e @ gram @ e - 2.0 * e @ h)


def drop_unexplained(gram: np.ndarray, h: np.ndarray, rr, config: MaterialConfig
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Backward elimination of lights (see ``MaterialConfig.drop_share``): repeatedly drop
    the light whose removal costs least, while it carries < drop_share of the re-fitted
    irradiance and raises the squared error by < drop_gain times the error with it.
    Per-segment sums (``gram`` [S, K, K], ``h`` [S, K], ``rr`` [S]) are fitted with a scale
    per segment (``segment_nnls``). Returns (keep [K] bool, irradiance [K]); the irradiance
    is the global fit of the kept lights (the segments' sums added)."""
    if gram.ndim == 3:
        keep = _eliminate(gram, h, float(np.sum(rr)), config, segment_nnls)
        return keep, nnls_irradiance(gram.sum(0), h.sum(0), keep)[0]
    keep = _eliminate(gram, h, float(rr), config, nnls_irradiance)
    return keep, nnls_irradiance(gram, h, keep)[0]


def _eliminate(gram: np.ndarray, h: np.ndarray, rr: float, config: MaterialConfig, solve
               ) -> np.ndarray:
    """``drop_unexplained``'s loop with the fit ``solve(gram, h, keep) -> (e, error)``."""
    keep = np.ones(h.shape[-1], bool)
    e, err = solve(gram, h, keep)
    while keep.sum() > 1:
        total = e[keep].sum()
        best, best_cost, best_fit = -1, math.inf, None
        for k in np.flatnonzero(keep):
            if total > 0 and e[k] >= config.drop_share * total:
                continue
            trial = keep.copy()
            trial[k] = False
            e_k, err_k = solve(gram, h, trial)
            if err_k - err < best_cost:
                best, best_cost, best_fit = k, err_k - err, (e_k, err_k)
        # The error with every current light: a light the data needs raises it by far more
        # than any threshold (a fit explaining the views exactly has error ~0).
        if best < 0 or best_cost >= config.drop_gain * max(rr + err, 1e-12 * rr):
            break
        keep[best] = False
        e, err = best_fit
    return keep


def settle_lights(views: list[TrainView], channels: dict, dirs: np.ndarray,
                  irradiance: np.ndarray, maps, render_maps, config: MaterialConfig,
                  with_specular: bool) -> tuple[np.ndarray, np.ndarray, object]:
    """After a refinement: lights that moved within ``merge_angle_deg`` of each other merge
    (a light split over two grid cells is refined onto one spot twice), then
    ``drop_unexplained``. Returns (dirs [K'], irradiance [K'], their maps)."""
    dirs, irr = np.asarray(dirs, np.float64), np.asarray(irradiance, np.float64)
    if config.merge_angle_deg > 0 and len(dirs) > 1:
        merged, irr_m = merge_directions(dirs, irr, config.merge_angle_deg)
        if len(merged) < len(dirs):
            dirs, irr = merged, irr_m
            maps = render_maps(dirs)
    if config.drop_share > 0 and len(dirs) > 1:
        gram, h, rr = light_normal_equations(views, channels, dirs, maps, config,
                                             with_specular, config.settle_score == "segment")
        keep, e = drop_unexplained(gram, h, rr, config)
        dirs, irr = dirs[keep], e[keep]  # the joint re-fit: better than one at a time
        if not keep.all() and maps is not None:
            maps = subset_maps(maps, keep)
    return dirs, irr, maps


def _settle(fit: MaterialFit, state: MaterialState) -> None:
    """``settle_lights`` on the refinement's views and the optimiser's current state."""
    config, opt = fit.config, state.opt
    cur = dict(state.channels)
    for key in opt.keys():
        if key not in _LIGHT_KEYS:
            cur[key] = opt[key]
    pick = np.unique(np.linspace(0, len(fit.views) - 1,
                                 min(config.refine_views, len(fit.views))).round().astype(int))
    dw = solid_angle(config.n_directions)
    irr = np.exp(opt["log_light"].numpy().astype(np.float64)) * dw
    dirs, irr, maps = settle_lights([fit.views[i] for i in pick], cur, state.directions, irr,
                                    fit.maps, fit.shadow_maps, config, state.specular)
    state.directions, fit.maps = dirs, maps
    opt["log_light"] = mi.Float(np.log(np.maximum(irr / dw, 1e-12)).astype(np.float32))
    opt.set_learning_rate({"log_light": config.lr_light})


@dataclasses.dataclass
class Refinement:
    """A light-direction refinement (``refine_directions``) in progress: it continues after
    each finished (light, pass) unit, so that a checkpoint can be written between units
    (cpu-small, 25k surfels, 2 cores: 40 s per refinement on quiet cores, 80 s on loaded
    ones; a unit ~10 s)."""

    dirs: np.ndarray  # [K, 3] the lights' directions so far
    irradiance: np.ndarray  # [K]
    lights: np.ndarray  # [R] the lights refined, strongest first
    done: int = 0  # finished (light, pass) units
    global_pass: bool = False  # each light starts with the global pass (refine_global)
    again: bool = False  # the main phase's second refinement (refine_again_passes)

    @staticmethod
    def start(dirs: np.ndarray, irradiance: np.ndarray, config: MaterialConfig,
              global_pass: bool = False, again: bool = False) -> Refinement:
        irr = np.array(irradiance, np.float64)
        # The strongest first: it shapes the residual most.
        return Refinement(np.array(dirs, np.float64), irr,
                          np.argsort(-irr)[:config.refine_max_lights],
                          global_pass=global_pass and config.refine_global > 0, again=again)

    def units(self, config: MaterialConfig) -> list[tuple[int, float, float]]:
        """(light, radius, step) in order; radius inf: the global pass."""
        # after a global pass the local passes start a grid cell away: the first
        # refinement's, whichever refinement this is
        passes = ([(math.inf, 0.0)] if self.global_pass else []) + \
            list(config.local_passes(self.again and not self.global_pass))
        return [(int(k), r, st) for k in self.lights for r, st in passes]

    def run(self, views: list[TrainView], channels: dict, maps, render_maps,
            config: MaterialConfig, with_specular: bool, on_unit=None) -> None:
        """The units left; ``maps``: the shadow maps of ``dirs``; ``on_unit()`` after each."""
        pick = np.unique(np.linspace(0, len(views) - 1, min(config.refine_views, len(views)))
                         .round().astype(int))
        sub = [views[i] for i in pick]
        sub_global = sub[::max(1, -(-len(sub) // config.refine_global_views))]
        for k, radius, step in self.units(config)[self.done:]:
            scored = sub
            if math.isinf(radius):
                cand = np.concatenate([self.dirs[k][None], light_grid(config.refine_global)])
                cand_maps = render_maps(cand, config.refine_global_map_resolution)
                scored = sub_global
            else:
                cand = candidate_directions(self.dirs[k], radius, step)
                cand_maps = render_maps(cand)
            irr = jit.array(self.irradiance.astype(np.float32))
            lights = shading.LightSet(self.dirs, mi.Color3f(irr, irr, irr))
            err, fit = _candidate_scores(scored, channels, lights, maps, k, cand_maps,
                                         config, with_specular)
            best = int(np.argmin(err))
            if best != 0 and fit[best] > 0:
                self.dirs[k], self.irradiance[k] = cand[best], fit[best]
                maps = render_maps(self.dirs)
            self.done += 1
            if on_unit:
                on_unit()


def refine_directions(views: list[TrainView], channels: dict, dirs: np.ndarray,
                      irradiance: np.ndarray, maps, render_maps, config: MaterialConfig,
                      with_specular: bool, global_pass: bool = False
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Grid search of each light's direction: the global pass (``global_pass`` and
    ``MaterialConfig.refine_global``), then the local ``refine_passes``.

    ``dirs`` [K, 3] and ``irradiance`` [K] are the current lights; ``maps`` their shadow
    maps; ``render_maps(directions, resolution=None)`` renders maps. Returns the refined
    (dirs, irradiance).
    """
    refinement = Refinement.start(dirs, irradiance, config, global_pass)
    refinement.run(views, channels, maps, render_maps, config, with_specular)
    return refinement.dirs, refinement.irradiance


@dataclasses.dataclass
class MaterialFit:
    """What a fit holds fixed (the surfels, the prepared views, the segments) and the shadow
    maps of its current lights; made by ``setup_fit``."""

    surfels: Surfels
    views: list[TrainView]
    seg: mi.UInt32  # [N] segment id per surfel
    n_seg: int
    config: MaterialConfig
    vis_config: VisibilityConfig
    bounds: SceneBounds
    maps: object  # the current lights' shadow maps (None without visibility)
    support: np.ndarray | None = None  # [N] surfel_support, made when first needed
    # The maps rendered so far: the refinement asks again for the candidates' current
    # direction and, after a move, for every light's map (the moved one a candidate's).
    # 96 MB: a local pass's 49 candidate maps at 512^2 and the lights'.
    map_cache: MapCache | None = None
    start_normals: mi.Vector3f | None = None  # [N] the normal phase's n0, made at its start
    held_normals: mi.Bool | None = None  # [N] the surfels whose normal the phase holds
    # The normal phase's per-view material maps (held there, so made once per view), by view
    # index; kept while they fit in HELD_MAPS_BYTES.
    held_maps: dict = dataclasses.field(default_factory=dict)

    def shadow_maps(self, directions, resolution=None):
        """Shadow maps of ``directions`` (at ``resolution``, default the visibility's)."""
        if not self.config.use_visibility:
            return None
        cfg = self.vis_config if resolution is None else \
            dataclasses.replace(self.vis_config, resolution=resolution)
        if self.map_cache is None:
            self.map_cache = MapCache(self.surfels, self.bounds, max_bytes=96 << 20)
        return self.map_cache.maps(directions, cfg)


def setup_fit(surfels: Surfels, cameras: list[Camera], images: list[np.ndarray],
              masks: list[np.ndarray], config: MaterialConfig, bounds: SceneBounds,
              vis_config: VisibilityConfig = DEFAULT_VISIBILITY,
              raster: RasterConfig = DEFAULT_RASTER, progress: bool = True,
              state: MaterialState | None = None) -> tuple[MaterialFit, MaterialState]:
    """Set-up: the training views' fixed lookups, the state at step 0 (or ``state``, from a
    checkpoint) and the shadow maps of its lights."""
    from tqdm import tqdm

    if not (len(cameras) == len(images) == len(masks)) or not cameras:
        raise ValueError("fit_material: need as many images and masks as cameras (>= 1)")
    t0 = time.perf_counter()
    seg = segment_ids(surfels)
    n_seg = int(np.max(seg.numpy())) + 1 if surfels.count else 1
    views = [prepare_view(surfels, c, im, m, config, raster, vis_config.receiver_band)
             for c, im, m in zip(tqdm(cameras, desc="stage 4: views", disable=not progress),
                                 images, masks, strict=True)]
    if state is None:
        state = _initial_state(surfels, images, views, seg, n_seg, config)
    state.timings["prepare_s"] = state.timings.get("prepare_s", 0.0) + \
        time.perf_counter() - t0
    fit = MaterialFit(surfels, views, seg, n_seg, config, vis_config, bounds, None)
    # Per-view point/normal lookups are fixed: visibility of all active directions per view
    # is re-evaluated on the fly (cheap gathers) rather than stored (V x H x W x L floats).
    # The warm-up's maps up to its end (unless the checkpoint is inside the refinement that
    # follows it), the full-resolution ones after.
    warmup_res = min(config.warmup_map_resolution, vis_config.resolution)
    fit.maps = fit.shadow_maps(state.directions, warmup_res if state.step < config.warmup or (
        state.step == config.warmup and state.refine is None) else None)
    if DETAIL_CHANNEL in state.channels and state.step < config.iterations:
        detail_gates(fit, state)  # resumed while the detail fits (the normal phase holds it)
    return fit, state


def refine_lights(fit: MaterialFit, state: MaterialState, on_unit=None,
                  global_pass: bool = False) -> None:
    """The light-direction refinement (or the rest of ``state.refine``), then the refined
    lights' maps (nothing without refinement passes or visibility), then ``settle_lights``
    (merge the lights that met, drop those that explain little)."""
    # the end of the warm-up (global_pass) or the main phase's second refinement
    if (fit.config.local_passes(not global_pass) or (global_pass and fit.config.refine_global)) \
            and fit.maps is not None:
        state.directions = _refine(fit.views, state, fit.maps, fit.shadow_maps, fit.config,
                                   on_unit, global_pass)
        fit.maps = fit.shadow_maps(state.directions)
        state.log_lights("refine", solid_angle(fit.config.n_directions))
    if len(state.directions) > 1:
        _settle(fit, state)
        state.log_lights("settle", solid_angle(fit.config.n_directions))


def end_warmup(fit: MaterialFit, state: MaterialState, on_unit=None) -> None:
    """At step ``warmup``: prune the dark lights, the survivors' maps at full resolution,
    settle them (``settle_warmup``; all three skipped when resuming inside the refinement
    that follows), refine the lights, then add the indirect light and decide on the
    specular lobe (``auto``)."""
    if state.refine is None:
        # One host read at the phase boundary.
        if fit.config.prune:
            state.directions, fit.maps = _prune(state.opt, state.directions, fit.maps,
                                                fit.config, fit.shadow_maps)
            state.log_lights("prune", solid_angle(fit.config.n_directions))
        fit.maps = fit.shadow_maps(state.directions)
        if fit.config.settle_warmup and len(state.directions) > 1:
            _settle(fit, state)
            state.log_lights("settle", solid_angle(fit.config.n_directions))
    refine_lights(fit, state, on_unit, global_pass=True)
    _end_warmup(state, fit.config)


def prune_due(config: MaterialConfig, step: int) -> bool:
    """Whether the main phase prunes the lights before ``step``."""
    return config.prune and step > config.warmup and config.prune_every > 0 and \
        (step - config.warmup) % config.prune_every == 0


def refine_step(config: MaterialConfig) -> int:
    """The main phase's second refinement: half way (-1: none)."""
    return (config.warmup + config.iterations) // 2 \
        if config.iterations > config.warmup + 1 else -1


def fit_step(fit: MaterialFit, state: MaterialState) -> float | None:
    """One optimisation step: loss over ``views_per_step`` random views, Adam, projection.
    Returns the mean loss since the last history entry on a ``log_every`` step, else None."""
    config, opt, ch = fit.config, state.opt, state.channels
    w_light = dr.exp(opt["log_light"]) * solid_angle(config.n_directions)
    lights = shading.LightSet(state.directions, mi.Color3f(w_light, w_light, w_light))
    cur = dict(ch)
    for k in opt.keys():
        if k not in _LIGHT_KEYS:
            cur[k] = opt[k]
    total = mi.Float(0.0)
    for _ in range(config.views_per_step):
        v = fit.views[int(state.rng.integers(len(fit.views)))]
        vis = None if fit.maps is None else \
            fit.maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint)
        total += view_loss(v, cur, lights, vis, config, state.specular)
    total = total / config.views_per_step
    dr.backward(total)
    opt.step()
    for k in opt.keys():
        if k not in _LIGHT_KEYS:
            ch[k] = opt[k]
    _clamp_channels(ch, fit.seg, fit.n_seg, config, state.specular)
    if config.albedo_scale > 0 and not state.specular and \
            state.step % config.albedo_scale_every == 0:  # a host read
        if fit.support is None:
            fit.support = surfel_support(fit.views, fit.surfels.count)
        hold_albedo_scale(ch, opt, albedo_scale_factor(ch["albedo"].numpy(), fit.support,
                                                       config))
    for k in opt.keys():
        if k not in _LIGHT_KEYS:
            opt[k] = ch[k]  # keeps Adam's state (same shape)
    return _count_step(state, config, total)


def _count_step(state: MaterialState, config: MaterialConfig, total: mi.Float) -> float | None:
    """A finished step's bookkeeping; the mean loss on a ``log_every`` step, else None."""
    state.loss_sum += dr.detach(total)
    state.step += 1
    if state.step % config.log_every != 0:
        return None
    # A host read every log_every steps.
    mean = float(state.loss_sum.numpy()[0]) / config.log_every
    state.history.append((state.step, mean))
    state.loss_sum = mi.Float(0.0)
    return mean


def detail_step(config: MaterialConfig) -> int:
    """The step the albedo detail joins (after the second refinement, else the warm-up's
    end); -1: never (``detail_prior`` 0)."""
    if config.detail_prior <= 0:
        return -1
    again = refine_step(config)
    return again if again >= 0 else config.warmup


def detail_gates(fit: MaterialFit, state: MaterialState) -> None:
    """Each view's ``detail_gate``: its pixels farther than ``detail_edge_px`` from where a
    light's shadow begins (its visibility crosses 0.5), for the lights the detail joined
    with (``state.detail_directions``: a fit resumed after a light was pruned makes the
    same gates; one host read a view). None (every pixel) without visibility."""
    from scipy.ndimage import maximum_filter, minimum_filter

    if fit.config.detail_edge_px <= 0 or fit.maps is None:
        return
    dirs = state.detail_directions
    maps = fit.maps if np.array_equal(dirs, state.directions) else fit.shadow_maps(dirs)
    size = (2 * fit.config.detail_edge_px + 1,) * 2 + (1,)
    for k, v in enumerate(fit.views):
        with dr.suspend_grad():
            vis = maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint)
        lit = vis.numpy().reshape(v.pairs.height, v.pairs.width, -1) > 0.5  # [H, W, L]
        edge = np.any(maximum_filter(lit, size) != minimum_filter(lit, size), axis=2)
        fit.views[k] = dataclasses.replace(
            v, detail_gate=mi.Float((~edge).reshape(-1).astype(np.float32)))


def start_detail(fit: MaterialFit, state: MaterialState) -> None:
    """At ``detail_step``: the albedo detail joins Adam at 0, and the views' gates."""
    n = fit.surfels.count
    state.channels[DETAIL_CHANNEL] = mi.TensorXf(dr.zeros(mi.Float, n * 3), (n, 3))
    state.opt[DETAIL_CHANNEL] = state.channels[DETAIL_CHANNEL]
    state.opt.set_learning_rate({DETAIL_CHANNEL: fit.config.lr_detail})
    state.detail_directions = np.array(state.directions, np.float64)
    detail_gates(fit, state)


def start_normal_phase(fit: MaterialFit, state: MaterialState) -> None:
    """At step ``iterations`` (``normal_steps`` > 0): the materials and the indirect light
    are final and leave Adam (their values stay in ``state.channels``), the light stays in it
    at learning rate 0 (as fitted), and the shading normals join it, started from the
    surfels' own (stage 2's)."""
    opt, n = state.opt, fit.surfels.count
    fit.held_maps.clear()  # made again from the materials held from here on
    for k in list(opt.keys()):
        if k not in _LIGHT_KEYS:
            state.channels[k] = opt[k]
            del opt[k]
    opt.set_learning_rate({k: 0.0 for k in _LIGHT_KEYS})
    start, _ = _start_normals(fit)
    opt[shading.SHADING_NORMAL_CHANNEL] = mi.TensorXf(dr.ravel(start), (n, 3))
    opt.set_learning_rate({shading.SHADING_NORMAL_CHANNEL: fit.config.lr_normal})
    state.channels[shading.SHADING_NORMAL_CHANNEL] = opt[shading.SHADING_NORMAL_CHANNEL]


# A shading normal this far (degrees) from its surfel's rotation normal was set by stage 2's
# planes (every other surfel's is a float32 copy of its rotation normal).
FLATTENED_MIN_DEG = 0.1


def _start_normals(fit: MaterialFit) -> tuple[mi.Vector3f, mi.Bool]:
    """The surfels' unit shading normals [N] as stage 2 left them (the prior's n0) and
    which of them the phase holds (``normal_hold_planar``: those stage 2 flattened)."""
    if fit.start_normals is None:
        with dr.suspend_grad():
            n0 = shading.shading_normals(fit.surfels)  # unit
            held = dr.zeros(mi.Bool, fit.surfels.count)
            if fit.config.normal_hold_planar and \
                    shading.SHADING_NORMAL_CHANNEL in fit.surfels.channels:
                own = fit.surfels.tangent_frame()[2]
                held = dr.abs(dr.dot(n0, own)) < math.cos(math.radians(FLATTENED_MIN_DEG))
            dr.eval(n0, held)
        fit.start_normals, fit.held_normals = n0, held
    return fit.start_normals, fit.held_normals


def with_surfel_normals(view: TrainView, normals: mi.Vector3f, position: mi.Point3f
                        ) -> TrainView:
    """``view`` with its pixel normals blended from per-surfel ``normals`` [N] (facing its
    camera, as the rasterizer flips them) over the pairs its receivers blend (the median
    surface's, with ``receiver_band``): differentiable in ``normals``; points, depth and
    the shadow-map lookups stay the view's."""
    from mi_shadowgs.core.raster import face_camera

    n = dr.width(normals)
    facing = face_camera(normals, position, view.camera)
    pairs = view.geom.surface_pairs or view.pairs
    flat = shading.splat(pairs, mi.TensorXf(dr.ravel(facing), (n, 3)))  # [H * W * 3]
    pn = shading.unit_or_zero(mi.Vector3f(*(shading.channel(flat, 3, k) for k in range(3))))
    return dataclasses.replace(view, geom=dataclasses.replace(view.geom, normal=pn))


# Memory for the normal phase's held per-view maps (8 floats a pixel: 33 MB for cpu-small's 64
# views at 128^2); views beyond it make theirs at each step.
HELD_MAPS_BYTES = 256 << 20


def _held_view_maps(fit: MaterialFit, state: MaterialState, k: int) -> tuple:
    """View ``k``'s ``view_maps`` of the held materials, made once while they fit."""
    if k in fit.held_maps:
        return fit.held_maps[k]
    v = fit.views[k]
    with dr.suspend_grad():
        maps = view_maps(v.pairs, state.channels, v.surfel_normal, state.specular)
        dr.eval(*(m for m in maps if m is not None))
    if (len(fit.held_maps) + 1) * 32 * v.pairs.height * v.pairs.width <= HELD_MAPS_BYTES:
        fit.held_maps[k] = maps
    return maps


def normal_step(fit: MaterialFit, state: MaterialState) -> float | None:
    """One step of the normal phase: Eq. 18's loss over ``views_per_step`` random views with
    the pixel normals blended from the shading-normal channel, plus the prior toward stage
    2's normals; everything else held. Returns as ``fit_step``."""
    config, opt = fit.config, state.opt
    w_light = dr.detach(dr.exp(opt["log_light"])) * solid_angle(config.n_directions)
    lights = shading.LightSet(state.directions, mi.Color3f(w_light, w_light, w_light))
    start, held = _start_normals(fit)
    free = shading.unit_rows(opt[shading.SHADING_NORMAL_CHANNEL])  # [N]
    normals = dr.select(held, start, free)
    position = dr.detach(fit.surfels.position)
    total = mi.Float(0.0)
    for _ in range(config.views_per_step):
        k = int(state.rng.integers(len(fit.views)))
        v = fit.views[k]
        # The lookup keeps the view's own normals: its offset is part of the occluder test.
        vis = None if fit.maps is None else \
            fit.maps.evaluate(v.geom.points, v.geom.normal, v.geom.footprint)
        total += view_loss(with_surfel_normals(v, normals, position), state.channels, lights,
                           vis, config, state.specular, _held_view_maps(fit, state, k))
    total = total / config.views_per_step
    prior = config.lambda_normal_prior * dr.mean(1.0 - dr.dot(normals, start))
    dr.backward(total + prior)
    opt.step()
    state.channels[shading.SHADING_NORMAL_CHANNEL] = opt[shading.SHADING_NORMAL_CHANNEL]
    return _count_step(state, config, total)


def fit_result(fit: MaterialFit, state: MaterialState) -> MaterialResult:
    """The fitted model: the input geometry with the material channels, and the light map
    over the grid (each light at its nearest grid direction, as the dataset builds the
    ground-truth map from its directional lights)."""
    config, surfels, ch = fit.config, fit.surfels, state.channels
    light = np.exp(state.opt["log_light"].numpy().astype(np.float64))
    active = nearest_grid_index(state.directions, light_grid(config.n_directions))
    radiance = np.zeros(config.n_directions)
    np.add.at(radiance, active, light)
    out = surfels.with_channels({k: mi.TensorXf(dr.detach(ch[k].array), ch[k].shape)
                                 for k in ("albedo", "roughness", "metallic",
                                           shading.INDIRECT_CHANNEL)})
    if DETAIL_CHANNEL in ch:  # the detailed albedo, which relighting and export read
        a = detailed_albedo(ch["albedo"], ch[DETAIL_CHANNEL])
        out = out.with_channels({"albedo": mi.TensorXf(dr.detach(a.array), a.shape)})
    if shading.SHADING_NORMAL_CHANNEL in ch:  # the normal phase's, as unit vectors
        start, held = _start_normals(fit)
        free = shading.unit_rows(ch[shading.SHADING_NORMAL_CHANNEL])
        n = dr.detach(dr.select(held, start, free))
        out = out.with_channels({shading.SHADING_NORMAL_CHANNEL:
                                 mi.TensorXf(dr.ravel(n), (surfels.count, 3))})
    return MaterialResult(out, LightModel(radiance, active, state.directions,
                                          light * solid_angle(config.n_directions)),
                          state.specular, config.use_visibility, state.history,
                          dict(state.timings), list(state.light_log))


def fit_material(surfels: Surfels, cameras: list[Camera], images: list[np.ndarray],
                 masks: list[np.ndarray], config: MaterialConfig, bounds: SceneBounds,
                 vis_config: VisibilityConfig = DEFAULT_VISIBILITY,
                 raster: RasterConfig = DEFAULT_RASTER, progress: bool = True,
                 state: MaterialState | None = None, on_checkpoint=None) -> MaterialResult:
    """Fit materials, light map and indirect light to the training views (the loop over
    ``setup_fit``, ``end_warmup``, ``prune_due``/``refine_lights``, ``fit_step``, then the
    normal phase's ``start_normal_phase`` and ``normal_step``, and ``fit_result``).

    ``state`` (``MaterialState.from_checkpoint``) continues an interrupted fit;
    ``on_checkpoint(state)`` is called every ``checkpoint_every`` steps, every
    ``checkpoint_seconds``, at the end and at SIGINT/SIGTERM (``mi_shadowgs.io.interrupt``).
    """
    from tqdm import tqdm

    from mi_shadowgs.io.interrupt import CheckpointClock, raise_pending

    clock = CheckpointClock(config.checkpoint_every, config.checkpoint_seconds)
    fit, state = setup_fit(surfels, cameras, images, masks, config, bounds, vis_config,
                           raster, progress, state)
    total_steps = config.iterations + config.normal_steps
    bar = tqdm(total=total_steps, initial=state.step, desc="stage 4: fit",
               disable=not progress)
    t_phase = time.perf_counter() - state.timings.pop("phase_s", 0.0)
    refine_again = refine_step(config)
    main_phase = "main_s" if config.iterations > config.warmup else "warmup_total_s"

    def save() -> None:
        state.timings["phase_s"] = time.perf_counter() - t_phase
        on_checkpoint(state)
        del state.timings["phase_s"]
        clock.saved()

    def refined_one() -> None:
        """After each unit of a refinement: a refinement can take minutes."""
        if on_checkpoint and clock.due():
            save()
        raise_pending(f"stage 4 stopped in the light refinement of step {state.step + 1}"
                      + (", checkpoint written" if on_checkpoint else ""))

    with bar, clock.running():
        while state.step < total_steps:
            it = state.step
            if it >= config.iterations:  # the normal phase
                if shading.SHADING_NORMAL_CHANNEL not in state.opt.keys():
                    dr.sync_thread()
                    state.timings[main_phase] = time.perf_counter() - t_phase
                    start_normal_phase(fit, state)
                    t_phase = time.perf_counter()
                mean = normal_step(fit, state)
            elif it == config.warmup:
                if state.refine is None:  # else this step resumes inside its refinement
                    dr.sync_thread()
                    state.timings["warmup_total_s"] = time.perf_counter() - t_phase
                end_warmup(fit, state, refined_one)
                t_phase = time.perf_counter()
            else:
                if state.refine is None and prune_due(config, it):
                    # A host read every prune_every steps (not per step): drop dark lights.
                    n_before = len(state.directions)
                    state.directions, fit.maps = _prune(state.opt, state.directions,
                                                        fit.maps, config, fit.shadow_maps)
                    if len(state.directions) != n_before:
                        state.log_lights("prune", solid_angle(config.n_directions))
                if it == refine_again:
                    refine_lights(fit, state, refined_one)
            if it == detail_step(config) and DETAIL_CHANNEL not in state.channels:
                start_detail(fit, state)
            if it < config.iterations:
                mean = fit_step(fit, state)
            if mean is not None:
                bar.set_postfix(loss=f"{mean:.4f}", dirs=len(state.directions),
                                spec=int(state.specular))
            bar.update(1)
            if on_checkpoint and (clock.due(state.step) or state.step in
                                  (config.iterations, total_steps)):
                save()
            raise_pending(f"stage 4 stopped at step {state.step} of {total_steps}"
                          + (", checkpoint written" if on_checkpoint else ""))
    dr.sync_thread()
    state.timings["normals_s" if config.normal_steps else main_phase] = \
        time.perf_counter() - t_phase
    return fit_result(fit, state)


def _initial_state(surfels: Surfels, images: list[np.ndarray], views: list[TrainView], seg,
                   n_seg: int, config: MaterialConfig) -> MaterialState:
    """Step 0: initial channels, the light on every grid direction, Adam over them."""
    ch = init_channels(surfels, config)
    with_specular = config.specular != "off"
    if not with_specular:
        ch["metallic"] = mi.TensorXf(dr.zeros(mi.Float, surfels.count), (surfels.count, 1))
    _clamp_channels(ch, seg, n_seg, config, with_specular)
    opt = mi.ad.Adam(lr=config.lr_albedo)
    opt["albedo"] = ch["albedo"]
    opt.set_learning_rate({"albedo": config.lr_albedo})
    # The indirect light (per-surfel RGB) joins after the warm-up: fitted from the start it
    # explains colour and shadows per surfel before the segment-constant albedo and the
    # light map can (measured on the tiny test scene: albedo ratio stuck at 1).
    if with_specular:
        for k in ("roughness", "metallic"):
            opt[k] = ch[k]
            opt.set_learning_rate({k: config.lr_material})
    light0 = config.light_init
    if light0 <= 0:
        sup = [np.asarray(im, np.float64).reshape(-1, np.shape(im)[-1])[:, :3]
               [np.asarray(v.weight.numpy(), bool)] for im, v in zip(images, views, strict=True)]
        light0 = max(float(np.mean(np.concatenate(sup))), 1e-3) / config.albedo_init
    grid = light_grid(config.n_directions)
    opt["log_light"] = mi.Float(np.full(len(grid), math.log(light0), np.float32))
    opt.set_learning_rate({"log_light": config.lr_light})
    return MaterialState(0, opt, ch, grid, with_specular, np.random.default_rng(config.seed),
                         mi.Float(0.0), [], {})


def _end_warmup(state: MaterialState, config: MaterialConfig) -> None:
    """After the warm-up's pruning and refinement: add the indirect light and decide on the
    specular lobe (one host read)."""
    opt, ch = state.opt, state.channels
    opt[shading.INDIRECT_CHANNEL] = ch[shading.INDIRECT_CHANNEL]
    opt.set_learning_rate({shading.INDIRECT_CHANNEL: config.lr_indirect})
    if state.specular and config.specular == "auto":
        m = opt["metallic"].numpy().reshape(-1)
        r = opt["roughness"].numpy().reshape(-1)
        if m.max() < config.auto_metallic_max and r.min() > config.auto_roughness_min:
            state.specular = False
            for k in ("roughness", "metallic"):
                del opt[k]
            n = len(m)
            ch["metallic"] = mi.TensorXf(dr.zeros(mi.Float, n), (n, 1))
