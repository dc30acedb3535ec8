"""Pinhole and orthographic cameras, and their exchange with Mitsuba sensors and dataset JSON.

One ``Camera`` feeds the rasterizer, the visibility shadow maps, the dataset generator and
the loader. Conventions (docs/conventions.md): ``c2w`` is camera-to-world in the
Blender/OpenGL convention (looks down -Z, +Y up, +X right); pixel (0, 0) is the top-left
corner and pixel centres sit at half-integers.

Internally projection uses the "CV" camera frame: +X right, +Y down, +Z forward, so that
``u = fx * x / z + cx`` and ``v = fy * y / z + cy`` (perspective) or
``u = x / pixel_size + cx`` (orthographic).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

# OpenGL camera frame -> CV camera frame (flip Y and Z); also Mitsuba <-> OpenGL is diag(-1,1,-1).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
_GL_TO_MI = np.diag([-1.0, 1.0, -1.0, 1.0])


@dataclasses.dataclass(frozen=True)
class Camera:
    """A camera: ``c2w`` [4, 4] OpenGL camera-to-world, image size, and projection.

    Perspective when ``fov_x`` (full horizontal field of view, radians) is set; orthographic
    when ``ortho_width`` (image-plane width in scene units) is set instead.
    Real cameras (nerfstudio ``fl_y``, ``cx``, ``cy``; COLMAP pinholes) add ``focal_y``
    (vertical focal length in pixels, perspective only; default: square pixels) and the
    principal point ``cx``, ``cy`` in pixels (default: the image centre).
    """

    c2w: np.ndarray  # [4, 4] float64, OpenGL convention
    width: int
    height: int
    fov_x: float | None = None
    ortho_width: float | None = None
    near: float = 0.01
    far: float = 1.0e4
    focal_y: float | None = None
    cx: float | None = None
    cy: float | None = None

    def __post_init__(self):
        c2w = np.asarray(self.c2w, dtype=np.float64)
        if c2w.shape != (4, 4):
            raise ValueError(f"camera c2w must be 4x4, got shape {c2w.shape}")
        if not np.all(np.isfinite(c2w)):
            raise ValueError("camera c2w holds NaN or Inf")
        object.__setattr__(self, "c2w", c2w)
        if (self.fov_x is None) == (self.ortho_width is None):
            raise ValueError("a camera needs exactly one of fov_x (perspective) or ortho_width")
        if self.fov_x is not None and not (0.0 < self.fov_x < math.pi):
            raise ValueError(f"camera fov_x must be in (0, pi) radians, got {self.fov_x}")
        if self.ortho_width is not None and not self.ortho_width > 0:
            raise ValueError(f"camera ortho_width must be > 0, got {self.ortho_width}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if self.focal_y is not None:
            if self.is_ortho:
                raise ValueError("camera focal_y is for perspective cameras only")
            if not (math.isfinite(self.focal_y) and self.focal_y > 0):
                raise ValueError(f"camera focal_y must be > 0 pixels, got {self.focal_y}")
        for key in ("cx", "cy"):
            v = getattr(self, key)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"camera {key} must be a finite pixel coordinate, got {v}")

    @staticmethod
    def from_intrinsics(c2w, width: int, height: int, fx: float, fy: float, cx: float,
                        cy: float, **kwargs) -> Camera:
        """A pinhole from focal lengths and principal point in pixels (nerfstudio, COLMAP)."""
        if not (math.isfinite(fx) and fx > 0):
            raise ValueError(f"camera focal length fx must be > 0 pixels, got {fx}")
        fov_x = 2.0 * math.atan(0.5 * width / fx)
        return Camera(c2w=c2w, width=width, height=height, fov_x=fov_x,
                      focal_y=None if fy == fx else float(fy),
                      cx=None if cx == 0.5 * width else float(cx),
                      cy=None if cy == 0.5 * height else float(cy), **kwargs)

    # -- projection -------------------------------------------------------------------
    @property
    def is_ortho(self) -> bool:
        return self.ortho_width is not None

    @property
    def focal(self) -> float:
        """Focal length in pixels (perspective), or pixels per scene unit (orthographic)."""
        if self.is_ortho:
            return self.width / self.ortho_width
        return 0.5 * self.width / math.tan(0.5 * self.fov_x)

    @property
    def focal_xy(self) -> tuple[float, float]:
        """(fx, fy): focal lengths in pixels (perspective) or pixels per unit (orthographic)."""
        f = self.focal
        return f, (f if self.focal_y is None else self.focal_y)

    @property
    def principal_point(self) -> tuple[float, float]:
        return (0.5 * self.width if self.cx is None else self.cx,
                0.5 * self.height if self.cy is None else self.cy)

    @property
    def is_centred(self) -> bool:
        """Square pixels and the principal point at the image centre (what Mitsuba's
        ``perspective`` sensor without offsets renders)."""
        return self.focal_y is None and self.cx is None and self.cy is None

    @property
    def origin(self) -> np.ndarray:
        return self.c2w[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        """Unit viewing direction in world space."""
        f = -self.c2w[:3, 2]
        return f / np.linalg.norm(f)

    def world_to_cv(self) -> np.ndarray:
        """[4, 4] world -> CV camera frame (+X right, +Y down, +Z forward)."""
        return _GL_TO_CV @ np.linalg.inv(self.c2w)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [M, 3] -> (pixel coordinates [M, 2] (x, y), z-depth [M])."""
        p = np.asarray(points, dtype=np.float64)
        w2c = self.world_to_cv()
        pc = p @ w2c[:3, :3].T + w2c[:3, 3]
        cx, cy = self.principal_point
        fx, fy = self.focal_xy
        if self.is_ortho:
            uv = np.stack([fx * pc[:, 0] + cx, fy * pc[:, 1] + cy], axis=-1)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                uv = np.stack([fx * pc[:, 0] / pc[:, 2] + cx, fy * pc[:, 1] / pc[:, 2] + cy],
                              -1)
        return uv, pc[:, 2]

    def unproject(self, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixel coordinates [M, 2] and z-depth [M] -> world points [M, 3]."""
        uv = np.asarray(pixels, dtype=np.float64)
        z = np.asarray(depth, dtype=np.float64)
        cx, cy = self.principal_point
        fx, fy = self.focal_xy
        if self.is_ortho:
            pc = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, z], axis=-1)
        else:
            pc = np.stack([(uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z], axis=-1)
        c2w_cv = np.linalg.inv(self.world_to_cv())
        return pc @ c2w_cv[:3, :3].T + c2w_cv[:3, 3]

    def pixel_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x index [M], y index [M], inside [M] bool) of the pixels holding world points
        [M, 3]: inside when in front of the near plane and within the image."""
        uv, z = self.project(points)
        uv = np.nan_to_num(uv, nan=-1.0, posinf=-1.0, neginf=-1.0)
        xi = np.clip(np.floor(uv[:, 0]), -1, self.width).astype(np.int64)
        yi = np.clip(np.floor(uv[:, 1]), -1, self.height).astype(np.int64)
        inside = ((z > self.near) & (xi >= 0) & (xi < self.width) & (yi >= 0)
                  & (yi < self.height))
        return xi, yi, inside

    def lookup(self, image: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values [M, ...], inside [M] bool): ``image`` [H, W, ...] at the pixels holding
        world points [M, 3] (``pixel_of``: the pixel the point falls in), zero (False) where
        not inside. The votes of masks over views (stage 1's hull and prune, the mesh
        base's outline, the import's ground check) read the masks through this."""
        xi, yi, inside = self.pixel_of(points)
        values = np.zeros((len(points),) + image.shape[2:], image.dtype)
        values[inside] = image[yi[inside], xi[inside]]
        return values, inside

    def pixel_grid(self) -> np.ndarray:
        """Pixel-centre coordinates [H*W, 2] in row-major order."""
        ys, xs = np.mgrid[0 : self.height, 0 : self.width]
        return np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=-1).astype(np.float64)

    # -- construction -----------------------------------------------------------------
    @staticmethod
    def look_at(origin, target, up=(0.0, 1.0, 0.0), **kwargs) -> Camera:
        """Camera at ``origin`` looking at ``target``; kwargs go to the constructor."""
        o, t, u = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
        back = o - t
        n = np.linalg.norm(back)
        if n == 0:
            raise ValueError("look_at: origin and target coincide")
        back /= n
        right = np.cross(u, back)
        if np.linalg.norm(right) < 1e-9:  # looking straight along up: the world axis least
            right = np.cross(np.eye(3)[np.argmin(np.abs(back))], back)  # along the view
        right /= np.linalg.norm(right)
        true_up = np.cross(back, right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, back, o
        return Camera(c2w=c2w, **kwargs)

    def with_size(self, width: int, height: int) -> Camera:
        """The same camera on a film of another size (intrinsics scaled with it)."""
        if self.is_centred:
            return dataclasses.replace(self, width=width, height=height)
        sx, sy = width / self.width, height / self.height
        fx, fy = self.focal_xy
        cx, cy = self.principal_point
        return Camera.from_intrinsics(self.c2w, width, height, fx * sx, fy * sy, cx * sx,
                                      cy * sy, near=self.near, far=self.far)

    # -- Mitsuba ----------------------------------------------------------------------
    def mitsuba_to_world(self) -> np.ndarray:
        """[4, 4] ``to_world`` of the equivalent Mitsuba sensor (without ortho scaling)."""
        return self.c2w @ _GL_TO_MI

    def to_mitsuba_dict(self, spp: int = 1, film: dict | None = None,
                        sampler: str = "independent", seed: int = 0) -> dict:
        """A ``mi.load_dict`` description of the equivalent Mitsuba sensor."""
        import mitsuba as mi

        if self.focal_y is not None:
            raise ValueError("Mitsuba's perspective sensor has square pixels; this camera's "
                             f"focal_y ({self.focal_y}) differs from fx ({self.focal})")
        to_world = self.mitsuba_to_world()
        film_dict = {"type": "hdrfilm", "width": self.width, "height": self.height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgba"}
        film_dict.update(film or {})
        d = {"film": film_dict, "sampler": {"type": sampler, "sample_count": spp,
                                            "seed": seed},
             "near_clip": self.near, "far_clip": self.far}
        if self.is_ortho:
            # Mitsuba's orthographic image plane spans [-1, 1] along the film's larger axis
            # before to_world; scale it to our width (and height, same pixel pitch).
            half_w = 0.5 * self.ortho_width
            half = half_w * max(1.0, self.height / self.width)
            d.update(type="orthographic",
                     to_world=mi.ScalarTransform4f(to_world) @ mi.ScalarTransform4f().scale(
                         [half, half, 1.0]))
        else:
            d.update(type="perspective", fov=math.degrees(self.fov_x), fov_axis="x",
                     to_world=mi.ScalarTransform4f(to_world))
            if self.cx is not None or self.cy is not None:
                # Mitsuba's offsets are fractions of the film size and move the image content
                # the other way (measured against project() in tests/test_camera_intrinsics).
                cx, cy = self.principal_point
                d.update(principal_point_offset_x=(0.5 * self.width - cx) / self.width,
                         principal_point_offset_y=(0.5 * self.height - cy) / self.height)
        return d

    @staticmethod
    def from_mitsuba(sensor) -> Camera:
        """The Camera of a Mitsuba ``perspective`` or ``orthographic`` sensor."""
        import mitsuba as mi

        params = mi.traverse(sensor)
        film = sensor.film()
        width, height = (int(v) for v in film.crop_size())
        if (tuple(int(v) for v in film.crop_offset()) != (0, 0)
                or (width, height) != tuple(int(v) for v in film.size())):
            raise ValueError("Camera.from_mitsuba: cropped films are not supported")
        to_world = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
        # By class, not by its parameters: a thinlens sensor has an x_fov too, and was drawn
        # as a pinhole without its depth of field.
        kind = sensor.class_name() if hasattr(sensor, "class_name") else str(sensor)
        kind = kind.split("[")[0]
        near = float(params["near_clip"]) if "near_clip" in params else 0.01
        far = float(params["far_clip"]) if "far_clip" in params else 1.0e4
        if kind == "PerspectiveCamera":
            fov_x = math.radians(float(np.asarray(params["x_fov"]).ravel()[0]))
            return Camera(c2w=to_world @ _GL_TO_MI, width=width, height=height, fov_x=fov_x,
                          near=near, far=far)
        if kind == "OrthographicCamera":
            sx = np.linalg.norm(to_world[:3, 0])
            sy = np.linalg.norm(to_world[:3, 1])
            rot = to_world.copy()
            rot[:3, 0] /= sx
            rot[:3, 1] /= sy
            rot[:3, 2] /= np.linalg.norm(to_world[:3, 2])
            half = sx / max(1.0, height / width)
            return Camera(c2w=rot @ _GL_TO_MI, width=width, height=height,
                          ortho_width=2.0 * half, near=near, far=far)
        raise ValueError(f"Camera.from_mitsuba: unsupported sensor {kind}; use a perspective "
                         "or orthographic sensor")

    # -- dataset JSON -----------------------------------------------------------------
    def to_frame_json(self, file_path: str) -> dict:
        """A NeRF-synthetic frame entry (the shared camera_angle_x goes at the top level)."""
        return {"file_path": file_path, "transform_matrix": self.c2w.tolist()}
