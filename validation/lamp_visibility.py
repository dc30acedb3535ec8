"""Visibility from a lamp against Mitsuba ray tracing (the lab capture's sphere lamp).

For each scene (the embedded default and the bunny), the lamp of a lab capture
(``-D capture=lab``: a sphere of radius 0.15 object radii) at 6 and 12 object radii and
four directions, and the test spiral's views, the ground truth is Mitsuba's: the **hard**
visibility of the lamp's centre (a shadow ray to it) and the **soft** visibility, the
share of the lamp's disc, as each pixel sees it, that is unoccluded (``truth_samples``
points; ``dataset.generate.trace_ground_truth``), both 0 where the lamp's centre is below
the pixel's horizon. Our maps (``stages.visibility.lamp_maps``) are rendered from surfels
sampled on the true shapes (``validation.visibility.scene_surfels``) and looked up at the
ray-traced points and normals: the hard map from the lamp's centre (``lamp_samples`` 0)
scored by the shadow IoU (V < 0.5) against the hard truth, and maps over the lamp's disc
(each ``lamp_samples`` of ``samples``) by the mean absolute error against the soft truth,
over the object and base pixels and over the true penumbra alone (where the soft truth is
strictly between 0 and 1), and by the IoU of V < 0.5 against the soft truth < 0.5. The maps have the
visibility settings of each ``--preset`` (default: ``cpu-small``, what a run uses, and the
paper's).

    python -m validation.lamp_visibility --out validation-out/lamp [--quick]
        [--preset P ...] [--results results]
    python -m validation.visibility --lamp --out validation-out/lamp [...]   (the same)

Writes ``summary.json`` and ``README.md`` (the tables); with ``--results DIR`` also
``DIR/lamp_visibility.json``, the section of RESULTS.md (``scripts/results.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import drjit as dr
import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects the variant)
from mi_shadowgs.dataset.assets import shared_data_dir
from mi_shadowgs.dataset.cameras import test_cameras
from mi_shadowgs.dataset.generate import trace_ground_truth
from mi_shadowgs.dataset.layout import NERF_CAMERA_ANGLE_X
from mi_shadowgs.dataset.scene import load_scene
from mi_shadowgs.io.atomic import write_json, write_text
from mi_shadowgs.presets import visibility_config as get_visibility_config
from mi_shadowgs.stages.visibility.shadow_maps import (
    SceneBounds,
    VisibilityConfig,
    mean_camera_distance,
    render_shadow_maps,
)
from validation import claim_out, fail
from validation.visibility import REPO, ValidationConfig, iou, scene_surfels

STUDY = "validation.lamp_visibility"
# the bunny's mesh: $MI_SHADOWGS_SHARED_DATA, else ../shared/data beside the repository
BUNNY = shared_data_dir() / "meshes" / "bunny" / "bunny.ply"


@dataclasses.dataclass(frozen=True)
class LampValidationConfig:
    """Sizes of the lamp validation; ``quick`` is a smoke run."""

    n_views: int = 8  # views on the test spiral
    resolution: int = 128  # view width = height (the cpu-small dataset's)
    camera_distance: float = 4.0  # as the dataset generator (object radius 1)
    object_surfels: int = 20_000  # sampled on the object's shapes
    base_surfels: int = 4_000  # on the base near the object
    distances: tuple = (6.0, 12.0)  # lamp distance, object radii
    # lamp radius, object radii: the lab capture's, and a large lamp whose penumbrae span
    # several pixels (the lab lamp's are about one pixel wide at 128^2)
    radii: tuple = (0.15, 0.5)
    # lamp directions (azimuth, elevation, degrees): the lab capture's and three others
    directions: tuple = ((35.0, 50.0), (110.0, 35.0), (200.0, 20.0), (290.0, 65.0))
    samples: tuple = (4, 8, 16, 32)  # lamp_samples of the soft maps
    truth_samples: int = 64  # points of the lamp's disc in the soft truth


QUICK = LampValidationConfig(n_views=2, resolution=64, object_surfels=6_000,
                             base_surfels=1_500, directions=((35.0, 50.0), (200.0, 20.0)),
                             radii=(0.15,), samples=(4, 16), truth_samples=32)


def scenes(bunny: Path = BUNNY) -> list[tuple[str, Path, dict]]:
    """(name, scene XML, overrides) of the scenes: the default, and the bunny when its mesh
    is there."""
    out = [("default", REPO / "mi_shadowgs" / "scenes" / "default.xml", {})]
    if Path(bunny).is_file():
        out.append(("bunny", REPO / "mi_shadowgs" / "scenes" / "mesh.xml",
                    {"mesh": str(bunny)}))
    return out


def lamp_truth(setup, cams, cfg: LampValidationConfig) -> dict:
    """The traced truth of ``setup``'s lamp for ``cams``: receivers (points, normals as
    Dr.Jit arrays per view), mask [V, H, W], the hard shadow [V, H, W] bool and the soft
    visibility [V, H, W], both with the horizon of the lamp's centre."""
    from validation.visibility import traced_receivers

    lamp = setup.lights[0]
    gt = trace_ground_truth(setup, cams, [lamp], lamp_samples=cfg.truth_samples)
    points, normals = traced_receivers(gt, cams)
    pts = np.stack([np.asarray(p, np.float64).reshape(3, -1).T for p in points])  # [V, P, 3]
    to_lamp = np.asarray(lamp.position) - pts
    shape = gt["mask"].shape
    facing = (np.einsum("vpk,vpk->vp", gt["normal"].reshape(len(cams), -1, 3), to_lamp) > 0
              ).reshape(shape)
    return {"points": points, "normals": normals, "mask": gt["mask"].astype(bool),
            "hard_shadow": (gt["visibility"][..., 0] < 0.5) | ~facing,
            "soft": np.where(facing, gt["visibility_soft"][..., 0], 0.0), "lamp": lamp}


