"""The viewer's frame time: a light change -> a new frame with recomputed shadows,
as ``mi-shadowgs view`` renders it (``ViewerSession.render``: the camera's cached G-buffer,
one new shadow map, the visibility lookup, Cook-Torrance shading, the read-back of the
image), at 128^2 and 256^2.

Model: a real run, ``$MI_SHADOWGS_VIEW_RUN`` or else ``runs/demo/run`` (``make demo``: a
cpu-small fit of the default scene, ~29k surfels, 512^2 shadow maps); where neither exists,
the raster workload's sphere on a plane with material channels (20k surfels; 5k with
``--quick``), said so in the summary.

Each resolution: a fresh session, 3 warm-up light changes (kernels compile), then FRAMES
light changes 3 degrees apart in azimuth (a slider drag: every one a new direction and so a
new shadow map). Reported: the median wall time and CPU time (all threads) of the full
frame (the run's shadow maps) and of the preview (half size, half-resolution maps) the page
shows while the slider moves, and of a camera move: the camera orbiting the model 5 degrees
a step about the vertical through its centre, the light unchanged (a new G-buffer with the
kernels compiled for the first pose, the light's shadow map reused), as the full frame and
as the preview the page shows at once while the camera moves (half the size: a quarter of
the pixels, ``viewer_server``). Targets: full frame
<= 0.15 s at 128^2 and <= 0.5 s at 256^2; camera move <= 0.2 s at 256^2.

    python -m benchmarks.run_all --out bench-out --only view
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from pathlib import Path

FRAMES = 12
WARMUP = 3
TARGETS = {128: 0.15, 256: 0.5}
MOVE_TARGETS = {256: 0.2}  # camera move, s
MOVES = 8
DEFAULT_RUN = Path(__file__).resolve().parents[1] / "runs" / "demo" / "run"


def _synthetic_run(folder: Path, n: int) -> Path:
    """The raster workload as a stage-4 run folder (material/full: model.ply, light.json),
    with the manifests a finished run has (the viewer reads only a fit its run lists)."""
    import numpy as np

    from benchmarks.workloads import WorkloadConfig, build_workload
    from mi_shadowgs.config import to_dict
    from mi_shadowgs.core.directions import direction_from_angles
    from mi_shadowgs.core.surfels import Surfels
    from mi_shadowgs.io.ply import save_ply
    from mi_shadowgs.io.provenance import Output, Provenance
    from mi_shadowgs.stages.relight.render import RelightConfig
    from mi_shadowgs.stages.visibility.shadow_maps import VisibilityConfig

    wl = build_workload(WorkloadConfig(n=n))
    channels = {"albedo": np.full((wl.n, 3), 0.6, np.float32),
                "roughness": np.full((wl.n, 1), 0.5, np.float32),
                "metallic": np.zeros((wl.n, 1), np.float32)}
    surfels = Surfels.from_numpy(wl.position, wl.scale, wl.rotation, wl.opacity, channels)
    run = folder / "run"
    with Output.open(run, "run", Provenance(), parts=("material",)) as top:
        top.add_part("material/full")
        settings = {"visibility": to_dict(VisibilityConfig()), "relight": to_dict(RelightConfig())}
        with Output.open(run / "material" / "full", "run", Provenance(settings=settings),
                         part_of=run) as out:
            save_ply(out.path("model.ply"), surfels)
            d = direction_from_angles(40.0, 45.0)
            out.path("light.json").write_text(json.dumps(
                {"radiance": [0.0] * 128, "active": [0], "directions": [d.tolist()],
                 "irradiance": [3.0], "specular": True, "use_visibility": True}))
            out.finish()
        top.finish()
    return run


def _light(az: float):
    from mi_shadowgs.stages.viewer import viewer

    return viewer.LightState((viewer.DirectionalLight(az % 360.0, 40.0, 3.0),))


def _timed(render) -> tuple[float, float, object]:
    """(wall s, CPU s, frame) of one render (the frame's numpy read-back syncs Dr.Jit)."""
    import drjit as dr

    dr.sync_thread()
    c0, t0 = time.process_time(), time.perf_counter()
    frame = render()
    wall = time.perf_counter() - t0
    return wall, time.process_time() - c0, frame


def _orbit(camera, centre, deg: float):
    """``camera`` turned by ``deg`` about the vertical through ``centre`` (an orbit drag)."""
    import dataclasses
    import math

    import numpy as np

    a = math.radians(deg)
    turn = np.eye(4)
    turn[[0, 0, 2, 2], [0, 2, 0, 2]] = [math.cos(a), math.sin(a), -math.sin(a), math.cos(a)]
    shift = np.eye(4)
    shift[:3, 3] = centre
    back = np.eye(4)
    back[:3, 3] = -np.asarray(centre)
    return dataclasses.replace(camera, c2w=shift @ turn @ back @ camera.c2w)


def _measure(run: Path, res: int, log) -> dict:
    from mi_shadowgs.stages.viewer import viewer

    session = viewer.ViewerSession(run)
    cam = session.default_camera(res, res)  # square: exactly res^2 pixels
    preview_cam = session.default_camera(res // 2, res // 2)
    preview_maps = max(64, session.vis_config.resolution // 2)
    az = 0.0
    for _ in range(WARMUP):  # compile every kernel of both paths
        az += 3.0
        session.render(cam, _light(az))
        session.render(preview_cam, _light(az + 1.0), shadow_resolution=preview_maps)
    full, full_cpu, prev, prev_cpu, maps = [], [], [], [], []
    for _ in range(FRAMES):
        az += 3.0
        w, c, f = _timed(lambda a=az: session.render(cam, _light(a)))
        full.append(w)
        full_cpu.append(c)
        maps.append(f.shadow_maps_rendered)
        w, c, _ = _timed(lambda a=az: session.render(
            preview_cam, _light(a + 1.0), shadow_resolution=preview_maps))
        prev.append(w)
        prev_cpu.append(c)
    # Camera moves under a light seen before: a new G-buffer, no new shadow map.
    centre = session.surfels.to_numpy()["position"].mean(0)
    moves, preview_moves, built = [], [], session.gbuffers.rendered
    for i in range(MOVES + 1):
        moved = _orbit(cam, centre, 5.0 * (i + 1))
        wall = _timed(lambda m=moved: session.render(m, _light(az)))[0]
        # What the page shows at once while the camera moves: the preview (half the size).
        small = _orbit(preview_cam, centre, 5.0 * (i + 1))
        wall_preview = _timed(lambda m=small: session.render(
            m, _light(az), shadow_resolution=preview_maps))[0]
        if i:  # the first: the kernels of a pose other than the warm-up's
            moves.append(wall)
            preview_moves.append(wall_preview)
    moved_built = session.gbuffers.rendered - built
    # A light change after the moves: the last pose's G-buffer reused.
    built = session.gbuffers.rendered
    session.render(moved, _light(az + 3.0))
    move_target = MOVE_TARGETS.get(res)
    out = {"resolution": res, "surfels": session.surfels.count,
           "shadow_map_resolution": session.vis_config.resolution,
           "preview_shadow_map_resolution": preview_maps, "frame_s": full,
           "frame_cpu_s": full_cpu, "preview_s": prev, "preview_cpu_s": prev_cpu,
           "camera_move_s": moves, "new_maps_per_change": maps,
           "camera_move_preview_s": preview_moves,
           "gbuffers_per_move": moved_built / (2 * (MOVES + 1)),
           "gbuffers_per_light_change": session.gbuffers.rendered - built,
           "median_s": statistics.median(full), "median_cpu_s": statistics.median(full_cpu),
           "preview_median_s": statistics.median(prev),
           "camera_move_median_s": statistics.median(moves),
           "camera_move_preview_median_s": statistics.median(preview_moves),
           "target_s": TARGETS[res], "camera_move_target_s": move_target}
    out["met"] = out["median_s"] <= TARGETS[res]
    out["camera_move_met"] = (None if move_target is None
                              else out["camera_move_median_s"] <= move_target)
    log(f"view {res}^2: light change {out['median_s'] * 1000:.0f} ms (CPU "
        f"{out['median_cpu_s'] * 1000:.0f} ms), preview {out['preview_median_s'] * 1000:.0f}"
        f" ms, camera move {out['camera_move_median_s'] * 1000:.0f} ms (preview "
        f"{out['camera_move_preview_median_s'] * 1000:.0f} ms)")
    return out


def run_suite(out: Path, preset: str = "paper", log=print) -> dict:
    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.io.atomic import write_json

    run = Path(os.environ.get("MI_SHADOWGS_VIEW_RUN", DEFAULT_RUN))
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        if (run / "material" / "full" / "model.ply").is_file():
            model = f"run {run}"
        else:
            n = 20_000 if preset == "paper" else 5_000
            model = (f"no run at {run} (make demo makes one): the raster workload's sphere "
                     "on a plane")
            run = _synthetic_run(Path(tmp), n)
        rows = [_measure(run, res, log) for res in sorted(TARGETS)]
    load1 = os.getloadavg()[0]
    result = {"model": model, "variant": mi.variant(), "threads": dr.thread_count(),
              "frames": FRAMES, "warmup": WARMUP, "loadavg": [load0, load1], "rows": rows}
    write_json(Path(out) / "view.json", result)
    md = ["## view", "",
          f"Light change -> new frame with recomputed shadows (`ViewerSession.render`), "
          f"{model}; {rows[0]['surfels']} surfels, {rows[0]['shadow_map_resolution']}^2 "
          f"shadow maps; median of {FRAMES} changes 3 degrees apart after {WARMUP} warm-up; "
          f"{mi.variant()}, {dr.thread_count()} threads; load {load0:.2f} -> {load1:.2f}.", "",
          "| frame | light change, wall (ms) | CPU, all threads (ms) | target | met | preview "
          "(half size, half-res maps) (ms) | camera move (ms) | target | met | camera move, "
          "preview (ms) |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        move_target = r.get("camera_move_target_s")
        md.append(f"| {r['resolution']}^2 | {r['median_s'] * 1000:.0f} | "
                  f"{r['median_cpu_s'] * 1000:.0f} | <= {r['target_s'] * 1000:.0f} | "
                  f"{r['met']} | {r['preview_median_s'] * 1000:.0f} | "
                  f"{r['camera_move_median_s'] * 1000:.0f} | "
                  + (f"<= {move_target * 1000:.0f} | {r['camera_move_met']} | "
                     if move_target else "| | ")
                  + f"{r['camera_move_preview_median_s'] * 1000:.0f} |")
    md.append("")
    return {**result, "markdown": "\n".join(md)}
