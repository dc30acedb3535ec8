"""Render a shadowed synthetic dataset: path-traced images plus exact ground-truth buffers.

Pure functions over a loaded scene (``scene.load_scene``) and cameras; the files are the
writer's business (``writer.py``) and the command line is ``generate_cli.py``.

Speed: one sensor is reused for every view and only its ``to_world`` changes (through
``mi.traverse``), so Mitsuba compiles the path-tracing kernel once; the ground-truth buffers
of many views come from one ``ray_intersect``/``ray_test`` kernel over all their pixels.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.directions import direction_from_angles
from mi_shadowgs.core.envmap import load_envmap
from mi_shadowgs.dataset.layout import NERF_CAMERA_ANGLE_X
from mi_shadowgs.dataset.scene import Light, SceneSetup

# Relighting setups that differ from the training lights (azimuth, elevation, irradiance).
DEFAULT_RELIGHT = (
    ("sun_high", ((120.0, 70.0, 3.0),)),
    ("sun_low", ((300.0, 20.0, 3.0),)),
    ("pair_cross", ((125.0, 40.0, 2.0), (305.0, 55.0, 1.5))),
)


@dataclasses.dataclass(frozen=True)
class SkyConfig:
    """A procedural sky-and-sun env map (lat-long, Y-up), built in code so that every
    dataset has an env-map relit test set without an external file (TensoIR's relighting
    protocol is env maps). Radiance in linear RGB; the sun is a uniform disc."""

    width: int = 256  # lat-long pixels: 1.4 degrees each, so the sun disc spans ~6 pixels
    height: int = 128
    sun_azimuth_deg: float = 250.0  # away from every training and relighting direction
    sun_elevation_deg: float = 45.0
    sun_radius_deg: float = 4.0
    sun_irradiance: float = 2.0  # W/m^2 at normal incidence, white
    zenith: tuple = (0.10, 0.16, 0.32)  # sky radiance at the zenith
    horizon: tuple = (0.32, 0.36, 0.42)  # and at the horizon (a bluish gradient)
    ground: tuple = (0.05, 0.05, 0.05)  # below the horizon (hidden by the base's plane)


def sky_envmap_image(sky: SkyConfig) -> np.ndarray:
    """The sky as a Mitsuba ``envmap`` image [height, width, 3] (float32, linear RGB).

    Mitsuba's lat-long map: pixel (u, v) looks along theta = pi v from +Y and
    atan2(x, -z) = 2 pi u, so with our azimuth (about +Y, from +X toward -Z) a direction of
    azimuth az sits at u = (90 deg - az) / 360 deg.
    """
    v = (np.arange(sky.height) + 0.5) / sky.height
    u = (np.arange(sky.width) + 0.5) / sky.width
    theta = np.pi * v[:, None] * np.ones_like(u)[None]  # [H, W] from +Y
    az = np.pi / 2 - 2 * np.pi * u[None] * np.ones_like(v)[:, None]
    d = np.stack([np.sin(theta) * np.cos(az), np.cos(theta), -np.sin(theta) * np.sin(az)], -1)
    up = np.clip(d[..., 1], 0.0, 1.0)[..., None]  # [H, W, 1]
    t = np.sqrt(up)  # the sky darkens quickly towards the zenith, as a clear sky does
    img = (1 - t) * np.array(sky.horizon) + t * np.array(sky.zenith)
    img = np.where(d[..., 1:2] < 0, np.array(sky.ground), img)
    sun = direction_from_angles(sky.sun_azimuth_deg, sky.sun_elevation_deg)
    cos_r = np.cos(np.radians(sky.sun_radius_deg))
    disc_solid_angle = 2 * np.pi * (1 - cos_r)
    in_sun = (d @ sun) >= cos_r
    img[in_sun] += sky.sun_irradiance / disc_solid_angle
    return img.astype(np.float32)


SAMPLERS = ("multijitter", "independent", "stratified", "ldsampler", "orthogonal")


def render_passes(spp: int, pass_spp: int | None) -> tuple[int, int]:
    """(samples per pass, passes) of ``spp`` samples per pixel rendered in passes of
    ``pass_spp`` (None, or more than spp: one pass); ValueError unless they divide evenly."""
    per = min(pass_spp or spp, spp)
    if per < 1 or spp % per:
        raise ValueError(f"dataset generation: spp={spp} must be at most pass_spp="
                         f"{pass_spp} or a multiple of it")
    return per, spp // per


@dataclasses.dataclass(frozen=True)
class GenerateConfig:
    """Dataset generation settings; defaults are the paper preset (TensoIR-like)."""

    width: int = 800
    height: int = 800
    n_train: int = 100
    n_test: int = 200
    spp: int = 256  # path-traced samples per pixel
    # Mitsuba's pixel sampler (one of SAMPLERS), and the samples per pixel of one render
    # pass: spp / pass_spp passes with their own seeds are averaged. Stratified samples reach
    # a given noise with fewer paths than independent ones, and multijitter is cheap when
    # its grid is a power of two (64: 8 x 8; other counts take its permutation's rejection
    # loop, 1.5-2x slower per sample; docs/decisions.md, "Two multi-jittered passes").
    # An spp up to pass_spp is one pass. The count per pass must be one the
    # sampler takes as is (``check_sampler``: multijitter rounds 128 up to 132).
    sampler: str = "multijitter"
    pass_spp: int = 64
    max_depth: int = 5  # path length limit: up to 3 indirect bounces after direct light
    camera_angle_x: float = NERF_CAMERA_ANGLE_X  # radians, as NeRF-synthetic
    # The object has radius 1 and the base half-size 1.6: at 5 units the whole base usually
    # fits in the frame with background around it, so the masks constrain the geometry
    # (as in the paper's data, where the object and its base are masked out).
    camera_distance: float = 5.0
    train_elevation_deg: tuple = (5.0, 85.0)  # upper hemisphere, not grazing the base
    test_elevation_deg: tuple = (15.0, 60.0)  # spiral bounds
    relight: tuple = DEFAULT_RELIGHT  # (name, ((az, el, irradiance), ...)) setups
    # Env maps of the env-map relit test sets (TensoIR's relighting protocol): "auto" (the
    # shipped maps of ``assets.shipped_envmaps()`` when present, else the procedural sky),
    # "sky", "none", or a tuple of entries, each "sky", "auto" or an env-map path. Each map
    # adds n_test path-traced views and its scoring in ``run``.
    envmaps: str | tuple = "auto"
    # The procedural sky that "sky" (and "auto" without shipped maps) renders (None: none).
    sky: SkyConfig | None = SkyConfig()
    envmap_scale: float = 1.0
    gt_chunk_rays: int = 1 << 22  # rays per ground-truth kernel launch (memory bound)

    def __post_init__(self):
        if self.sampler not in SAMPLERS:
            raise ValueError(f"dataset generation: sampler must be one of {SAMPLERS}, got "
                             f"{self.sampler!r}")
        if self.pass_spp < 1:
            raise ValueError(f"dataset generation: pass_spp must be >= 1, got {self.pass_spp}")
        render_passes(self.spp, self.pass_spp)

    @property
    def samples_per_pass(self) -> int:
        return render_passes(self.spp, self.pass_spp)[0]


def relight_lights(config: GenerateConfig) -> list[tuple[str, list[Light]]]:
    """The directional relighting setups of ``config`` as Light lists."""
    out = []
    for name, specs in config.relight:
        lights = []
        for k, (az, el, e) in enumerate(specs):
            d = direction_from_angles(az, el)
            lights.append(Light(f"light{k}", tuple(d.tolist()), (float(e),) * 3, float(az),
                                float(el)))
        out.append((name, lights))
    return out


# -- ground truth -----------------------------------------------------------------------
def camera_rays(cameras: list[Camera], offset: tuple[float, float] = (0.5, 0.5)
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One ray per pixel of all cameras, through the point ``offset`` (x, y in [0, 1) of the
    pixel; (0.5, 0.5): its centre): origins [M, 3], unit directions [M, 3], and each
    camera's forward axis per ray [M, 3] (for z-depth), in view-major, row-major order."""
    origins, dirs, fwd = [], [], []
    shift = np.asarray(offset, np.float64) - 0.5
    for cam in cameras:
        pix = cam.pixel_grid() + shift  # [H*W, 2]
        far = cam.unproject(pix, np.ones(len(pix)))  # points at z-depth 1
        if cam.is_ortho:
            o = cam.unproject(pix, np.zeros(len(pix)))
            d = np.broadcast_to(cam.forward, o.shape)
        else:
            o = np.broadcast_to(cam.origin, far.shape)
            d = far - o
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        origins.append(o)
        dirs.append(d)
        fwd.append(np.broadcast_to(cam.forward, d.shape))
    return np.concatenate(origins), np.concatenate(dirs), np.concatenate(fwd)


