"""Independent float64 NumPy reference of the 2DGS rasterizer maths (no Dr.Jit).

Written from the maths, not from mi_shadowgs.core.raster: rays come from ``Camera.unproject``,
the ray-splat intersection is a plain world-space ray-plane hit, rotations come from
SciPy, and there is no bounding box or pair list (every pixel meets every surfel; the
``cutoff_sigma`` test is a per-pair threshold). Compositing is vectorised over pixels.

``render`` also returns ``unsure`` [H, W]: pixels where some pair sits within a relative
``margin`` of a discrete threshold (alpha_min, the cutoff, the near plane, the
rho3d/rho2d switch, the transmittance stop, T = 0.5 for the median, equal centre depths).
There float32 and float64 may legitimately take different branches, so tests skip them.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def sigmoid(x):
    with np.errstate(over="ignore"):
        return 1.0 / (1.0 + np.exp(-x))


def frames(quat_wxyz):  # [N, 4] -> three [N, 3] world axes (t_u, t_v, normal)
    q = np.asarray(quat_wxyz, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1)
    q = np.where(norm[:, None] > 1e-15, q, np.array([1.0, 0.0, 0.0, 0.0]))
    m = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # SciPy is scalar-last
    return m[:, :, 0], m[:, :, 1], m[:, :, 2]


def render(camera, position, log_scale, rotation, opacity_logit, colors, cfg, margin=1e-4,
           surface_band=None):
    """Images of the raw parameters (float64 numpy) seen by ``camera``.

    position [N, 3]; log_scale [N, 2]; rotation [N, 4] wxyz; opacity_logit [N];
    colors [N, C]; ``cfg`` a RasterConfig (only its numbers are read).
    Returns dict: color [H, W, C], alpha, depth, median_depth, distortion [H, W],
    normal [H, W, 3], count [H, W], unsure [H, W] bool. With ``surface_band`` also the
    receivers on the median surface (``shading.surface_aovs``): surface_depth [H, W],
    surface_normal [H, W, 3], surface_unsure [H, W] bool, and reordered [H, W] bool (the
    pixel's pairs lie in another order along its ray than in compositing order).
    """
    H, W = camera.height, camera.width
    p = np.asarray(position, np.float64)
    scale = np.exp(np.asarray(log_scale, np.float64))
    opac = sigmoid(np.asarray(opacity_logit, np.float64))
    colors = np.asarray(colors, np.float64)
    t_u, t_v, nrm = frames(rotation)

    pix = camera.pixel_grid()  # [M, 2]
    fwd = camera.forward
    if camera.is_ortho:
        ray_o = camera.unproject(pix, np.zeros(len(pix)))
        ray_d = np.broadcast_to(fwd, ray_o.shape)
        view = np.broadcast_to(fwd, p.shape)
    else:
        ray_o = np.broadcast_to(camera.origin, (len(pix), 3))
        ray_d = camera.unproject(pix, np.ones(len(pix))) - camera.origin
        view = p - camera.origin
    centre_px, centre_z = camera.project(p)  # [N, 2], [N]

    # Ray-plane hit for every (pixel, surfel): [M, N].
    rel = p[None, :, :] - ray_o[:, None, :]  # [M, N, 3]
    num = np.einsum("mnk,nk->mn", rel, nrm)
    den = np.einsum("mk,nk->mn", ray_d, nrm)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
        hit = ray_o[:, None, :] + t[..., None] * ray_d[:, None, :] - p[None]  # hit - centre
        u = np.einsum("mnk,nk->mn", hit, t_u) / scale[None, :, 0]
        v = np.einsum("mnk,nk->mn", hit, t_v) / scale[None, :, 1]
        rho3d = np.where(den != 0, u * u + v * v, np.inf)
    rho3d = np.nan_to_num(rho3d, nan=np.inf)
    hit_depth = np.einsum("mnk,k->mn", ray_o[:, None, :] + t[..., None] * ray_d[:, None, :]
                          - camera.origin, fwd)
    d2 = np.sum((pix[:, None, :] - centre_px[None]) ** 2, axis=-1)
    rho2d = cfg.lowpass_inv_var * d2
    use3d = rho3d <= rho2d
    rho = np.minimum(rho3d, rho2d)
    depth = np.where(use3d, hit_depth, centre_z[None, :])
    alpha = np.minimum(cfg.alpha_max, opac[None] * np.exp(-0.5 * rho))
    k2 = cfg.cutoff_sigma ** 2
    surf_ok = (centre_z >= cfg.near) & (scale.min(axis=1) > cfg.scale_min)
    keep = (alpha >= cfg.alpha_min) & (rho <= k2) & (depth >= cfg.near) & surf_ok[None]

    def near_thr(x, thr):
        return np.abs(x - thr) <= margin * max(abs(thr), 1e-12)

    unsure = np.zeros(len(pix), bool)
    live = surf_ok[None] & np.isfinite(rho)
    unsure |= np.any(live & (near_thr(alpha, cfg.alpha_min) | near_thr(rho, k2)
                             | near_thr(depth, cfg.near)), axis=1)
    unsure |= np.any(live & (rho < k2 * 1.1) & np.isfinite(rho3d)
                     & (np.abs(rho3d - rho2d) <= margin * np.maximum(rho2d, 1e-6)), axis=1)

    # Front to back by centre depth (stable: ties keep surfel order).
    order = np.argsort(centre_z, kind="stable")
    a = np.where(keep, alpha, 0.0)[:, order]
    dep = depth[:, order]
    T = np.cumprod(np.concatenate([np.ones((len(pix), 1)), 1.0 - a[:, :-1]], axis=1), axis=1)
    T_after = T * (1.0 - a)
    contrib = keep[:, order] & (T_after >= cfg.transmittance_min)
    # Once a pair fails the transmittance test the pixel is finished (2DGS "done").
    contrib &= np.cumsum(keep[:, order] & ~contrib, axis=1) == 0
    w = np.where(contrib, T * a, 0.0)
    unsure |= np.any(keep[:, order] & near_thr(T_after, cfg.transmittance_min), axis=1)
    unsure |= np.any(contrib & near_thr(T, 0.5), axis=1)

    # Two pairs of a pixel whose centre depths agree to float32 precision (2.5 ulps,
    # 3e-7 relative, as Dr.Jit computes z in float32) may be composited in either order;
    # only pairs up to the transmittance stop matter.
    kept = keep[:, order]
    upto = kept & (np.cumsum(kept & ~contrib, axis=1) <= 1)
    zk = np.where(upto, centre_z[order][None, :], np.nan)
    for i in range(len(pix)):
        zi = zk[i][~np.isnan(zk[i])]
        if len(zi) > 1 and np.min(np.diff(zi)) <= 3e-7 * np.abs(zi).max():
            unsure[i] = True

    out = {}
    out["color"] = (w @ colors[order]).reshape(H, W, -1)
    alpha_img = w.sum(axis=1)
    out["alpha"] = alpha_img.reshape(H, W)
    with np.errstate(invalid="ignore", divide="ignore"):
        out["depth"] = np.where(alpha_img > 0, (w * dep).sum(1) / alpha_img, 0.0).reshape(H, W)
    med = np.zeros(len(pix))
    for i in range(len(pix)):
        idx = np.nonzero(contrib[i] & (T[i] > 0.5))[0]
        if len(idx):
            med[i] = dep[i, idx[-1]]
    out["median_depth"] = med.reshape(H, W)
    flip = np.where(np.sum(nrm * view, axis=1) > 0, -1.0, 1.0)
    out["normal"] = (w @ (nrm * flip[:, None])[order]).reshape(H, W, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.where(contrib, cfg.distortion_far / (cfg.distortion_far - cfg.distortion_near)
                     * (1.0 - cfg.distortion_near / dep), 0.0)
    # sum_{j < i} w_i w_j (m_i - m_j)^2, the 2DGS depth distortion, by exclusive sums.
    excl = np.cumsum(w, axis=1) - w
    m1 = np.cumsum(w * m, axis=1) - w * m
    m2 = np.cumsum(w * m * m, axis=1) - w * m * m
    out["distortion"] = np.sum(w * (m * m * excl + m2 - 2 * m * m1), axis=1).reshape(H, W)
    out["count"] = contrib.sum(axis=1).reshape(H, W).astype(np.float64)
    out["unsure"] = unsure.reshape(H, W)
    if surface_band is not None:
        facing = (nrm * flip[:, None])[order]
        out.update(_surface(camera, w, dep, facing, surface_band, margin, H, W))
    out["_structure"] = (keep, use3d & keep, contrib, contrib & (T > 0.5))
    return out


def _surface(camera, w, dep, facing, band, margin, H, W):
    """Per pixel: the weights summed along the ray (pairs sorted by their hit depth) reach
    0.5 at the median pair (the last pair where they never do); the pairs whose depth lies
    within ``band`` pixel footprints of the median's are blended with their weights."""
    depth = np.zeros(len(w))
    normal = np.zeros((len(w), 3))
    unsure = np.zeros(len(w), bool)
    reordered = np.zeros(len(w), bool)
    for i in range(len(w)):
        live = np.nonzero(w[i] > 0)[0]
        if not len(live):
            continue
        by_ray = live[np.argsort(dep[i, live], kind="stable")]
        reordered[i] = not np.array_equal(by_ray, live)
        cum = np.cumsum(w[i, by_ray])
        k = int(np.argmax(cum >= 0.5)) if cum[-1] >= 0.5 else len(by_ray) - 1
        z_med = dep[i, by_ray[k]]
        foot = camera.ortho_width / camera.width if camera.is_ortho else z_med / camera.focal
        reach = band * foot
        gap = np.abs(dep[i, live] - z_med)
        near = live[gap <= reach]
        depth[i] = np.sum(w[i, near] * dep[i, near]) / np.sum(w[i, near])
        normal[i] = w[i, near] @ facing[near]
        # float32 may take the other branch: a sum at 0.5, a gap at the band's edge, or
        # two hits at (nearly) the same depth, whose order along the ray is then a tie.
        zs = np.sort(dep[i, live])
        unsure[i] = np.any(np.abs(cum - 0.5) <= margin) or \
            np.any(np.abs(gap - reach) <= margin * max(reach, 1e-12)) or \
            (len(zs) > 1 and np.min(np.diff(zs)) <= 1e-5 * abs(zs).max())
    return {"surface_depth": depth.reshape(H, W), "surface_normal": normal.reshape(H, W, 3),
            "surface_unsure": unsure.reshape(H, W), "reordered": reordered.reshape(H, W)}


def structure_equal(a, b) -> bool:
    """Whether two renders made the same discrete choices (for finite differences)."""
    return all(np.array_equal(x, y) for x, y in zip(a["_structure"], b["_structure"],
                                                    strict=True))


# -- scenes shared by the rasterizer tests ------------------------------------------------
def random_scene(n, seed, extent=0.5, scale=(0.05, 0.25), opacity=(0.2, 0.95), channels=3):
    """Raw float32-representable parameters of a random scene (as float64 numpy)."""
    rng = np.random.default_rng(seed)
    raw = {
        "position": rng.uniform(-extent, extent, (n, 3)),
        "log_scale": np.log(rng.uniform(*scale, (n, 2))),
        "rotation": rng.normal(size=(n, 4)),
        "opacity_logit": np.log(1 / rng.uniform(*opacity, n) - 1) * -1.0,
        "colors": rng.uniform(0.0, 1.0, (n, channels)),
    }
    return {k: v.astype(np.float32).astype(np.float64) for k, v in raw.items()}


def to_surfels(raw):
    """Dr.Jit Surfels holding exactly the raw parameters (float32)."""
    import mitsuba as mi

    from mi_shadowgs.core.surfels import Surfels

    def cols(a):
        return [np.ascontiguousarray(a[:, i], dtype=np.float32) for i in range(a.shape[1])]

    return Surfels(position=mi.Point3f(*cols(raw["position"])),
                   log_scale=mi.Point2f(*cols(raw["log_scale"])),
                   rotation=mi.Vector4f(*cols(raw["rotation"])),
                   opacity_logit=mi.Float(raw["opacity_logit"].astype(np.float32)),
                   channels={"color": mi.TensorXf(raw["colors"].astype(np.float32))})


def reference(camera, raw, cfg, **kw):
    return render(camera, raw["position"], raw["log_scale"], raw["rotation"],
                  raw["opacity_logit"], raw["colors"], cfg, **kw)