def _timed(fn):
    dr.sync_thread()
    t0 = time.perf_counter()
    out = fn()
    dr.sync_thread()
    return out, time.perf_counter() - t0


def evaluate_maps(surfels, bounds: SceneBounds, truth: dict, vc: VisibilityConfig) -> tuple:
    """(V [V, H, W], map seconds, lookup seconds per view) of the lamp's maps with ``vc``."""
    lamp = truth["lamp"]
    pos = np.asarray(lamp.position, np.float64)[None]
    d = (pos - np.asarray(bounds.center)) / np.linalg.norm(pos - np.asarray(bounds.center))
    maps, t_map = _timed(lambda: render_shadow_maps(surfels, d, bounds, vc, positions=pos,
                                                    radii=np.array([lamp.radius])))
    shape = truth["mask"].shape
    vis, t_look = [], 0.0
    for p, n in zip(truth["points"], truth["normals"], strict=True):
        v, t = _timed(lambda p=p, n=n: np.asarray(maps.evaluate(p, n), np.float64))
        vis.append(v.reshape(shape[1:]))
        t_look += t
    return np.stack(vis), t_map, t_look / len(vis)


def soft_scores(vis: np.ndarray, truth: dict) -> dict:
    """Soft V against the soft truth inside the mask: mean absolute error over every
    pixel and over the true penumbra (strictly between 0 and 1), and the IoU of V < 0.5."""
    m = truth["mask"]
    soft = truth["soft"]
    err = np.abs(vis - soft)[m]
    pen = ((soft > 0) & (soft < 1))[m]
    return {"soft_mae": float(err.mean()),
            "penumbra_mae": float(err[pen].mean()) if pen.any() else float("nan"),
            "penumbra_pixels": int(pen.sum()),
            "soft_iou": iou((vis < 0.5)[m], (soft < 0.5)[m])}


