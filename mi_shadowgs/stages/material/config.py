"""Stage 4's settings: ``MaterialConfig`` with its checks, the presets, and the settings
that segments labelled from chromaticity change (``label_source_overrides``)."""

from __future__ import annotations

import dataclasses
import math

from mi_shadowgs.config import LABEL_MAP_SOURCES, get_preset

SPECULAR_MODES = ("auto", "on", "off")
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