LAMP_SAMPLES = 16  # points on a sphere lamp's disc for its soft visibility


def _disc_points(count: int) -> np.ndarray:
    """[count, 2] points evenly spread over the unit disc (Vogel's sunflower), each the
    centre of an equal area."""
    k = np.arange(count) + 0.5
    r = np.sqrt(k / count)
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi)], -1)


def _lamp_terms(scene, si, n, valid, light, samples: int):
    """(hard visibility, soft visibility, irradiance [RGB]) of a lamp ``Light`` at the
    interactions ``si`` (normals ``n``): shadow rays to its centre, and to ``samples``
    points of the disc of its radius across the direction to it."""
    import drjit as dr
    import mitsuba as mi

    centre = mi.Point3f(*light.position)
    to = centre - si.p
    dist2 = dr.squared_norm(to)
    l_dir = to * dr.rsqrt(dist2)
    hard = valid & ~scene.ray_test(si.spawn_ray_to(centre), valid)
    v_hard = dr.select(hard, 1.0, 0.0)
    if light.radius > 0 and samples > 0:
        e1, e2 = mi.coordinate_system(l_dir)
        v_soft = dr.zeros(mi.Float, dr.width(valid))
        for a, b in _disc_points(samples) * light.radius:
            target = centre + float(a) * e1 + float(b) * e2
            seen = valid & ~scene.ray_test(si.spawn_ray_to(target), valid)
            v_soft += dr.select(seen, 1.0 / samples, 0.0)
    else:
        v_soft = v_hard
    cos = dr.maximum(dr.dot(n, l_dir), 0.0)
    falloff = light.distance**2 / dist2
    irr = mi.Color3f(*light.irradiance) * dr.select(valid, cos * falloff * v_soft, 0.0)
    return v_hard, v_soft, irr


