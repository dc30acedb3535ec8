"""One world frame for captured data (docs/conventions.md): Y-up, the support plane at y = 0,
the object centred on the Y axis with a bounding sphere of radius 1.

Pure NumPy maths on SfM points and camera centres; ``mi_shadowgs.dataset.importer`` calls it.
The result is a similarity ``x_ours = scale * R @ x_src + t`` recorded in ``import.json``.
"""

from __future__ import annotations

import dataclasses

import numpy as np


class WorldFrameError(ValueError):
    """The points and cameras do not determine a world frame; the message says why."""


@dataclasses.dataclass(frozen=True)
class Similarity:
    """``x_ours = scale * rotation @ x_src + translation``."""

    scale: float
    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3]

    @property
    def matrix(self) -> np.ndarray:
        """[4, 4] acting on homogeneous source points."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def points(self, x: np.ndarray) -> np.ndarray:
        """Source points [M, 3] -> ours [M, 3]."""
        return self.scale * np.asarray(x, np.float64) @ self.rotation.T + self.translation

    def c2w(self, c2w: np.ndarray) -> np.ndarray:
        """A camera-to-world [4, 4] (rigid) in the source frame -> ours (rigid)."""
        out = np.eye(4)
        out[:3, :3] = self.rotation @ c2w[:3, :3]
        out[:3, 3] = self.points(c2w[None, :3, 3])[0]
        return out

    def to_json(self) -> dict:
        return {"maps": "x_ours = scale * rotation @ x_source + translation",
                "scale": self.scale, "rotation": self.rotation.tolist(),
                "translation": self.translation.tolist(), "matrix": self.matrix.tolist(),
                "inverse": np.linalg.inv(self.matrix).tolist()}


@dataclasses.dataclass(frozen=True)
class FrameConfig:
    ransac_iterations: int = 2000
    # plane inlier distance, as a fraction of the points' robust extent (median distance from
    # their median): a mat is flat to well under 1% of the scene
    plane_threshold: float = 0.01
    # a plane counts when it holds this fraction of the points (else: cameras' up vectors)
    min_plane_fraction: float = 0.15
    # points further above the plane than this many thresholds are the object's
    object_clearance: float = 3.0
    # robust object bounds: these percentiles of the object's points along each axis
    bound_percentiles: tuple = (1.0, 99.0)
    seed: int = 0
    # fewer SfM points than this in all: the whole frame from the cameras (no plane fit)
    min_points: int = 10
    # fewer object points than this: centre and size from the cameras instead
    min_object_points: int = 50
    # then the cameras are taken to stand this many object radii from the centre (the
    # generator's and NeRF-synthetic's camera distance)
    camera_distance_radii: float = 5.0


def fit_plane(points: np.ndarray, threshold: float, iterations: int,
              rng: np.random.Generator) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane through ``points`` [M, 3]: (unit normal [3], offset d with n.x = d,
    inlier mask [M]); refined by least squares over the inliers."""
    m = len(points)
    best = None
    for _ in range(iterations):
        a, b, c = points[rng.choice(m, 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        inl = np.abs(points @ n - n @ a) < threshold
        if best is None or inl.sum() > best[2].sum():
            best = (n, n @ a, inl)
    if best is None:
        raise WorldFrameError("the SfM points are all collinear: no plane can be fitted")
    inl = best[2]
    centre = points[inl].mean(axis=0)
    n = np.linalg.svd(points[inl] - centre, full_matrices=False)[2][2]
    inl = np.abs((points - centre) @ n) < threshold
    return n, float(n @ centre), inl


def look_at_point(c2w: np.ndarray) -> np.ndarray:
    """The point [3] nearest (least squares) to every camera's optical axis."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for c in c2w:
        f = -c[:3, 2] / np.linalg.norm(c[:3, 2])
        p = np.eye(3) - np.outer(f, f)
        a += p
        b += p @ c[:3, 3]
    return np.linalg.solve(a, b)


def camera_up(c2w: np.ndarray) -> np.ndarray:
    """The mean of the cameras' image-up axes (OpenGL +Y) [3]: people hold cameras upright."""
    up = c2w[:, :3, 1].sum(axis=0)
    return up / np.linalg.norm(up)


def world_frame(points: np.ndarray, c2w: np.ndarray,
                config: FrameConfig = FrameConfig()) -> tuple[Similarity, dict]:
    """The similarity from the source frame to ours, and a report of how it was found.

    ``points`` [M, 3] SfM points, ``c2w`` [N, 4, 4] OpenGL camera-to-world, both in the
    source frame. Up is the normal of the dominant plane (RANSAC; the side the cameras are
    on), or the cameras' mean up vector where no plane holds enough points; the plane (or
    the lowest object points) goes to y = 0, the object's robust bounding box is centred on
    the Y axis and its bounding sphere scaled to radius 1.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    c2w = np.asarray(c2w, np.float64)
    if len(points) < config.min_points:
        return _frame_from_cameras(c2w, config, len(points))
    rng = np.random.default_rng(config.seed)
    median = np.median(points, axis=0)
    extent = float(np.median(np.linalg.norm(points - median, axis=1)))
    thr = config.plane_threshold * extent
    n, d, inl = fit_plane(points, thr, config.ransac_iterations, rng)
    centres = c2w[:, :3, 3]
    report = {"plane_inliers": int(inl.sum()), "points": len(points),
              "plane_threshold": thr}
    if inl.mean() >= config.min_plane_fraction:
        if np.median(centres @ n - d) < 0:  # the cameras look down on the mat
            n, d = -n, -d
        report["up_from"] = "plane"
        height = points @ n - d
    else:
        n = camera_up(c2w)
        report["up_from"] = ("camera up vectors (no plane holds "
                             f"{config.min_plane_fraction:.0%} of the points)")
        height = points @ n
        d = float(np.percentile(height, config.bound_percentiles[0]))
        height = height - d
    obj = points[height > config.object_clearance * thr]
    # Axes: y = up; x = the first camera's right vector made horizontal (any would do).
    x = c2w[0, :3, 0] - (c2w[0, :3, 0] @ n) * n
    if np.linalg.norm(x) < 1e-6:
        x = np.eye(3)[np.argmin(np.abs(n))] - n * n[np.argmin(np.abs(n))]
    x /= np.linalg.norm(x)
    z = np.cross(x, n)
    rot = np.stack([x, n, z])  # rows: source -> ours
    if len(obj) >= config.min_object_points:
        local = obj @ rot.T
        local[:, 1] -= d
        lo = np.percentile(local, config.bound_percentiles[0], axis=0)
        hi = np.percentile(local, config.bound_percentiles[1], axis=0)
        lo[1] = 0.0  # the object stands on the plane
        radius = 0.5 * float(np.linalg.norm(hi - lo))
        centre = 0.5 * (lo + hi)
        report["centre_from"] = "object points"
    else:
        # A textureless object gives SfM few points: centre it where the cameras look, and
        # take the size from the cameras' distance to that point.
        look = look_at_point(c2w) @ rot.T
        dist = float(np.median(np.linalg.norm(centres @ rot.T - look, axis=1)))
        radius = dist / config.camera_distance_radii
        centre = np.array([look[0], 0.0, look[2]])
        report["centre_from"] = (f"cameras' look-at point (only {len(obj)} object points); "
                                 f"size: cameras {config.camera_distance_radii} radii away")
    scale = 1.0 / radius
    t = -scale * np.array([centre[0], d, centre[2]])
    # ours = scale * (rot @ x_src - (cx, d, cz))
    sim = Similarity(scale=scale, rotation=rot, translation=t)
    report["object_points"] = len(obj)
    return sim, report


def _frame_from_cameras(c2w: np.ndarray, config: FrameConfig,
                        n_points: int) -> tuple[Similarity, dict]:
    """No points (a transforms file without a point cloud): up from the cameras' up
    vectors, the object at the point they look at, its radius from their distance
    (``camera_distance_radii``), standing on y = 0."""
    n = camera_up(c2w)
    x = c2w[0, :3, 0] - (c2w[0, :3, 0] @ n) * n
    x /= np.linalg.norm(x)
    rot = np.stack([x, n, np.cross(x, n)])
    look = look_at_point(c2w) @ rot.T
    dist = float(np.median(np.linalg.norm(c2w[:, :3, 3] @ rot.T - look, axis=1)))
    scale = config.camera_distance_radii / dist
    # the bounding sphere's centre is at the look-at point; the object stands on y = 0
    bottom = look[1] - dist / config.camera_distance_radii
    t = -scale * np.array([look[0], bottom, look[2]])
    report = {"points": n_points, "up_from": "camera up vectors (no points)",
              "centre_from": f"cameras' look-at point; size: cameras "
                             f"{config.camera_distance_radii} radii away"}
    return Similarity(scale=scale, rotation=rot, translation=t), report


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """The least-squares similarity taking points ``src`` [M, 3] onto ``dst`` [M, 3]
    (Umeyama 1991)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2, 2] = -1.0
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(sig) @ d) / (a ** 2).sum(axis=1).mean())
    return Similarity(scale=scale, rotation=rot, translation=mu_d - scale * rot @ mu_s)


