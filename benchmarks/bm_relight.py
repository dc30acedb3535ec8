"""Relighting speed: ``mi-shadowgs relight`` frames and the
``surfel_relight`` plugin's env-map render, with shadow maps reused between frames.

Workload: the raster benchmark's sphere on a plane (``workloads.py``: 20k surfels, 5k with
``--quick``; a cpu-small fit of the default scene has ~27k) given
material channels (albedo 0.6, roughness 0.5, metallic 0, GGX on), 128^2 views on an orbit.

- directional: one light; the first frame renders its shadow map, later frames reuse it
  (target: later frames <= 0.1 s);
- env map: the generator's procedural sky over the 128-direction grid; the first frame
  integrates the env map and renders its shadow maps (target: later frames <= 1 s);
- plugin: ``mi.render`` of a scene with the sky and the ``surfel_relight`` integrator twice
  (target: the second >= 10x faster than the first).

    python -m benchmarks.run_all --out bench-out --only relight
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from mi_shadowgs import presets as run_presets

FRAMES = 8
TARGETS = {"directional_later_s": 0.1, "envmap_later_s": 1.0, "plugin_speedup": 10.0}


def _model(n: int, res: int):
    import numpy as np

    from benchmarks.workloads import build_workload, workload_camera
    from mi_shadowgs.core.surfels import Surfels

    wl = build_workload(n=n, resolution=res)
    channels = {"albedo": np.full((wl.n, 3), 0.6, np.float32),
                "roughness": np.full((wl.n, 1), 0.5, np.float32),
                "metallic": np.zeros((wl.n, 1), np.float32)}
    surfels = Surfels.from_numpy(wl.position, wl.scale, wl.rotation, wl.opacity, channels)
    return wl, surfels, workload_camera(wl.config)


def _sky(folder: Path) -> Path:
    from mi_shadowgs.dataset.generate import SkyConfig, sky_envmap_image
    from mi_shadowgs.io.images import write_exr

    path = folder / "sky.exr"
    write_exr(path, sky_envmap_image(SkyConfig()))
    return path


def _frames(fit, cameras, lights, preset: str) -> tuple[list[float], list[float]]:
    """Wall seconds per frame, and process CPU seconds per frame (all threads): on a shared
    machine the wall time grows with the load, the CPU time much less so."""
    from mi_shadowgs.stages.relight import render as relight
    from mi_shadowgs.stages.relight import runner

    cache = relight.RelightCache()
    wall, cpu = [], []
    frames = runner.relight_frames(fit, cameras, lights, cache)
    while True:
        c0 = time.process_time()
        try:
            _, _, s = next(frames)
        except StopIteration:
            return wall, cpu
        cpu.append(time.process_time() - c0)
        wall.append(s)


def _plugin_times(folder: Path, surfels, camera, sky: Path) -> tuple[float, float]:
    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.io.ply import save_ply

    ply = folder / "model.ply"
    save_ply(ply, surfels)
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "surfel_relight", "filename": str(ply)},
        "sky": {"type": "envmap", "filename": str(sky)},
        "sensor": camera.to_mitsuba_dict(film={"type": "hdrfilm", "width": camera.width,
                                               "height": camera.height})})
    times = []
    for _ in range(2):
        dr.sync_thread()
        t0 = time.perf_counter()
        img = mi.render(scene)
        dr.eval(img)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return times[0], times[1]


def run_suite(out: Path, preset: str = "paper", log=print) -> dict:
    import os

    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.core.directions import direction_from_angles
    from mi_shadowgs.io.atomic import write_json
    from mi_shadowgs.stages.relight import render as relight
    from mi_shadowgs.stages.relight import runner
    from mi_shadowgs.stages.visibility import shadow_maps

    n, res = (20_000, 128) if preset == "paper" else (5_000, 128)  # --quick: 5k surfels
    wl, surfels, cam = _model(n, res)
    pos = wl.position
    bounds = shadow_maps.SceneBounds.from_points(pos, [cam], 0.98)
    model = relight.RelightModel(surfels, True, True)
    fit = runner.RunFit(None, model, bounds, None, "cpu-small")
    cams = runner.orbit_cameras(FRAMES, cam, bounds.center)
    load0 = os.getloadavg()[0]
    sun = relight.directional_light_set(direction_from_angles(40.0, 45.0)[None], [[3.0] * 3])
    directional, directional_cpu = _frames(fit, cams, sun, preset)
    log(f"relight directional: first {directional[0]:.3f} s, later median "
        f"{statistics.median(directional[1:]):.3f} s (CPU "
        f"{statistics.median(directional_cpu[1:]):.3f} s)")
    with tempfile.TemporaryDirectory() as tmp:
        sky = _sky(Path(tmp))
        cfg = run_presets.relight_config("cpu-small")
        t0 = time.perf_counter()
        env_lights = runner.build_lights(envmap=str(sky), config=cfg,
                                         cache=relight.RelightCache())
        integrate_s = time.perf_counter() - t0
        env, env_cpu = _frames(fit, cams, env_lights, preset)
        env[0] += integrate_s  # the first frame pays the integration too
        log(f"relight env map ({env_lights.count} directions): first {env[0]:.2f} s, later "
            f"median {statistics.median(env[1:]):.3f} s (CPU "
            f"{statistics.median(env_cpu[1:]):.3f} s)")
        p_first, p_second = _plugin_times(Path(tmp), surfels, cam, sky)
    log(f"surfel_relight env map mi.render: first {p_first:.2f} s, second {p_second:.3f} s "
        f"({p_first / p_second:.0f}x)")
    load1 = os.getloadavg()[0]
    res_d = {"surfels": n, "resolution": res, "frames": FRAMES, "variant": mi.variant(),
             "directional_frame_s": directional, "envmap_frame_s": env,
             "envmap_directions": env_lights.count,
             "directional_later_s": statistics.median(directional[1:]),
             "envmap_later_s": statistics.median(env[1:]),
             "directional_cpu_s": directional_cpu, "envmap_cpu_s": env_cpu,
             "directional_later_cpu_s": statistics.median(directional_cpu[1:]),
             "envmap_later_cpu_s": statistics.median(env_cpu[1:]),
             "threads": dr.thread_count(),
             "plugin_first_s": p_first, "plugin_second_s": p_second,
             "plugin_speedup": p_first / p_second, "loadavg": [load0, load1],
             "targets": TARGETS}
    res_d["met"] = {"directional": res_d["directional_later_s"] <= TARGETS[
        "directional_later_s"], "envmap": res_d["envmap_later_s"] <= TARGETS["envmap_later_s"],
        "plugin": res_d["plugin_speedup"] >= TARGETS["plugin_speedup"]}
    write_json(Path(out) / "relight.json", res_d)
    md = ["## relight", "",
          f"{n} surfels, {res}x{res} px, {FRAMES} orbit frames, {mi.variant()}; load "
          f"{load0:.2f} -> {load1:.2f}.", "",
          "| case | first frame (s) | later frames, median (s) | later frames, CPU s "
          "(all threads) | target | met (wall) |",
          "|---|---|---|---|---|---|",
          f"| directional (1 light) | {directional[0]:.3f} | {res_d['directional_later_s']:.3f}"
          f" | {res_d['directional_later_cpu_s']:.3f} | <= 0.1 s | "
          f"{res_d['met']['directional']} |",
          f"| env map ({env_lights.count} directions) | {env[0]:.2f} | "
          f"{res_d['envmap_later_s']:.3f} | {res_d['envmap_later_cpu_s']:.3f} | <= 1 s | "
          f"{res_d['met']['envmap']} |",
          f"| plugin env map, mi.render | {p_first:.2f} | {p_second:.3f} (second) | | "
          f">= 10x | {res_d['met']['plugin']} ({res_d['plugin_speedup']:.0f}x) |", ""]
    return {**res_d, "markdown": "\n".join(md)}
