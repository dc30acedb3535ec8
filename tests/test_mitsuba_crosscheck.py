"""Cross-check with Mitsuba ray tracing: opaque surfels tangent to a sphere, rendered through
the ``surfel_raster`` plugin, against the analytic sphere traced by Mitsuba from the same
sensor (perspective and orthographic). This pins our camera conventions to Mitsuba's.

Run as a script to print the figures: ``python tests/test_mitsuba_crosscheck.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

import mi_shadowgs

mi_shadowgs.register_plugins()  # the sensor renders through surfel_raster

RADIUS = 1.0
CENTER = np.array([0.2, 1.0, -0.1])
ORIGIN = (1.5, 2.2, 3.2)
TARGET = (0.25, 0.97, -0.1)  # a little off the centre: no symmetry hides a flipped axis
W, H = 400, 380  # non-square; the sphere is ~160 px in radius and wholly in frame
N_SURFELS = 20000
SCALE_PER_SPACING = 1.5  # tangent std-dev in units of the mean surfel spacing
OPACITY_LOGIT = 8.0  # opacity 0.9997 (alpha is clamped to 0.99 anyway)
SENSORS = {
    "perspective": ('<float name="fov" value="36"/>', ""),
    "orthographic": ("", '<scale x="1.25" y="1.25"/>'),
}


def fibonacci_sphere(n: int) -> np.ndarray:
    """[n, 3] unit vectors, near-uniform on the sphere."""
    i = np.arange(n) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / n)
    azim = np.pi * (1.0 + 5.0**0.5) * i
    return np.stack([np.cos(azim) * np.sin(polar), np.cos(polar),
                     np.sin(azim) * np.sin(polar)], axis=-1)


def quat_z_to(normals: np.ndarray) -> np.ndarray:
    """[N, 4] (w, x, y, z) rotations taking +Z to ``normals`` [N, 3] (unit)."""
    z = np.array([0.0, 0.0, 1.0])
    q = np.concatenate([(1.0 + normals[:, 2])[:, None], np.cross(z, normals)], axis=-1)
    flip = q[:, 0] < 1e-8  # normal = -Z: any half-turn about a tangent axis
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def write_sphere_model(path) -> None:
    from mi_shadowgs.io import ply

    normals = fibonacci_sphere(N_SURFELS)
    spacing = np.sqrt(4.0 * np.pi * RADIUS**2 / N_SURFELS)
    model = ply.PlyModel(
        position=(CENTER + RADIUS * normals).astype(np.float32),
        log_scale=np.full((N_SURFELS, 2), np.log(SCALE_PER_SPACING * spacing), np.float32),
        rotation=quat_z_to(normals).astype(np.float32),
        opacity_logit=np.full(N_SURFELS, OPACITY_LOGIT, np.float32),
        channels={"sh": np.zeros((N_SURFELS, 3), np.float32)})
    ply.write_ply_model(path, model)


def crosscheck(kind: str, model_path) -> dict:
    """Render both ways from one Mitsuba sensor; returns the figures and the images."""
    import mitsuba as mi

    from mi_shadowgs.core.camera import Camera

    sens, scale = SENSORS[kind]
    lookat = (f'<lookat origin="{", ".join(map(str, ORIGIN))}" '
              f'target="{", ".join(map(str, TARGET))}" up="0, 1, 0"/>')
    scene = mi.load_string(f"""<scene version="3.0.0">
      <integrator type="surfel_raster">
        <string name="filename" value="{model_path}"/>
        <string name="aovs" value="depth"/>
      </integrator>
      <sensor type="{kind}">{sens}
        <transform name="to_world">{scale}{lookat}</transform>
        <film type="hdrfilm"><integer name="width" value="{W}"/>
          <integer name="height" value="{H}"/>
          <string name="pixel_format" value="rgba"/></film>
      </sensor>
      <shape type="sphere"><float name="radius" value="{RADIUS}"/>
        <point name="center" x="{CENTER[0]}" y="{CENTER[1]}" z="{CENTER[2]}"/></shape>
    </scene>""")
    img = np.asarray(mi.render(scene))  # [H, W, R G B A depth.T]
    alpha, depth = img[..., 3], img[..., 4]

    # Mitsuba ray tracing of the analytic sphere through the same sensor, at pixel centres.
    sensor = scene.sensors()[0]
    ys, xs = np.mgrid[0:H, 0:W]
    film_pos = mi.Point2f(((xs.ravel() + 0.5) / W).astype(np.float32),
                          ((ys.ravel() + 0.5) / H).astype(np.float32))
    rays, _ = sensor.sample_ray(0.0, 0.5, film_pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(rays)
    hit = np.asarray(si.is_valid()).reshape(H, W)
    points = np.asarray(si.p).reshape(3, H * W).T  # Dr.Jit arrays convert as [3, N]
    cam = Camera.from_mitsuba(sensor)
    # Ray length is not our depth: z-depth is the distance along the optical axis.
    z_ref = ((points - cam.origin) @ cam.forward).reshape(H, W)

    sil = alpha > 0.5
    both = sil & hit
    rel = np.abs(depth[both] - z_ref[both]) / z_ref[both]
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(both, iterations=2)
    rel_inner = np.abs(depth[inner] - z_ref[inner]) / z_ref[inner]
    cy_s, cx_s = (np.nonzero(sil)[k].mean() for k in (0, 1))
    cy_h, cx_h = (np.nonzero(hit)[k].mean() for k in (0, 1))
    edge = hit ^ binary_erosion(hit)
    return {
        "iou": float((sil & hit).sum() / (sil | hit).sum()),
        "hit_pixels": int(hit.sum()), "silhouette_pixels": int(sil.sum()),
        "missed_pixels": int((hit & ~sil).sum()),
        "band_px": float((sil & ~hit).sum() / edge.sum()),  # mean outward growth
        "centroid_shift_px": (float(cx_s - cx_h), float(cy_s - cy_h)),
        "depth_rel_median": float(np.median(rel)), "depth_rel_p99": float(np.quantile(rel, 0.99)),
        "depth_rel_max": float(rel.max()), "depth_rel_max_inner": float(rel_inner.max()),
        "in_frame": bool(not (hit[0].any() or hit[-1].any() or hit[:, 0].any()
                              or hit[:, -1].any())),
    }


@pytest.fixture(scope="module")
def sphere_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("crosscheck") / "sphere_surfels.ply"
    write_sphere_model(path)
    return path


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
def test_sphere_surfels_match_mitsuba(kind, sphere_model):
    r = crosscheck(kind, sphere_model)
    assert r["in_frame"] and r["hit_pixels"] > 40000, r
    # Acceptance: silhouette IoU >= 0.98. The surfel silhouette is a ~1 px wider
    # band than the sphere's (the 2DGS screen-space low-pass gives every splat a >= 1 px
    # footprint), so IoU depends on the sphere's size in pixels: ~160 px radius here.
    assert r["iou"] >= 0.98, r
    assert r["missed_pixels"] == 0, r  # opaque surfels cover every pixel the sphere does
    assert r["band_px"] < 1.5, r
    # A half-pixel convention error would shift the silhouette by 0.5 px; measured < 0.05.
    assert max(abs(v) for v in r["centroid_shift_px"]) < 0.15, r
    # Acceptance: depth within 1% on pixels both see. Tangent discs deviate from the sphere
    # by ~d^2/(2 r) (measured median 0.13%); the outermost 1-2 px of the rim reach ~2%
    # because the sphere's depth there changes by several % per pixel, so the per-pixel
    # bound holds on pixels 2 px inside the joint silhouette, and for 99% of all of them.
    assert r["depth_rel_median"] < 0.003, r
    assert r["depth_rel_p99"] < 0.01, r
    assert r["depth_rel_max_inner"] < 0.01, r


if __name__ == "__main__":
    import tempfile
    import time
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        model = Path(d) / "sphere.ply"
        write_sphere_model(model)
        for kind in SENSORS:
            t0 = time.perf_counter()
            res = crosscheck(kind, model)
            print(kind, f"{time.perf_counter() - t0:.2f}s", res)
