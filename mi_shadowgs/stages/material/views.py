"""The training views: each view's fixed lookups (``prepare_view``), its per-pixel material
maps (``view_maps``) and the loss of Eq. 18 on it (``view_loss``)."""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowgs.core import jit, shading
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import RasterConfig
from mi_shadowgs.core.surfels import Surfels, eval_sh
from mi_shadowgs.stages.material.channels import DETAIL_CHANNEL, detailed_albedo, segment_ids
from mi_shadowgs.stages.material.config import MaterialConfig

DEFAULT_RASTER = RasterConfig()


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
                 receiver_band: float = 0.0, past=None) -> TrainView:
    """Pairs, geometry buffers and the target of one view (computed once: fixed geometry);
    ``receiver_band``: ``VisibilityConfig.receiver_band``; ``past``: a
    ``background.PastTheGround`` whose pixels are left out (None: none)."""
    h, w = camera.height, camera.width
    img = np.asarray(image, np.float32).reshape(h * w, -1)[:, :3]
    if receiver_band > 0:  # one pair list for the shading and the receivers
        with_depth = shading.splat_pairs_with_depth(surfels, camera, raster)
        pairs = shading.SplatPairs(*with_depth[:3], h, w)
    else:
        with_depth, pairs = None, shading.splat_pairs(surfels, camera, raster)
    geom = shading.pixel_geometry(surfels, camera, raster, receiver_band, with_depth)
    sup = np.asarray(mask, bool).reshape(-1) & (geom.alpha.numpy() >= config.mask_alpha)
    if past is not None:
        sup &= ~past.pixels(np.stack([geom.points[c].numpy() for c in range(3)], -1), img)
    weight = jit.host(sup.astype(np.float32))
    target = mi.Color3f(*(jit.host(img[:, c]) for c in range(3)))
    inv = dr.opaque(mi.Float, 1.0 / float(max(sup.sum(), 1)))
    seg, n_seg = pixel_segments(surfels, pairs, config.refine_segment_purity)
    return TrainView(camera, pairs, geom, weight, target, inv, seg, n_seg,
                     shading.facing_normals(surfels, camera))


def held_images(images: list[np.ndarray], gains: list[np.ndarray] | None
                 ) -> list[np.ndarray]:
    """Each training photo [H, W, 3+] divided by its view's RGB gain [3] from stage 1
    (``GeometryConfig.view_gains``): the photos as if taken with one exposure and white
    balance. ``images`` as they are without gains."""
    if gains is None:
        return images
    if len(gains) != len(images):
        raise ValueError(f"fit_material: {len(gains)} view gains for {len(images)} images")
    return [(np.asarray(im, np.float32)[..., :3] / np.asarray(g, np.float32)[None, None])
            for im, g in zip(images, gains, strict=True)]


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
    return jit.host(np.where(pure, top, n_seg).astype(np.uint32), mi.UInt32), n_seg


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
    albedo, rough, metal, ind = (maps if maps is not None else view_maps(
        view.pairs, channels, view.surfel_normal, with_specular, view.detail_gate))
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


def surfel_support(views: list[TrainView], n: int) -> np.ndarray:
    """Each surfel's blending weight summed over the supervised pixels of ``views`` [N]."""
    sup = dr.zeros(mi.Float, n)
    for v in views:
        w = v.pairs.weight * dr.gather(mi.Float, v.weight, v.pairs.pix)
        dr.scatter_reduce(dr.ReduceOp.Add, sup, w, v.pairs.sid)
    return sup.numpy().astype(np.float64)
