"""Rendering a surfel model for a viewer: colour + AOVs, shared by the plugin and the CLI.

``render_surfels`` picks the colour source (SH evaluated from the camera, or a named
per-surfel channel), calls the differentiable rasterizer, and returns named images.
``aov_layout`` names the film channels of each AOV in Mitsuba's style (``depth.T``,
``normal.X/Y/Z``, ``albedo.R/G/B``), as the ``aov`` integrator does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import mitsuba as mi

from mi_shadowgs.core.camera import Camera

# AOVs the rasterizer computes (everything else must name a per-surfel channel).
RASTER_AOVS = {"alpha": 1, "depth": 1, "median_depth": 1, "normal": 3, "distortion": 1,
               "count": 1}
DEFAULT_COLOR_CHANNEL = "sh"


class RenderError(ValueError):
    """A render request names an unknown AOV/channel or has bad values."""


def channel_suffixes(width: int) -> list[str]:
    if width == 1:
        return ["T"]
    if width == 3:
        return ["R", "G", "B"]
    return [str(i) for i in range(width)]


def aov_layout(aovs: Sequence[str], surfels) -> list[tuple[str, list[str]]]:
    """[(aov, film channel names)] for the requested AOVs, checked against the model."""
    if isinstance(aovs, str):  # read letter by letter it gave "unknown AOV 'd'"
        raise TypeError(f"aovs must be a sequence of names, e.g. ({aovs!r},), got the string "
                        f"{aovs!r}")
    out = []
    for name in aovs:
        if name in RASTER_AOVS:
            suffixes = ["X", "Y", "Z"] if name == "normal" else ["T"]
        elif name in surfels.channels:
            suffixes = channel_suffixes(int(surfels.channels[name].shape[1]))
        else:
            raise RenderError(f"unknown AOV {name!r}: choose from {sorted(RASTER_AOVS)} or a "
                              f"surfel channel {sorted(surfels.channels)}")
        out.append((name, [f"{name}.{s}" for s in suffixes]))
    if len({n for n, _ in out}) != len(out):
        raise RenderError(f"AOV list {list(aovs)} names an AOV twice")
    return out


def parse_background(value, what: str = "background") -> tuple[float, float, float] | None:
    """None, a number, "r,g,b", or 3 numbers -> finite (r, g, b)."""
    if value is None:
        return None
    if isinstance(value, str):
        parts = [p for p in value.replace(",", " ").split() if p]
    elif isinstance(value, int | float):
        parts = [value]
    else:
        parts = list(value)
    try:
        rgb = [float(p) for p in parts]
    except (TypeError, ValueError):
        raise RenderError(f"{what} must be 1 or 3 numbers, got {value!r}") from None
    if len(rgb) == 1:
        rgb = rgb * 3
    if len(rgb) != 3 or not all(abs(v) < float("inf") for v in rgb):
        raise RenderError(f"{what} must be 1 or 3 finite numbers, got {value!r}")
    return (rgb[0], rgb[1], rgb[2])


def check_color_channel(surfels, color_channel: str) -> None:
    """RenderError unless ``color_channel`` can colour ``surfels``: ``sh`` of 3(d+1)^2
    columns, or another channel of 1 or 3."""
    if color_channel not in surfels.channels:
        raise RenderError(f"colour channel {color_channel!r} is not in the model "
                          f"(channels: {sorted(surfels.channels)})")
    width = int(surfels.channels[color_channel].shape[1])
    if color_channel == "sh":
        from mi_shadowgs.core.surfels import sh_degree

        try:
            sh_degree(width // 3 if width % 3 == 0 else 0)
        except ValueError:
            raise RenderError(f"colour channel 'sh' has {width} columns; need 3(d+1)^2 "
                              "(3, 12, 27 or 48)") from None
    elif width not in (1, 3):
        raise RenderError(f"colour channel {color_channel!r} has {width} columns; need 1 or 3")


def surfel_colors(surfels, camera: Camera, color_channel: str = DEFAULT_COLOR_CHANNEL):
    """Per-surfel RGB [N, 3] (TensorXf): SH seen from the camera, or a stored channel."""
    check_color_channel(surfels, color_channel)
    if color_channel == "sh":
        from mi_shadowgs.core.surfels import sh_colors

        return sh_colors(surfels, camera_origin_for_sh(camera))
    values = surfels.channels[color_channel]
    if int(values.shape[1]) == 3:
        return values
    # grey: repeat the one column
    import drjit as dr

    idx = dr.arange(mi.UInt32, surfels.count * 3) // 3
    return mi.TensorXf(dr.gather(mi.Float, values.array, idx), (surfels.count, 3))


def camera_origin_for_sh(camera: Camera):
    """Viewpoint for SH evaluation; an orthographic camera's is pushed far back along its axis
    so that every surfel sees (nearly) the same direction, as parallel rays do."""
    o = camera.origin  # [3]
    if camera.is_ortho:
        o = o - camera.forward * 1.0e4
    return o


def render_surfels(surfels, camera: Camera, *, color_channel: str = DEFAULT_COLOR_CHANNEL,
                   aovs: Sequence[str] = (), background=None,
                   config=None) -> dict[str, mi.TensorXf]:
    """Images [H, W, C]: "rgb" (premultiplied over black unless ``background``), "alpha",
    and each requested AOV (a rasterizer AOV or a per-surfel channel, premultiplied)."""
    from mi_shadowgs.core.raster import RasterConfig, rasterize

    config = RasterConfig() if config is None else config
    aov_layout(aovs, surfels)  # validates the names
    bg = parse_background(background)
    channels = {"rgb": surfel_colors(surfels, camera, color_channel)}
    for name in aovs:
        if name not in RASTER_AOVS:
            channels[name] = surfels.channels[name]
    raster_aovs = tuple(dict.fromkeys(["alpha"] + [a for a in aovs if a in RASTER_AOVS]))
    return rasterize(surfels, camera, channels, aovs=raster_aovs,
                     background=None if bg is None else {"rgb": bg}, config=config)


def sensor_camera(sensor) -> Camera:
    """The Camera of a Mitsuba sensor, refusing what the rasterizer cannot reproduce."""
    params = mi.traverse(sensor)
    for key in ("principal_point_offset_x", "principal_point_offset_y"):
        if key in params and abs(float(mi.Float(params[key])[0])) > 0.0:
            raise RenderError(f"sensor {key} must be 0 for surfel rendering")
    return Camera.from_mitsuba(sensor)


@dataclasses.dataclass(frozen=True)
class FilmLayout:
    """Where each image goes in the storage block of an ``hdrfilm``: R, G, B, [A], W, AOVs."""

    has_alpha: bool
    aovs: tuple[tuple[str, tuple[str, ...]], ...]

    @property
    def storage_channels(self) -> int:
        return 3 + int(self.has_alpha) + 1 + sum(len(c) for _, c in self.aovs)

    def assemble(self, images: Mapping[str, mi.TensorXf]) -> mi.TensorXf:
        """Concatenate the images [H, W, *] into the film's storage layout [H, W, C]."""
        import drjit as dr

        rgb = images["rgb"]
        h, w = rgb.shape[0], rgb.shape[1]
        parts = [rgb]
        if self.has_alpha:
            parts.append(images["alpha"])
        parts.append(dr.full(mi.TensorXf, 1.0, (h, w, 1)))  # sample weight: one per pixel
        parts += [images[name] for name, _ in self.aovs]
        return dr.concat(parts, axis=-1)


def develop_film(film, layout: FilmLayout, aov_names: Sequence[str],
                 images: Mapping[str, mi.TensorXf], plugin: str) -> mi.TensorXf:
    """Put ``images`` into ``film`` (prepared for ``aov_names``) and develop it; shared by
    the integrator plugins, whose Mitsuba films must hold exactly ``layout``'s channels."""
    count = film.prepare(list(aov_names))
    if count != layout.storage_channels:
        raise ValueError(f"{plugin}: film {film.class_name()} stores {count} channels, "
                         f"expected {layout.storage_channels} (use an hdrfilm)")
    film.put_block(mi.ImageBlock(layout.assemble(images), mi.ScalarPoint2i(film.crop_offset())))
    return film.develop()
