"""How much a lamp's place shows in the views: what stage 4 can read its distance from.

For each scene (the embedded default and the bunny) and each lamp of a lab capture
(``-D capture=lab``: a point at 6 and 12 object radii, four directions), Mitsuba traces the
true scene from the test spiral's views at the imported photos' width (``cpu-small``: 128
pixels) and compares the lamp with the lamp moved:

- **Shadow edges.** Moved 5% of its distance along its direction, or 1 degree across it (in
  elevation, and in azimuth), the lamp's hard cast shadows move; the mean move of their
  edges, in pixels, is the pixels whose shadow flips over the edges' length
  (``edge_shift``).
- **Fall-off.** Moved 5% of its distance, the lamp's unshadowed irradiance changes shape
  across the receivers it lights in both places: the mean and the 95th percentile of
  ``|ratio / median(ratio) - 1|`` (its scale is free: the fit takes the light's strength).

A fit places the lamp no better than its cues allow: where 5% of the distance moves the
edges far less than a pixel and less than the direction's bound does, and changes the
shading less than the photos' gains, noise and a print on the receiver, the position is
not in the views at that precision.

    python -m validation.lamp_cues --out validation-out/cues [--quick] [--results results]

Writes ``summary.json`` and ``README.md``; with ``--results DIR`` also
``DIR/lamp_cues.json``, the section of RESULTS.md (``scripts/results.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM, selects the variant)
from mi_shadowgs.dataset.cameras import test_cameras
from mi_shadowgs.dataset.generate import trace_ground_truth
from mi_shadowgs.dataset.layout import NERF_CAMERA_ANGLE_X
from mi_shadowgs.dataset.scene import load_scene
from mi_shadowgs.io.atomic import write_json, write_text
from validation import claim_out, fail
from validation.lamp_visibility import BUNNY, markdown, scenes

STUDY = "validation.lamp_cues"


@dataclasses.dataclass(frozen=True)
class CueConfig:
    """Sizes of the study; ``QUICK`` is a smoke run."""

    n_views: int = 8  # views on the test spiral
    resolution: int = 128  # view width = height (cpu-small's import of 640x480 photos)
    camera_distance: float = 4.0  # as the dataset generator (object radius 1)
    distances: tuple = (6.0, 12.0)  # lamp distance, object radii
    # lamp directions (azimuth, elevation, degrees): the lab capture's and three others
    directions: tuple = ((35.0, 50.0), (110.0, 35.0), (200.0, 20.0), (290.0, 65.0))
    distance_step: float = 0.05  # the move along the direction, a share of the distance
    angle_step_deg: float = 1.0  # the move across it


QUICK = CueConfig(n_views=2, resolution=64, distances=(6.0,), directions=((35.0, 50.0),))


def edge_shift(before: np.ndarray, after: np.ndarray, mask: np.ndarray) -> float:
    """Mean move, in pixels, of the edges of the boolean images ``before`` [V, H, W]
    inside ``mask`` when they become ``after``: the pixels that flip over the edges' length.
    The length is the count of 4-neighbour pairs that straddle an edge times pi / 4 (a line
    at a uniformly random angle crosses 4 / pi of them per pixel of its length)."""
    crossings = 0
    for axis in (1, 2):
        a, b = _pairs(before, axis), _pairs(mask, axis)
        crossings += int(np.count_nonzero((a[0] != a[1]) & b[0] & b[1]))
    if crossings == 0:
        return float("nan")
    flips = int(np.count_nonzero((before != after) & mask))
    return flips / (crossings * math.pi / 4.0)


def _pairs(img: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    n = img.shape[axis]
    return img.take(range(n - 1), axis=axis), img.take(range(1, n), axis=axis)


def falloff_change(before: np.ndarray, after: np.ndarray, lit: np.ndarray) -> tuple:
    """(mean, 95th percentile) of ``|r / median(r) - 1|`` with r = after / before, the
    irradiance [V, H, W] at the pixels ``lit`` in both."""
    r = after[lit] / before[lit]
    dev = np.abs(r / np.median(r) - 1.0)
    return float(dev.mean()), float(np.percentile(dev, 95))


def moved_lamps(lamp, center: np.ndarray, cfg: CueConfig) -> list:
    """The lamp, then moved: farther and nearer by ``distance_step``, then ``angle_step``
    across in elevation and in azimuth (great-circle degrees), each a point lamp."""
    center = np.asarray(center, np.float64)
    dist = float(np.linalg.norm(np.asarray(lamp.position) - center))
    d = (np.asarray(lamp.position) - center) / dist
    up = np.array([0.0, 1.0, 0.0])
    across_az = np.cross(up, d)
    across_az /= np.linalg.norm(across_az)
    across_el = np.cross(d, across_az)
    a = math.radians(cfg.angle_step_deg)
    places = [("lamp", d, dist), ("farther", d, dist * (1 + cfg.distance_step)),
              ("nearer", d, dist * (1 - cfg.distance_step)),
              ("elevation", math.cos(a) * d + math.sin(a) * across_el, dist),
              ("azimuth", math.cos(a) * d + math.sin(a) * across_az, dist)]
    return [dataclasses.replace(lamp, name=name, radius=0.0, direction=tuple(u.tolist()),
                                position=tuple((center + u * r).tolist()), distance=r)
            for name, u, r in places]


def case_row(name: str, setup, cfg: CueConfig) -> dict:
    """One lamp's cues on the test spiral's views."""
    cams = test_cameras(cfg.n_views, setup.object_center, cfg.camera_distance,
                        NERF_CAMERA_ANGLE_X, cfg.resolution, cfg.resolution, 15.0, 60.0)
    lamp = setup.lights[0]
    lamps = moved_lamps(lamp, setup.object_center, cfg)
    gt = trace_ground_truth(setup, cams, lamps, lamp_samples=0)
    mask = gt["mask"].astype(bool)
    irr = gt["irradiance"].mean(axis=-1)  # [V, H, W, L]: E cos V, falling off as 1/r^2
    shadow = ~(irr > 0)  # occluded, or the lamp below the pixel's horizon
    row = {"scene": name, "distance": lamp.distance / setup.object_radius,
           "azimuth": lamp.azimuth_deg, "elevation": lamp.elevation_deg,
           "shadow_pixels": int(np.count_nonzero(shadow[..., 0] & mask))}
    for k, key in enumerate(("farther", "nearer", "elevation", "azimuth"), start=1):
        row[f"shift_{key}"] = edge_shift(shadow[..., 0], shadow[..., k], mask)
    lit = mask & ~shadow[..., 0] & ~shadow[..., 1]
    row["falloff_mean"], row["falloff_p95"] = falloff_change(irr[..., 0], irr[..., 1], lit)
    return row


def tables(rows: list[dict]) -> list[dict]:
    """Per scene and distance, the means over the lamp's directions."""
    out = []
    for scene, dist in dict.fromkeys((r["scene"], r["distance"]) for r in rows):
        group = [r for r in rows if (r["scene"], r["distance"]) == (scene, dist)]
        m = {k: float(np.nanmean([r[k] for r in group])) for k in group[0] if
             k.startswith(("shift_", "falloff_"))}
        along = (m["shift_farther"] + m["shift_nearer"]) / 2
        across = (m["shift_elevation"] + m["shift_azimuth"]) / 2
        out.append({"scene": scene, "distance": dist, "lamps": len(group),
                    "along": along, "across": across, "degrees": along / across,
                    "falloff_mean": m["falloff_mean"], "falloff_p95": m["falloff_p95"]})
    return out


