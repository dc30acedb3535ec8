"""The exported mesh asset, path-traced by Mitsuba, against ground truth.

    python -m validation.asset --run RUN --data DATA --out OUT [--spp 64] [--overwrite]

1. ``mi-shadowgs export RUN --format mesh`` into ``OUT/export`` (its wall time: the speed
   item, <= 60 s at cpu-small).
2. Chamfer distance of the exported object mesh to the ground-truth object (the shapes
   ``object*`` of the dataset's scene, loaded with the parameters ``dataset.json`` records):
   both surfaces point-sampled (area-uniform), the ground truth only where a training camera
   sees it (hidden contact faces, e.g. a block's underside on the base, cannot be recovered
   by any method); mean nearest-sample distance each way, their mean, as % of the object's
   diameter (2 x its bounding-sphere radius).
3. The exported ``scene.xml`` path-traced (Mitsuba ``path``, the dataset's ``max_depth``)
   under each directional relighting of ``lights.json`` in place of the fitted lights, the
   albedo attribute scaled by the same global per-channel factor stage 5 applies to our
   surfel relighting (albedo and light are recovered up to that scale). PSNR/SSIM against
   the ground-truth relit views on the dataset masks, beside the surfel relighting's scores
   from ``RUN/material/full/metrics.json``.

Writes ``OUT/asset.json`` (numbers, pass/fail per acceptance item, load average) and
``OUT/asset.png`` (per relighting: ground truth | path-traced exported asset | error). The
export (``OUT/export``), the Chamfer distance, the albedo scale and each relighting's
path-trace are units (``validation.units``: ``OUT/units/chamfer/``,
``OUT/units/albedo_scale/``, ``OUT/units/relight_<name>/`` with its ``scene.xml`` and
``renders/<view>.exr``): a killed call, run again, reuses what is finished and continues a
path-trace from its last view, when the inputs and settings are the same; it exits 2 naming
what differs otherwise (``--overwrite`` makes them again).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)
from mi_shadowgs.io.atomic import atomic_path, write_json, write_text
from mi_shadowgs.io.images import read_exr, write_exr
from validation import claim_out, fail
from validation.units import UNITS, run_unit, settings_of

STUDY = "validation.asset"
ACCEPT = {"chamfer_pct": 1.0, "psnr_gap_db": 2.0, "export_s": 60.0}
SAMPLES = 400_000  # points per surface: nearest-sample spacing ~0.5 % of the diameter


# -- geometry -------------------------------------------------------------------------------
def ground_truth_points(data: Path, cameras, n: int = SAMPLES, seed: int = 0) -> np.ndarray:
    """Area-uniform points [M, 3] on the dataset scene's ``object*`` shapes that at least one
    of ``cameras`` sees (unoccluded, front side)."""
    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.dataset.scene import dataset_scene

    scene = dataset_scene(data).scene  # as rendered: a mesh scene's parts, if it has them
    shapes = [s for s in scene.shapes() if s.id().startswith("object")]
    if not shapes:
        raise ValueError(f"{data / 'dataset.json'}: its scene has no object* shape")
    areas = np.array([float(s.surface_area()[0]) for s in shapes])
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(n, areas / areas.sum())
    pts, nrm = [], []
    for s, c in zip(shapes, counts, strict=True):
        if c == 0:
            continue
        u = rng.random((c, 2)).astype(np.float32)
        ps = s.sample_position(0.0, mi.Point2f(u[:, 0], u[:, 1]))
        # A flat shape's normal may come back as one value for every sample: broadcast.
        pts.append(np.stack([np.broadcast_to(np.asarray(ps.p[k]), (c,)) for k in range(3)], -1))
        nrm.append(np.stack([np.broadcast_to(np.asarray(ps.n[k]), (c,)) for k in range(3)], -1))
    p, nn = np.concatenate(pts).astype(np.float64), np.concatenate(nrm).astype(np.float64)
    seen = np.zeros(len(p), bool)
    for cam in cameras:
        o = cam.origin
        d = o[None] - p
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        # Open shapes (disk, cylinder) are seen from either side; closed ones face outward.
        facing = np.abs(np.einsum("ij,ij->i", d, nn)) > 1e-3
        todo = np.flatnonzero(facing & ~seen)
        if len(todo) == 0:
            continue
        eps = 1e-4 * (1.0 + np.abs(p[todo]).max(axis=1))
        org = p[todo] + d[todo] * eps[:, None]
        ray = mi.Ray3f(mi.Point3f(*(org[:, k].astype(np.float32) for k in range(3))),
                       mi.Vector3f(*(d[todo, k].astype(np.float32) for k in range(3))))
        ray.maxt = mi.Float((dist[todo] - 2 * eps).astype(np.float32))
        hit = np.asarray(scene.ray_test(ray))
        dr.eval()
        seen[todo[~hit]] = True
    return p[seen]


def chamfer(recon: np.ndarray, truth: np.ndarray) -> dict:
    """Mean nearest-point distances between point sets [M, 3] and [K, 3], both ways."""
    from scipy.spatial import cKDTree

    d_rt = cKDTree(truth).query(recon)[0]
    d_tr = cKDTree(recon).query(truth)[0]
    return {"recon_to_truth": float(d_rt.mean()), "truth_to_recon": float(d_tr.mean()),
            "chamfer": float(0.5 * (d_rt.mean() + d_tr.mean())),
            "recon_to_truth_p95": float(np.quantile(d_rt, 0.95)),
            "truth_to_recon_p95": float(np.quantile(d_tr, 0.95))}


def mesh_points(path: Path, n: int = SAMPLES, seed: int = 0) -> np.ndarray:
    """Area-uniform points [n, 3] on a triangle mesh file."""
    import trimesh

    mesh = trimesh.load(path, process=False)
    tri = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    f = rng.choice(len(tri), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1  # fold the unit square onto the triangle
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = tri[f]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


# -- path-traced relighting ------------------------------------------------------------------
def relight_scene_xml(scene_xml: Path, lights: list[dict], max_depth: int) -> str:
    """The exported scene with its emitters replaced by ``lights`` (lights.json entries:
    direction toward the light, irradiance) and mesh file names made absolute."""
    root = ET.parse(scene_xml).getroot()
    for em in root.findall("emitter"):
        root.remove(em)
    for s in root.iter("string"):
        if s.get("name") == "filename":
            s.set("value", str((scene_xml.parent / s.get("value")).resolve()))
    for d in root.findall("default"):
        if d.get("name") == "max_depth":
            d.set("value", str(max_depth))
    for k, lt in enumerate(lights):
        em = ET.SubElement(root, "emitter", type="directional", id=f"relight_{k}")
        d = -np.asarray(lt["direction"], np.float64)
        e = np.broadcast_to(np.asarray(lt["irradiance"], np.float64), (3,))
        ET.SubElement(em, "vector", name="direction", value=", ".join(f"{v:.9g}" for v in d))
        ET.SubElement(em, "rgb", name="irradiance", value=", ".join(f"{v:.9g}" for v in e))
    return ET.tostring(root, "unicode")


def path_trace(xml_text: str, where: Path, albedo_scale: np.ndarray, spp: int,
               progress: bool, renders: list[Path]) -> tuple[np.ndarray, int]:
    """Every sensor's render [V, H, W, 3] of the scene text (written to ``where``), each
    kept as the EXR ``renders[i]``: one already there (a killed call's; sensor i's seed is
    i) is read, not traced again. Returns the renders and how many were traced now."""
    import mitsuba as mi
    from tqdm import tqdm

    write_text(where, xml_text)
    scene = mi.load_file(str(where), spp=spp)
    params = mi.traverse(scene)
    for key in [k for k in params.keys() if k.endswith("vertex_albedo_color")]:
        a = np.asarray(params[key], np.float32).reshape(-1, 3) * albedo_scale[None].astype(
            np.float32)
        params[key] = mi.Float(a.ravel())
    params.update()
    if len(renders) != len(scene.sensors()):
        raise ValueError(f"{where}: {len(scene.sensors())} sensors, {len(renders)} renders")
    out, traced = [], 0
    for i in tqdm(range(len(renders)), desc="path trace", disable=not progress):
        if not renders[i].is_file():
            write_exr(renders[i], np.asarray(mi.render(scene, sensor=i, spp=spp, seed=i))[..., :3])
            traced += 1
        out.append(read_exr(renders[i])[..., :3])
    return np.stack(out), traced


def surfel_albedo_scale(run: Path, test) -> np.ndarray:
    """Stage 5's global per-channel albedo factor (``evaluation.global_albedo_scale`` of
    the surfel model's rendered diffuse albedo against the ground truth)."""
    from mi_shadowgs.io.ply import load_ply
    from mi_shadowgs.stages.evaluation import metrics as evaluation
    from mi_shadowgs.stages.evaluation.evaluate import scored_pixels
    from validation.albedo_global import diffuse_albedo_views

    est = diffuse_albedo_views(load_ply(run / "material" / "full" / "model.ply"), test.cameras)
    return evaluation.global_albedo_scale(est, test.stack("albedo"), scored_pixels(test))