def case_rows(name: str, setup, surfels, cfg: LampValidationConfig, base: VisibilityConfig,
              preset: str, samples: tuple) -> list[dict]:
    """One lamp case's rows: the hard map, then each of ``samples`` (lamp_samples). The
    times are of warm kernels (a first lookup compiles them)."""
    cams = test_cameras(cfg.n_views, setup.object_center, cfg.camera_distance,
                        NERF_CAMERA_ANGLE_X, cfg.resolution, cfg.resolution, 15.0, 60.0)
    truth = lamp_truth(setup, cams, cfg)
    bounds = SceneBounds(tuple(np.asarray(setup.object_center, float).tolist()),
                         float(setup.object_radius),
                         mean_camera_distance(cams, setup.object_center))
    lamp = truth["lamp"]
    head = {"scene": name, "preset": preset, "distance": lamp.distance / setup.object_radius,
            "radius": lamp.radius / setup.object_radius,
            "azimuth": lamp.azimuth_deg, "elevation": lamp.elevation_deg,
            "shadow_pixels": int((truth["hard_shadow"] & truth["mask"]).sum()),
            "directional_iou": directional_iou(setup, cams, surfels, bounds, base, truth)}
    rows = []
    evaluate_maps(surfels, bounds, truth, dataclasses.replace(base, lamp_samples=1))
    for n in (0, *samples):
        vis, t_map, t_look = evaluate_maps(surfels, bounds, truth,
                                           dataclasses.replace(base, lamp_samples=n))
        m = truth["mask"]
        row = {**head, "lamp_samples": n,
               "hard_iou": iou((vis < 0.5)[m], truth["hard_shadow"][m]),
               **soft_scores(vis, truth), "maps_s": t_map, "lookup_ms_per_view": 1e3 * t_look}
        rows.append(row)
    return rows


def directional_iou(setup, cams, surfels, bounds: SceneBounds, base: VisibilityConfig,
                    truth: dict) -> float:
    """The directional maps' shadow IoU on the same views under a directional light of the
    lamp's direction (from the object's centre): what the method scores without the lamp."""
    from validation.visibility import make_lights, truth_shadow

    lamp = truth["lamp"]
    lights, dirs = make_lights([(lamp.azimuth_deg, lamp.elevation_deg)])
    shadow = truth_shadow(trace_ground_truth(setup, cams, lights), dirs)[..., 0]
    maps = render_shadow_maps(surfels, dirs, bounds, base)
    m = truth["mask"]
    vis = np.stack([np.asarray(maps.evaluate(p, n), np.float64).reshape(m.shape[1:])
                    for p, n in zip(truth["points"], truth["normals"], strict=True)])
    return iou((vis < 0.5)[m], shadow[m])


def _mean(rows: list[dict], key: str) -> float:
    vals = [r[key] for r in rows if r[key] == r[key]]  # NaN: no penumbra
    return float(np.mean(vals)) if vals else float("nan")


def tables(rows: list[dict], default_samples: int) -> dict:
    """The summary tables: per scene, distance and preset (means over the lamp's
    directions), and the samples sweep (means over every case)."""
    main, sweep = [], []
    keys = sorted({(r["preset"], r["radius"], r["scene"], r["distance"]) for r in rows},
                  key=lambda k: (k[0] != "cpu-small", k[0], k[1], k[2] != "default", k[2],
                                 k[3]))
    for preset, radius, scene, dist in keys:
        group = [r for r in rows if (r["preset"], r["radius"], r["scene"], r["distance"]) ==
                 (preset, radius, scene, dist)]
        hard = [r for r in group if r["lamp_samples"] == 0]
        soft = [r for r in group if r["lamp_samples"] == default_samples]
        main.append({"preset": preset, "scene": scene, "distance": dist, "radius": radius,
                     "lamps": len(hard), "hard_iou": _mean(hard, "hard_iou"),
                     "hard_iou_min": min(r["hard_iou"] for r in hard),
                     "directional_iou": _mean(hard, "directional_iou"),
                     "soft_iou": _mean(soft, "soft_iou"), "soft_mae": _mean(soft, "soft_mae"),
                     "penumbra_mae": _mean(soft, "penumbra_mae"),
                     "hard_map_penumbra_mae": _mean(hard, "penumbra_mae")})
    for preset, radius in sorted({(r["preset"], r["radius"]) for r in rows},
                                 key=lambda k: (k[0] != "cpu-small", k)):
        for samples in sorted({r["lamp_samples"] for r in rows if r["preset"] == preset}):
            group = [r for r in rows if (r["preset"], r["radius"], r["lamp_samples"]) ==
                     (preset, radius, samples)]
            sweep.append({"preset": preset, "radius": radius, "lamp_samples": samples,
                          "soft_mae": _mean(group, "soft_mae"),
                          "penumbra_mae": _mean(group, "penumbra_mae"),
                          "soft_iou": _mean(group, "soft_iou"),
                          "maps_s": _mean(group, "maps_s"),
                          "lookup_ms_per_view": _mean(group, "lookup_ms_per_view")})
    return {"main": main, "sweep": sweep}