def camera_errors(est_c2w: np.ndarray, gt_c2w: np.ndarray) -> dict:
    """Camera accuracy after aligning ``est_c2w`` [N, 4, 4] to ``gt_c2w`` [N, 4, 4] by the
    similarity of their centres: RMS centre error as a percentage of the mean camera
    distance from the cameras' centroid, and rotation errors in degrees."""
    est_c2w, gt_c2w = np.asarray(est_c2w, np.float64), np.asarray(gt_c2w, np.float64)
    sim = umeyama(est_c2w[:, :3, 3], gt_c2w[:, :3, 3])
    aligned = np.stack([sim.c2w(c) for c in est_c2w])
    err = np.linalg.norm(aligned[:, :3, 3] - gt_c2w[:, :3, 3], axis=1)
    gt_c = gt_c2w[:, :3, 3]
    dist = float(np.linalg.norm(gt_c - gt_c.mean(axis=0), axis=1).mean())
    rel = np.einsum("nij,nik->njk", aligned[:, :3, :3], gt_c2w[:, :3, :3])  # R_est^T R_gt
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    return {"centre_rms_pct": float(100.0 * np.sqrt((err ** 2).mean()) / dist),
            "centre_max_pct": float(100.0 * err.max() / dist),
            "rotation_mean_deg": float(ang.mean()), "rotation_max_deg": float(ang.max()),
            "rotation_rms_deg": float(np.sqrt((ang ** 2).mean())),
            "rotation_median_deg": float(np.median(ang)),
            "views": len(est_c2w)}
