"""Kernels compiled once: a new camera must not change the source of a step's kernels.

Dr.Jit reuses a compiled kernel only when its source is the same (``mi_shadowgs.core.jit``).
A camera value that enters a kernel as a literal compiles every kernel that reads it again
for every view: ~100 ms per kernel on the CPU, a cost that can exceed the step itself
(stage 1's view-dependent colours once did this for ~1300 steps). The test compares the
kernel hashes (a hash of the source) of one stage-1 step from two cameras: equal sets,
whatever the kernel cache holds. A model read from host memory (a PLY file, a checkpoint)
compiles the same kernels wherever NumPy put its arrays.
The last test counts kernels run rather than compiled: work done once, not per channel.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import numpy as np

from mi_shadowgs import presets as run_presets
from mi_shadowgs.core import jit
from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.surfels import Surfels
from mi_shadowgs.stages.geometry import train as geometry_train


def _surfels(n: int = 200) -> Surfels:
    rng = np.random.default_rng(3)
    pos = rng.uniform(-0.5, 0.5, (n, 3))
    rot = rng.standard_normal((n, 4))
    sh = rng.uniform(-0.3, 0.3, (n, 12))  # SH degree 1: the colour depends on the view
    s = Surfels.from_numpy(pos, np.full((n, 2), 0.08), rot, np.full(n, 0.6), {"sh": sh})
    dr.enable_grad(s.position, s.channels["sh"])
    return s


def _view(origin) -> geometry_train.ViewData:
    cam = Camera.look_at(origin, (0.0, 0.0, 0.0), width=24, height=24, fov_x=0.8)
    # In memory Dr.Jit allocated, as stage 1's views are: NumPy's memory would put its
    # alignment into the loss's kernels (``core.jit``).
    image = jit.tensor(np.full((24, 24, 3), 0.4, np.float32))
    mask = jit.tensor(np.ones((24, 24, 1), np.float32))
    return geometry_train.ViewData(cam, image, mask)


def _step_hashes(surfels: Surfels, view, config, step: int) -> set:
    # Zero gradients: a backward into the arrays' gradients would accumulate (another
    # kernel). The same arrays every time: arrays wrapping fresh NumPy memory have their
    # own alignment in the loads' source (``core.jit``), another cause of new kernels.
    dr.clear_grad(surfels.position)
    dr.clear_grad(surfels.channels["sh"])
    dr.kernel_history()  # clear
    loss, _ = geometry_train.geometry_loss(surfels, view, config, step)
    dr.backward(loss)
    dr.eval(dr.grad(surfels.position), dr.grad(surfels.channels["sh"]))
    dr.sync_thread()
    return {k["hash"] for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT}


def test_a_new_camera_compiles_no_new_stage1_kernel():
    config = run_presets.geometry_config("cpu-small")
    config = dataclasses.replace(config, sh_degree=1)
    step = config.dist_from + 1  # every loss term on: colour, mask, normal, distortion
    surfels = _surfels()
    views = [_view((2.5, 1.0, 1.5)), _view((-1.0, 1.8, 2.4))]
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        first = _step_hashes(surfels, views[0], config, step)
        again = _step_hashes(surfels, views[0], config, step)
        other = _step_hashes(surfels, views[1], config, step)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert first, "no kernel ran: the history did not record the step"
    assert again == first  # the baseline: the same camera, the same kernels
    assert other == first, f"{len(other - first)} kernel(s) compiled for the second camera"


def _placed(a: np.ndarray, offset: int) -> np.ndarray:
    """A float32 copy of ``a`` whose data starts ``offset`` bytes past a 64-byte boundary."""
    a = np.asarray(a, np.float32)
    raw = np.empty(a.size + 32, np.float32)
    start = (-(raw.ctypes.data // 4) + offset // 4) % 16
    out = raw[start:start + a.size].reshape(a.shape)
    out[...] = a
    assert out.ctypes.data % 64 == offset
    return out


def test_a_model_read_from_host_memory_compiles_the_same_kernels_wherever_it_lies():
    """A model from NumPy (a PLY file, a checkpoint) goes to memory Dr.Jit allocated: where
    NumPy put the arrays (their alignment) must not reach the kernels' source."""
    from mi_shadowgs.core.raster import rasterize
    from mi_shadowgs.io.ply import PlyModel

    rng = np.random.default_rng(4)
    n = 300
    arrays = (rng.uniform(-0.5, 0.5, (n, 3)), np.full((n, 2), np.log(0.08)),
              rng.standard_normal((n, 4)), rng.uniform(-1, 1, n),
              {"albedo": rng.uniform(0, 1, (n, 3))})
    cam = Camera.look_at((2.5, 1.0, 1.5), (0.0, 0.0, 0.0), width=24, height=24, fov_x=0.8)

    def hashes(place, how: str) -> set:
        pos, log_s, rot, logit, ch = arrays
        if how == "ply":
            s = PlyModel(place(pos), place(log_s), place(rot), place(logit),
                         {k: place(v) for k, v in ch.items()}).to_surfels()
        else:
            s = Surfels.from_numpy(place(pos), np.exp(place(log_s)), place(rot),
                                   1 / (1 + np.exp(-place(logit))),
                                   {k: place(v) for k, v in ch.items()})
        dr.kernel_history()
        out = rasterize(s, cam, {"albedo": s.channels["albedo"]}, aovs=("alpha",))
        dr.eval(out["albedo"], out["alpha"])
        dr.sync_thread()
        return {k["hash"] for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT}

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for how in ("ply", "from_numpy"):
            aligned = hashes(lambda a: _placed(a, 0), how)
            assert aligned
            assert hashes(lambda a: _placed(a, 4), how) == aligned, how
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_shadow_maps_compile_no_new_kernel_for_another_light_count():
    from mi_shadowgs.stages.visibility.shadow_maps import (
        SceneBounds,
        VisibilityConfig,
        render_shadow_maps,
    )

    surfels = _surfels()
    bounds = SceneBounds((0.0, 0.0, 0.0), 0.9, 3.0)
    config = VisibilityConfig(resolution=32)  # the layer slack's window: the default's path
    rng = np.random.default_rng(5)

    def hashes(count: int) -> set:
        d = rng.standard_normal((count, 3))
        d[:, 1] = np.abs(d[:, 1]) + 0.5  # above the horizon
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        dr.kernel_history()
        maps = render_shadow_maps(surfels, d, bounds, config)
        dr.eval(maps.depth)
        dr.sync_thread()
        return {k["hash"] for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT}

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        three = hashes(3)
        five = hashes(5)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert three
    assert five <= three, f"{len(five - three)} kernel(s) compiled for 5 maps after 3"


