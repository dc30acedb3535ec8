"""The light fit under light pairs all over the hemisphere.

Eight pairs of opposing directional lights (irradiance 3.0 and 1.5, so each carries at
least a third of it): the strong light at azimuths 0-315 deg in steps of 45, elevations
15-75 deg, the weak one opposite in azimuth with the complementary elevation (15-75 deg).
Each pair runs the whole method (``validation.pipeline.run_scene``, cpu-small, no
ablations) on each scene; the table gives every true light's angular error to the fitted
light set, the fitted light count and the spurious irradiance, and whether every light
carrying at least ``SHARE`` of the irradiance is fitted within ``MAX_ERROR_DEG``::

    python -m validation.light_sweep --out OUT [--scene default --scene bunny]
        [--pair s0 ...] [--threads N] [--table-only]

Runs live in ``OUT/<scene>-<pair>/`` and are resumed, not redone. Writes
``OUT/light_sweep.json`` and ``.md`` from every finished row.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from validation import claim_out, fail

SHARE = 0.25  # lights carrying at least this share of the irradiance must be found ...
MAX_ERROR_DEG = 3.0  # ... within this angle (the acceptance)
STRONG, WEAK = 3.0, 1.5  # irradiance (W/m^2) of the two lights
# (azimuth, elevation) of the strong light per pair; the weak one is at azimuth + 180 and
# elevation 90 - elevation (clipped to 15-75)
STRONG_LIGHTS = ((0, 15), (45, 25), (90, 35), (135, 45), (180, 55), (225, 65), (270, 75),
                 (315, 30))


def sweep_pairs() -> dict[str, dict[str, str]]:
    """Pair name -> scene-XML overrides (as ``validation.pipeline.LIGHT_PAIRS``)."""
    pairs = {}
    for i, (az, el) in enumerate(STRONG_LIGHTS):
        weak_el = min(75, max(15, 90 - el))
        pairs[f"s{i}"] = {
            "light0_azimuth": str(az), "light0_elevation": str(el),
            "light0_irradiance": str(STRONG),
            "light1_azimuth": str((az + 180) % 360), "light1_elevation": str(weak_el),
            "light1_irradiance": str(WEAK)}
    return pairs


def sweep_row(row: dict) -> dict:
    """The light-fit figures of one finished ``validation.pipeline`` row."""
    pair = row["light_pair"]
    irr = np.array([float(pair[f"light{k}_irradiance"]) for k in range(2)])
    share = irr / irr.sum()
    full = row["variants"]["full"]
    errors = full.get("angular_error_deg") or [float("nan")] * 2
    errors = [float("nan") if e is None else float(e) for e in errors]
    needed = [k for k in range(2) if share[k] >= SHARE]
    ok = all(np.isfinite(errors[k]) and errors[k] <= MAX_ERROR_DEG for k in needed)
    return {"scene": row["scene"], "pair": row["lights"],
            "lights": [(float(pair[f"light{k}_azimuth"]), float(pair[f"light{k}_elevation"]),
                        float(share[k])) for k in range(2)],
            "angular_error_deg": errors, "fitted_lights": full.get("fitted_lights"),
            "spurious_irradiance_fraction": full.get("spurious_irradiance_fraction"),
            "light_cosine": full.get("light_cosine"), "shadow_iou": full.get("shadow_iou"),
            "shadow_iou_decided": full.get("shadow_iou_decided"),
            "albedo_psnr": full.get("albedo_psnr"), "relight_psnr": full.get("relight_psnr"),
            "within": bool(ok), "wall_s": row.get("wall_s")}


def markdown(rows: list[dict]) -> str:
    lines = ["| scene | pair | strong light az/el | weak light az/el | angular error deg "
             "(strong / weak) | fitted | spurious share | light cos | shadow IoU | shadow IoU "
             f"(decided) | within {MAX_ERROR_DEG:g} deg |", "|" + "---|" * 11]
    for r in rows:
        (a0, e0, _), (a1, e1, _) = r["lights"]
        err = " / ".join("lost" if not np.isfinite(e) else f"{e:.1f}"
                         for e in r["angular_error_deg"])
        # rows evaluated before the decided figure existed have none
        decided = "n/a" if r.get("shadow_iou_decided") is None else \
            f"{r['shadow_iou_decided']:.3f}"
        lines.append(f"| {r['scene']} | {r['pair']} | {a0:g}/{e0:g} | {a1:g}/{e1:g} | {err} | "
                     f"{r['fitted_lights']} | {r['spurious_irradiance_fraction']:.2f} | "
                     f"{r['light_cosine']:.3f} | {r['shadow_iou']:.3f} | {decided} | "
                     f"{'yes' if r['within'] else '**no**'} |")
    n_ok = sum(r["within"] for r in rows)
    lines.append(f"\n{n_ok} of {len(rows)} scene/pairs have every light with >= "
                 f"{SHARE:.0%} of the irradiance within {MAX_ERROR_DEG:g} deg.")
    return "\n".join(lines) + "\n"


def gather(out: Path) -> list[dict]:
    pairs = list(sweep_pairs())
    rows = [json.loads(p.read_text()) for p in sorted(out.glob("*/row.json"))]
    rows = [sweep_row(r) for r in rows if r["lights"] in pairs]
    return sorted(rows, key=lambda r: (r["scene"], pairs.index(r["pair"])))


def main(argv=None) -> int:
    from validation.pipeline import available_scenes, run_scene

    pairs = sweep_pairs()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--scene", action="append", default=None,
                    help="scene (repeatable; default: default and bunny)")
    ap.add_argument("--pair", action="append", choices=sorted(pairs), default=None)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args(argv)
    claim_out(args.out, "validation.light_sweep", ('light_sweep.json',))
    from mi_shadowgs.io.atomic import write_json, write_text

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.table_only:
        import drjit as dr

        if args.threads:
            dr.set_thread_count(args.threads)
        avail = available_scenes()
        scenes = args.scene or ["default", "bunny"]
        missing = [s for s in scenes if s not in avail]
        if missing:
            fail(f"--scene {missing[0]}: not available (meshes under "
                 "../shared/data/meshes)")
        for name in args.pair or list(pairs):  # pair by pair: both scenes see each pair
            for scene in scenes:
                run_scene(scene, avail[scene], out, name, ablations=False, pair=pairs[name])
    rows = gather(out)
    write_json(out / "light_sweep.json", rows)
    md = markdown(rows)
    write_text(out / "light_sweep.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