COLUMNS = ("scene", "lamp distance", "lamps", "edges' move per 5% of distance (px)",
           "edges' move per degree (px)", "5% of distance in degrees",
           "fall-off change per 5% (mean / p95)")


def table_rows(t: list[dict]) -> list[list[str]]:
    return [[r["scene"], f"{r['distance']:g}", str(r["lamps"]), f"{r['along']:.3f}",
             f"{r['across']:.3f}", f"{r['degrees']:.2f}",
             f"{100 * r['falloff_mean']:.2f}% / {100 * r['falloff_p95']:.2f}%"] for r in t]


def result_doc(summary: dict, command: str) -> dict:
    """The RESULTS.md section (``scripts/results.py``'s schema) of a summary."""
    cfg = summary["config"]
    return {
        "order": 5, "title": "How much a lamp's place shows in the views",
        "command": command, "produced_by": f"{command} --results results",
        "machine": summary["device"], "commit": summary["commit"][:7], "date": summary["date"],
        "text": [f"A lab capture's lamp (as a point) at {cfg['distances']} object radii in "
                 f"{len(cfg['directions'])} directions, {cfg['n_views']} test-spiral views at "
                 f"{cfg['resolution']}^2 (the width of `cpu-small`'s import of the lab "
                 "photos), traced by Mitsuba. The mean move of the cast shadows' edges when "
                 f"the lamp moves {100 * cfg['distance_step']:g}% of its distance along its "
                 f"direction and {cfg['angle_step_deg']:g} degree across it, and the change "
                 "in shape of its irradiance over the receivers lit in both places (one "
                 "scale taken out).",
                 "The lab table's bounds are 2 degrees on the direction and 5% of the "
                 "distance on the position. Here 5% of the distance moves the shadows' edges "
                 "as far as the 'degrees' column's share of a degree across, a few hundredths "
                 "of a pixel, and reshapes the light by about 1%: less than the fitted gains' "
                 "worst error (about 2%), the lab photos' noise at mid grey (1.4-2.2%) and "
                 "the mat's print (0.11 to 0.70, a standard deviation of 44% of its mean)."],
        "tables": [{"columns": list(COLUMNS), "rows": table_rows(summary["tables"])}],
    }