def test_per_light_shading_runs_once_for_three_channels():
    """``shading.direct`` sums f_r (n . l) V E over K lights per pixel with one block_reduce
    per colour channel. Left lazy, reading the channels one by one (as ``color_image``
    does) ran the [P * K] shading and its inputs once per channel: 3x the work at the
    warm-up's and an env map's 128 lights."""
    import mitsuba as mi

    from mi_shadowgs.core import shading

    npix, k = 64, 8
    rng = np.random.default_rng(2)
    normal = rng.standard_normal((npix, 3))
    normal[:, 1] = np.abs(normal[:, 1]) + 0.5
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    zeros = dr.zeros(mi.Float, npix)
    geom = shading.PixelGeometry(dr.ones(mi.Float, npix), None, None,
                                 mi.Vector3f(*(jit.array(normal[:, c]) for c in range(3))),
                                 None, None, zeros)
    dirs = rng.standard_normal((k, 3))
    dirs[:, 1] = np.abs(dirs[:, 1])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # Three different channels: equal ones would be merged by Dr.Jit into one computation.
    e = rng.uniform(0.5, 1.0, (3, k))
    a = rng.uniform(0.2, 0.8, (3, npix))
    vis = rng.uniform(0.0, 1.0, npix * k)
    lights = shading.LightSet(dirs, mi.Color3f(*(jit.array(x) for x in e)))
    albedo = mi.Color3f(*(jit.array(x) for x in a))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        out = shading.direct(geom, albedo, zeros, zeros, lights, jit.array(vis), False)
        got = [out[c].numpy() for c in range(3)]  # one channel at a time
        dr.sync_thread()
        wide = [h for h in dr.kernel_history()
                if h.get("type") == dr.KernelType.JIT and h["size"] == npix * k]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(wide) == 1, f"{len(wide)} kernels over the {npix} x {k} pixel-light pairs"
    # and the sum itself, in float64
    cos = np.maximum(normal @ dirs.T, 0.0)  # [P, K]
    for c in range(3):
        want = (a[c][:, None] / np.pi * cos * vis.reshape(npix, k) * e[c][None]).sum(1)
        np.testing.assert_allclose(got[c], want, rtol=1e-5, atol=1e-7)