def _figure(path: Path, rows: list[tuple[str, np.ndarray, np.ndarray]], views) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_shadowgs.io.images import linear_to_srgb

    cols = len(views) * 3
    fig, axes = plt.subplots(len(rows), cols, figsize=(1.6 * cols, 1.8 * len(rows)),
                             squeeze=False)
    for r, (name, est, gt) in enumerate(rows):
        for j, v in enumerate(views):
            err = np.abs(est[v] - gt[v]).mean(-1)
            for c, (img, title) in enumerate(((linear_to_srgb(gt[v]), "ground truth"),
                                              (linear_to_srgb(est[v]), "exported, path-traced"),
                                              (err, "|error|"))):
                ax = axes[r, 3 * j + c]
                ax.imshow(img, cmap="magma" if img.ndim == 2 else None, vmin=0, vmax=0.25
                          if img.ndim == 2 else None)
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(f"{title}\nview {v}", fontsize=7)
            axes[r, 0].set_ylabel(name, fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def interior_psnr(est: np.ndarray, gt: np.ndarray, mask: np.ndarray, band: int = 2) -> float:
    """Mean over views of the PSNR [dB] of ``est`` against ``gt`` [V, H, W, 3] over ``mask``
    [V, H, W] eroded by ``band`` pixels (as ``evaluation.image_metrics`` over the mask)."""
    from scipy.ndimage import binary_erosion

    from mi_shadowgs.core import metrics

    inner = [binary_erosion(m, iterations=band) for m in np.asarray(mask, bool)]
    return float(np.mean([metrics.psnr(e, g, m) for e, g, m in zip(est, gt, inner, strict=True)
                          if m.any()]))


def _export_files(scene_xml: Path) -> dict:
    """``input_ref`` of the exported scene and of every file it loads (the meshes)."""
    from mi_shadowgs.io.provenance import input_ref

    names = [s.get("value") for s in ET.parse(scene_xml).getroot().iter("string")
             if s.get("name") == "filename"]
    return {name: input_ref(scene_xml.parent / name) for name in [scene_xml.name, *names]}


def validate(run: Path, data: Path, out: Path, spp: int = 64, progress: bool = True,
             overwrite: bool = False) -> dict:
    from mi_shadowgs.dataset.fingerprint import dataset_ref
    from mi_shadowgs.dataset.loader import DatasetError, load_dataset
    from mi_shadowgs.io.provenance import Provenance, ProvenanceError, input_ref
    from mi_shadowgs.stages.evaluation import metrics as evaluation
    from mi_shadowgs.stages.export.export import ExportError, export_run

    out.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    try:
        res = export_run(run, out / "export", "mesh", data=data, overwrite=overwrite,
                         progress=progress)
        export_s = time.perf_counter() - t0  # the export alone: the speed item's bound
        train = load_dataset(data, "train")
        test = load_dataset(data, "test")
    except (ExportError, ProvenanceError, DatasetError, FileNotFoundError) as exc:
        fail(f"{exc} (validation.asset)")
    info = json.loads((out / "export" / "export.json").read_text())
    if not res.ran:  # reused: its own recorded time
        export_s = float(info["seconds_total"])
    data_ref = dataset_ref(data)
    dataset = json.loads((data / "dataset.json").read_text())
    # Geometry.
    mesh = out / "export" / "object.ply"

    def score_geometry(unit) -> dict:
        diameter = 2.0 * float(dataset["object"]["radius"])
        truth = ground_truth_points(data, train.cameras)
        cd = chamfer(mesh_points(mesh), truth)
        cd.update({k + "_pct": 100.0 * v / diameter for k, v in list(cd.items())})
        cd["diameter"] = diameter
        cd["truth_points_seen"] = len(truth)
        return cd

    cd = run_unit(out, "chamfer", STUDY, Provenance(
        data_ref, {"mesh": input_ref(mesh)}, settings_of(samples=SAMPLES)),
        score_geometry, overwrite=overwrite)
    # Relighting. The scale is recorded: renders with threads may differ in the last bits,
    # and the path-traces' settings hold it.
    model = run / "material" / "full" / "model.ply"
    scale = np.asarray(run_unit(
        out, "albedo_scale", STUDY, Provenance(data_ref, {"model": input_ref(model)}),
        lambda unit: {"albedo_scale": surfel_albedo_scale(run, test).tolist()},
        overwrite=overwrite)["albedo_scale"])
    surfel = json.loads((run / "material" / "full" / "metrics.json").read_text())
    max_depth = int((dataset.get("config") or {}).get("max_depth", 8))
    mask = test.stack("mask")
    exported = _export_files(out / "export" / "scene.xml")
    stems = [Path(view.name).name for view in test.views]
    relit, fig_rows = {}, []
    for entry in train.lights.get("relightings", []):
        if entry.get("type", "directional") != "directional":
            continue
        name = entry["name"]
        gt = np.stack([v.relit[name] for v in test.views])

        def trace(unit, lights=entry["lights"], gt=gt) -> dict:
            xml = relight_scene_xml(out / "export" / "scene.xml", lights, max_depth)
            t1 = time.perf_counter()
            est, traced = path_trace(xml, unit.path("scene.xml"), scale, spp, progress,
                                     [unit.path(f"renders/{s}.exr") for s in stems])
            secs = time.perf_counter() - t1
            m = evaluation.image_metrics(est, gt, mask)
            return {"path_traced_psnr": m["psnr"],
                    # the same without a 2-pixel band inside the masks' outline: how much
                    # of the error is the edge of the base and the silhouettes
                    "path_traced_psnr_interior": interior_psnr(est, gt, mask),
                    "path_traced_ssim": m["ssim"], "path_traced_lpips": m["lpips"],
                    "render_s": secs,  # of the views traced in the call that finished
                    "views_traced": traced}

        unit = f"relight_{name}"
        provenance = Provenance(data_ref, exported, settings_of(
            spp=spp, max_depth=max_depth, lights=entry["lights"],
            albedo_scale=scale.tolist()))
        scores = run_unit(out, unit, STUDY, provenance, trace, overwrite=overwrite)
        ours = (surfel.get("relighting") or {}).get(name, {})
        relit[name] = {**scores, "surfel_psnr": ours.get("psnr"),
                       "surfel_ssim": ours.get("ssim"),
                       "gap_db": None if ours.get("psnr") is None else
                       ours["psnr"] - scores["path_traced_psnr"]}
        est = np.stack([read_exr(out / UNITS / unit / "renders" / f"{s}.exr")[..., :3]
                        for s in stems])
        fig_rows.append((name, est, gt))
    if fig_rows:
        _figure(out / "asset.png", fig_rows, [0, len(test.views) // 2])
    gaps = [r["gap_db"] for r in relit.values() if r["gap_db"] is not None]
    result = {
        "run": str(run), "data": str(data), "spp": spp, "max_depth": max_depth,
        "albedo_scale": scale.tolist(), "export_s": export_s, "export": info,
        "chamfer": cd, "relighting": relit,
        "accept": {"chamfer": cd["chamfer_pct"] <= ACCEPT["chamfer_pct"],
                   "relight_within_2db": bool(gaps) and max(gaps) <= ACCEPT["psnr_gap_db"],
                   "export_time": export_s <= ACCEPT["export_s"]},
        "loadavg_start": list(load0), "loadavg_end": list(os.getloadavg()),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    write_json(out / "asset.json", result)
    return result


def markdown(r: dict) -> str:
    cd = r["chamfer"]
    lines = [f"Chamfer {cd['chamfer_pct']:.3f} % of diameter (recon->truth "
             f"{cd['recon_to_truth_pct']:.3f} %, truth->recon {cd['truth_to_recon_pct']:.3f} "
             f"%), export {r['export_s']:.1f} s",
             "| relighting | path-traced PSNR | surfel PSNR | gap dB | path-traced SSIM | "
             "path-traced PSNR without the 2-px outline band |",
             "|---|---|---|---|---|---|"]
    for name, x in r["relighting"].items():
        sp = "n/a" if x["surfel_psnr"] is None else f"{x['surfel_psnr']:.2f}"
        gap = "n/a" if x["gap_db"] is None else f"{x['gap_db']:+.2f}"
        inner = x.get("path_traced_psnr_interior")
        lines.append(f"| {name} | {x['path_traced_psnr']:.2f} | {sp} | {gap} | "
                     f"{x['path_traced_ssim']:.4f} | "
                     f"{'n/a' if inner is None else f'{inner:.2f}'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True, help="finished run folder (stage 4 done)")
    ap.add_argument("--data", required=True, help="its dataset folder")
    ap.add_argument("--out", required=True, help="output folder (export/, asset.json, ...)")
    ap.add_argument("--spp", type=int, default=64, help="path-tracing samples per pixel")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--overwrite", action="store_true",
                    help="make the export, the Chamfer distance and the path-traces again")
    args = ap.parse_args(argv)
    claim_out(args.out, STUDY, ('asset.json',))
    run = Path(args.run)
    out = Path(args.out)
    r = validate(run, Path(args.data), out, args.spp, progress=not args.no_progress,
                 overwrite=args.overwrite)
    print(markdown(r))
    print("accept:", r["accept"])
    return 0 if all(r["accept"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