def run(out_dir, quick: bool = False, quiet: bool = False, results: str | None = None,
        command: str = "python -m validation.lamp_cues", bunny: Path = BUNNY) -> dict:
    """Everything above, written into ``out_dir``; returns the summary with a
    ``markdown`` entry."""
    import mitsuba as mi

    from mi_shadowgs.io.provenance import device_name, git_commit

    cfg = QUICK if quick else CueConfig()
    out = claim_out(out_dir, STUDY, ("summary.json",))
    t0 = time.perf_counter()
    rows = []
    for name, path, overrides in scenes(bunny)[:1 if quick else None]:
        for dist in cfg.distances:
            for az, el in cfg.directions:
                setup = load_scene(path, {**overrides, "capture": "lab",
                                          "lamp_distance": f"{dist:g}", "lamp_radius": "0",
                                          "lamp_azimuth": f"{az:g}",
                                          "lamp_elevation": f"{el:g}"})
                rows.append(case_row(name, setup, cfg))
                if not quiet:
                    r = rows[-1]
                    print(f"{name} d={dist:g} az={az:g} el={el:g}: edges move "
                          f"{(r['shift_farther'] + r['shift_nearer']) / 2:.3f} px per 5%, "
                          f"{(r['shift_elevation'] + r['shift_azimuth']) / 2:.3f} px per "
                          "degree", flush=True)
    t = tables(rows)
    notes = [] if Path(bunny).is_file() or quick else [f"bunny skipped: {bunny} is absent"]
    md = "\n".join([f"## How much a lamp's place shows ({'quick' if quick else 'full'})", "",
                    markdown(COLUMNS, table_rows(t)), ""] + [f"Note: {n}" for n in notes])
    summary = {"config": dataclasses.asdict(cfg), "rows": rows, "tables": t, "notes": notes,
               "device": device_name(mi.variant()), "commit": git_commit(),
               "date": time.strftime("%Y-%m-%d"), "wall_s": time.perf_counter() - t0}
    write_json(out / "summary.json", summary)
    write_text(out / "README.md", md + "\n")
    if results is not None:
        from scripts.results import write_result

        write_result(Path(results) / "lamp_cues.json", result_doc(summary, command))
    summary["markdown"] = md
    return summary


def main(argv=None, command: str = "python -m validation.lamp_cues") -> int:
    ap = argparse.ArgumentParser(prog=command, description="How far a lab capture's shadows "
                                 "and shading move when its lamp moves (Mitsuba ray tracing).")
    ap.add_argument("--out", required=True, help="output folder (new, or this study's)")
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    ap.add_argument("--results", default=None,
                    help="also write DIR/lamp_cues.json, the RESULTS.md section")
    ap.add_argument("--bunny", default=str(BUNNY),
                    help="the bunny's mesh (default: the shared data's; absent: skipped)")
    args = ap.parse_args(argv)
    try:
        summary = run(args.out, args.quick, args.quiet, args.results,
                      f"{command} --out OUT" + (" --quick" if args.quick else ""),
                      Path(args.bunny))
    except (ValueError, FileNotFoundError) as e:
        fail(str(e))
    print(summary["markdown"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