MAIN_COLUMNS = ("settings", "lamp radius", "scene", "lamp distance", "lamps",
                "hard IoU (mean / min)", "directional IoU", "soft IoU", "soft MAE",
                "penumbra MAE", "penumbra MAE, hard map")
SWEEP_COLUMNS = ("settings", "lamp radius", "lamp_samples", "soft MAE", "penumbra MAE",
                 "soft IoU", "maps s", "lookup ms/view")


def table_rows(t: dict) -> tuple[list[list[str]], list[list[str]]]:
    main = [[r["preset"], f"{r['radius']:g}", r["scene"], f"{r['distance']:g}", str(r["lamps"]),
             f"{r['hard_iou']:.3f} / {r['hard_iou_min']:.3f}",
             f"{r['directional_iou']:.3f}", f"{r['soft_iou']:.3f}",
             f"{r['soft_mae']:.4f}", f"{r['penumbra_mae']:.3f}",
             f"{r['hard_map_penumbra_mae']:.3f}"] for r in t["main"]]
    sweep = [[r["preset"], f"{r['radius']:g}", str(r["lamp_samples"]), f"{r['soft_mae']:.4f}",
              f"{r['penumbra_mae']:.3f}", f"{r['soft_iou']:.3f}", f"{r['maps_s']:.2f}",
              f"{r['lookup_ms_per_view']:.1f}"] for r in t["sweep"]]
    return main, sweep


def markdown(columns, rows) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def _joined(values) -> str:
    return " and ".join(f"{v:g}" for v in values)


def result_doc(summary: dict, command: str) -> dict:
    """The RESULTS.md section (``scripts/results.py``'s schema) of a summary."""
    main, sweep = table_rows(summary["tables"])
    cfg = summary["config"]
    return {
        "order": 7, "title": "Shadow maps from a lamp against Mitsuba's ray-traced visibility",
        "command": command, "produced_by": f"{command} --results results",
        "machine": summary["device"], "commit": summary["commit"][:7], "date": summary["date"],
        "text": [f"A lab capture's sphere lamp of radius {_joined(cfg['radii'])} object radii "
                 f"(the lab capture's: 0.15) at {_joined(cfg['distances'])} object radii, "
                 f"{len(cfg['directions'])} directions (azimuth, elevation: "
                 f"{[list(d) for d in cfg['directions']]}); "
                 f"{cfg['n_views']} test-spiral views at {cfg['resolution']}^2; surfels sampled "
                 "on the true shapes; receivers ray-traced. Hard: the map from the lamp's "
                 "centre against a shadow ray to it (shadow IoU, V < 0.5); directional IoU: "
                 "the directional maps on the same views under a directional light of the "
                 "lamp's direction, against its traced shadows. Soft: the maps over "
                 f"the lamp's disc (lamp_samples {summary['default_samples']}) against the "
                 f"unoccluded share of the disc ({cfg['truth_samples']} points), mean absolute "
                 "error over the object and base pixels and over the penumbra alone. "
                 "Settings: each preset's visibility settings (cpu-small: 512^2 maps, a "
                 "one-texel bias and the occluder layer's slack; paper: 512^2, tau 8e-4)."],
        "notes": [f"Times on a machine shared with other jobs (load average "
                  f"{summary['loadavg'][0]:.0f}): compare them with each other only."],
        "tables": [{"columns": list(MAIN_COLUMNS), "rows": main},
                   {"caption": "Soft shadows by lamp_samples (mean over every lamp; 0: the "
                               "hard map from the centre).",
                    "columns": list(SWEEP_COLUMNS), "rows": sweep}],
    }