def trace_ground_truth(setup: SceneSetup, cameras: list[Camera],
                       lights: list[Light] | None = None,
                       chunk_rays: int = 1 << 22,
                       offset: tuple[float, float] = (0.5, 0.5),
                       lamp_samples: int = LAMP_SAMPLES) -> dict[str, np.ndarray]:
    """Exact per-pixel buffers at pixel centres for each camera (all the same size); at
    the point ``offset`` of each pixel instead when given (``camera_rays``).

    Returns [N, H, W, ...] arrays: ``albedo`` [3], ``normal`` [3] (unit, world, facing the
    camera), ``depth`` (z-depth, 0 on background), ``mask`` (object or base hit), ``object``
    (object parts hit), ``material`` (int32), ``visibility`` [L] (1 where the light's shadow
    ray is unoccluded), ``visibility_soft`` [L] (a sphere lamp's visible share: of
    ``lamp_samples`` points on its disc as the pixel sees it; the hard one for the other
    lights), ``irradiance`` [L, 3] = E * max(0, n . l) * V. A lamp's V is its soft
    visibility, its l points from the pixel to its centre, and its E falls off as 1 / r^2
    from the irradiance it gives at the object's centre: exact for a point lamp, and for a
    sphere wholly above the pixel's horizon that is unoccluded.
    """
    import drjit as dr
    import mitsuba as mi

    lights = setup.lights if lights is None else lights
    h, w = cameras[0].height, cameras[0].width
    if any((c.height, c.width) != (h, w) for c in cameras):
        raise ValueError("trace_ground_truth: all cameras must have the same image size")
    scene = setup.scene
    ids = setup.shape_material_ids()
    shape_ids = [(mi.ShapePtr(s), ids[s.id()]) for s in scene.shapes() if s.id() in ids]
    n_parts = len(setup.parts)
    views_per_chunk = max(1, chunk_rays // (h * w))
    out = {k: [] for k in ("albedo", "normal", "depth", "mask", "object", "material",
                           "visibility", "visibility_soft", "irradiance")}
    for v0 in range(0, len(cameras), views_per_chunk):
        o, d, f = camera_rays(cameras[v0:v0 + views_per_chunk], offset)
        ray = mi.Ray3f(mi.Point3f(*(o.T.astype(np.float32))),
                       mi.Vector3f(*(d.T.astype(np.float32))))
        si = scene.ray_intersect(ray)
        valid = si.is_valid()
        n = si.sh_frame.n
        n = dr.select(dr.dot(n, ray.d) > 0, -n, n)  # face the camera (open meshes)
        fwd = mi.Vector3f(*(f.T.astype(np.float32)))
        depth = dr.select(valid, si.t * dr.dot(ray.d, fwd), 0.0)
        albedo = dr.select(valid, si.bsdf().eval_diffuse_reflectance(si, valid), 0.0)
        mat = dr.zeros(mi.UInt32, dr.width(valid))
        for ptr, mid in shape_ids:
            mat = dr.select(valid & (si.shape == ptr), mid, mat)
        vis, soft, irr = [], [], []
        for lt in lights:
            if lt.is_lamp:
                v, vs, e = _lamp_terms(scene, si, n, valid, lt, lamp_samples)
                vis.append(v)
                soft.append(vs)
                irr.append(e)
                continue
            l_dir = mi.Vector3f(*lt.direction)
            occluded = scene.ray_test(si.spawn_ray(l_dir), valid)
            v = valid & ~occluded
            cos = dr.maximum(dr.dot(n, l_dir), 0.0)
            vis.append(dr.select(v, 1.0, 0.0))
            soft.append(vis[-1])
            irr.append(mi.Color3f(*lt.irradiance) * dr.select(v, cos, 0.0))
        dr.eval(n, depth, albedo, mat, vis, soft, irr)
        nv = len(cameras[v0:v0 + views_per_chunk])

        def arr(x, c=None, nv=nv):
            a = np.asarray(x, dtype=np.float32)
            a = a.T if a.ndim == 2 else a
            return a.reshape((nv, h, w) + ((c,) if c else ()))

        m = np.asarray(valid).reshape(nv, h, w)
        matv = np.asarray(mat).astype(np.int32).reshape(nv, h, w)
        out["mask"].append(m)
        out["object"].append((matv >= 1) & (matv <= n_parts))
        out["material"].append(matv)
        out["depth"].append(arr(depth))
        out["normal"].append(np.where(m[..., None], arr(n, 3), 0.0).astype(np.float32))
        out["albedo"].append(arr(albedo, 3))
        out["visibility"].append(np.stack([arr(v) for v in vis], -1) if vis else
                                 np.zeros((nv, h, w, 0), np.float32))
        out["visibility_soft"].append(np.stack([arr(v) for v in soft], -1) if soft else
                                      np.zeros((nv, h, w, 0), np.float32))
        out["irradiance"].append(np.stack([arr(e, 3) for e in irr], -2) if irr else
                                 np.zeros((nv, h, w, 0, 3), np.float32))
    return {k: np.concatenate(v) for k, v in out.items()}


def facing_lights(normal: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Whether each normal [..., 3] faces each light direction [L, 3] (n . l > 0, the
    horizon test of the truth's visibility): [..., L] bool."""
    return np.einsum("...k,lk->...l", np.asarray(normal, np.float64),
                     np.asarray(directions, np.float64)) > 0


def box_filtered_ground_truth(setup: SceneSetup, cameras: list[Camera],
                              lights: list[Light] | None = None, samples: int = 4
                              ) -> dict[str, np.ndarray]:
    """The albedo and irradiance a pixel-area sensor sees: ``trace_ground_truth`` at
    ``samples`` x ``samples`` stratified points of each pixel (the photos' box filter),
    averaged over the points that hit the scene. Returns [N, H, W, ...] arrays ``albedo``
    [3], ``irradiance`` [L, 3], ``lit`` [L] (the share of the points each light reaches:
    shadow ray unoccluded and n . l > 0; a light of zero irradiance reaches none),
    ``facing`` [L] (the share of the points whose normal faces each light, occluded or
    not), all 0 where no point hits, and ``coverage`` (the share of the points that hit).
    The dataset's buffers are point samples at the pixel centre; this is what a fit to the
    box-filtered photos can be held to (``validation.metric_floor``, ``validation.visibility``)."""
    if samples < 1:
        raise ValueError(f"box_filtered_ground_truth: samples must be >= 1, got {samples}")
    acc: dict[str, np.ndarray] = {}
    hits = None
    lights = setup.lights if lights is None else lights
    dirs = np.array([light.direction for light in lights], np.float64).reshape(-1, 3)  # [L, 3]
    for iy in range(samples):
        for ix in range(samples):
            g = trace_ground_truth(setup, cameras, lights,
                                   offset=((ix + 0.5) / samples, (iy + 0.5) / samples))
            hit = g["mask"].astype(np.float64)  # [N, H, W]
            hits = hit if hits is None else hits + hit
            g["lit"] = g["irradiance"].sum(axis=-1) > 0  # [N, H, W, L]
            g["facing"] = facing_lights(g["normal"], dirs)  # [N, H, W, L]
            for key, extra in (("albedo", 1), ("irradiance", 2), ("lit", 1), ("facing", 1)):
                w = hit.reshape(hit.shape + (1,) * extra)
                acc[key] = acc.get(key, 0.0) + g[key].astype(np.float64) * w
    n = samples * samples
    safe = np.maximum(hits, 1.0)
    return {"albedo": acc["albedo"] / safe[..., None],
            "irradiance": acc["irradiance"] / safe[..., None, None],
            "lit": acc["lit"] / safe[..., None],
            "facing": acc["facing"] / safe[..., None],
            "coverage": hits / n}


# -- path tracing -------------------------------------------------------------------------
def check_sampler(sampler: str, spp: int) -> None:
    """Raise ValueError unless Mitsuba's ``sampler`` takes ``spp`` samples per pixel as
    they are (it rounds some counts silently: multijitter 128 -> 132)."""
    import mitsuba as mi

    taken = mi.load_dict({"type": sampler, "sample_count": spp}).sample_count()
    if taken != spp:
        raise ValueError(f"dataset generation: the {sampler} sampler would take {taken} "
                         f"samples per pixel in a pass, not {spp}; choose a count it takes "
                         f"as is for spp (or pass_spp), e.g. 64")


class ViewRenderer:
    """Path-traces many views of a scene with one sensor, so the kernel is compiled once.
    Each view is the mean of spp / pass_spp passes (one when pass_spp is None or >= spp)."""

    def __init__(self, camera: Camera, spp: int, max_depth: int, hide_emitters: bool = True,
                 sampler: str = "multijitter", pass_spp: int | None = None):
        import mitsuba as mi

        self.spp, self.passes = render_passes(spp, pass_spp)  # self.spp: per pass
        check_sampler(sampler, self.spp)
        self.size = (camera.width, camera.height)
        self.sensor = mi.load_dict(camera.to_mitsuba_dict(spp=self.spp, sampler=sampler))
        self.params = mi.traverse(self.sensor)
        self.integrator = mi.load_dict({"type": "path", "max_depth": max_depth,
                                        "hide_emitters": hide_emitters})

    def render(self, scene, camera: Camera, seed: int) -> np.ndarray:
        """Linear RGBA [H, W, 4] (alpha: pixel coverage)."""
        import mitsuba as mi

        if (camera.width, camera.height) != self.size or camera.is_ortho:
            raise ValueError("ViewRenderer: every view needs the same perspective film size")
        self.params["to_world"] = mi.AffineTransform4f(camera.mitsuba_to_world())
        self.params["x_fov"] = math.degrees(camera.fov_x)
        self.params.update()
        img = 0.0
        for k in range(self.passes):  # pass 0 keeps the view's seed; the others their own
            img = img + np.asarray(mi.render(
                scene, sensor=self.sensor, integrator=self.integrator, spp=self.spp,
                seed=(seed + k * 0x9E3779B1) % (1 << 32)), dtype=np.float64)
        return (img / self.passes).astype(np.float32)


def lit_scene(setup: SceneSetup, lights: list[Light] | None = None,
              envmap: str | None = None, envmap_scale: float = 1.0):
    """The scene's shapes under other lighting: ``lights`` (directional, or lamps: a
    ``point`` emitter, or a ``sphere`` area emitter with a radius) or an env map."""
    import mitsuba as mi

    from mi_shadowgs.dataset.capture import lamp_emitter

    desc = {"type": "scene"}
    for s in setup.scene.shapes():
        desc[s.id() or f"shape{len(desc)}"] = s
    for lt in lights or []:
        if lt.is_lamp:
            desc[lt.name] = lamp_emitter(lt, area=True)
            continue
        desc[lt.name] = {"type": "directional", "direction": [-x for x in lt.direction],
                         "irradiance": {"type": "rgb", "value": list(lt.irradiance)}}
    if envmap is not None:
        desc["envmap"] = load_envmap(envmap, envmap_scale)
    return mi.load_dict(desc, optimize=False)