def run(out_dir, quick: bool = False, presets=("cpu-small", "paper"), quiet: bool = False,
        results: str | None = None, command: str = "python -m validation.lamp_visibility",
        bunny: Path = BUNNY) -> dict:
    """Everything above, written into ``out_dir``; returns the summary with a
    ``markdown`` entry."""
    import mitsuba as mi

    from mi_shadowgs.io.provenance import device_name, git_commit

    cfg = QUICK if quick else LampValidationConfig()
    bases = {p: get_visibility_config(p) for p in presets}  # a bad name: ValueError
    default_samples = VisibilityConfig().lamp_samples
    if default_samples not in cfg.samples:
        raise ValueError(f"the samples {cfg.samples} lack the default {default_samples}")
    out = claim_out(out_dir, STUDY, ("summary.json",))
    t0 = time.perf_counter()
    surf_cfg = dataclasses.replace(ValidationConfig(), object_surfels=cfg.object_surfels,
                                   base_surfels=cfg.base_surfels)
    rows = []
    cases = [(name, path, overrides, dist, radius, az, el)
             for name, path, overrides in scenes(bunny)
             for radius in cfg.radii for dist in cfg.distances for az, el in cfg.directions]
    surfels = {}
    for name, path, overrides, dist, radius, az, el in cases:
        if name not in surfels:
            surfels[name] = scene_surfels(load_scene(path, overrides or None), surf_cfg)
        setup = load_scene(path, {**overrides, "capture": "lab", "lamp_distance": f"{dist:g}",
                                  "lamp_radius": f"{radius:g}", "lamp_azimuth": f"{az:g}",
                                  "lamp_elevation": f"{el:g}"})
        for i, (preset, base) in enumerate(bases.items()):
            # the first settings get the samples sweep, the others the default alone
            samples = cfg.samples if i == 0 else (default_samples,)
            rows += case_rows(name, setup, surfels[name], cfg, base, preset, samples)
            if not quiet:
                r = rows[-len(samples) - 1]
                print(f"{preset} {name} radius {radius:g} d={dist:g} az={az:g} el={el:g}: "
                      f"hard IoU {r['hard_iou']:.3f}", flush=True)
    t = tables(rows, default_samples)
    main, sweep = table_rows(t)
    notes = [] if Path(bunny).is_file() else [f"bunny skipped: {bunny} is absent"]
    md = "\n".join([f"## Visibility from a lamp ({'quick' if quick else 'full'})", "",
                    markdown(MAIN_COLUMNS, main), "", markdown(SWEEP_COLUMNS, sweep), ""]
                   + [f"Note: {n}" for n in notes])
    summary = {"config": dataclasses.asdict(cfg), "presets": list(presets),
               "default_samples": default_samples, "rows": rows, "tables": t, "notes": notes,
               "device": device_name(mi.variant()), "commit": git_commit(),
               "date": time.strftime("%Y-%m-%d"), "wall_s": time.perf_counter() - t0,
               "loadavg": list(os.getloadavg())}
    write_json(out / "summary.json", summary)
    write_text(out / "README.md", md + "\n")
    if results is not None:
        from scripts.results import write_result

        write_result(Path(results) / "lamp_visibility.json", result_doc(summary, command))
    summary["markdown"] = md
    return summary


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--preset", action="append", default=None,
                    help="the maps' visibility settings of this preset (repeat; default: "
                         "cpu-small and paper)")
    ap.add_argument("--results", default=None,
                    help="also write DIR/lamp_visibility.json, the RESULTS.md section")
    ap.add_argument("--bunny", default=str(BUNNY),
                    help="the bunny's mesh (default: the shared data's; absent: skipped)")


def main(argv=None, command: str = "python -m validation.lamp_visibility") -> int:
    ap = argparse.ArgumentParser(prog=command, description="Shadow maps from a lamp against "
                                 "Mitsuba's ray-traced visibility (hard and soft).")
    ap.add_argument("--out", required=True, help="output folder (new, or this study's)")
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    add_arguments(ap)
    args = ap.parse_args(argv)
    return run_args(args, command)


def run_args(args, command: str) -> int:
    """``run`` from parsed arguments (``--out``, ``--quick``, ``--quiet``, and
    ``add_arguments``'); exit 2 on bad input."""
    presets = tuple(args.preset or ("cpu-small", "paper"))
    flags = " --quick" if args.quick else ""
    flags += "".join(f" --preset {p}" for p in args.preset or ())
    try:
        summary = run(args.out, args.quick, presets, args.quiet, args.results,
                      f"{command} --out OUT{flags}", Path(args.bunny))
    except (ValueError, FileNotFoundError) as e:
        fail(str(e))
    print(summary["markdown"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
