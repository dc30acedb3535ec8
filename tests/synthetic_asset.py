"""A known surfel model for the export tests: a sphere of surfels standing above a plane of
surfels (y = 0, our base), with per-surfel materials, and a ring of cameras around it; and
a finished-looking run folder holding it (manifests as `mi-shadowgs run` writes them), so
that the exporter is tested on geometry whose true surface is known analytically.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.io.ply import PlyModel

CENTER = np.array([0.0, 0.6, 0.0])
RADIUS = 0.5
TOP_ALBEDO = (0.8, 0.2, 0.1)  # upper hemisphere (y > centre)
BOTTOM_ALBEDO = (0.1, 0.3, 0.7)
PLANE_ALBEDO = (0.5, 0.5, 0.5)


def _frames(n: np.ndarray) -> np.ndarray:
    """[N, 3, 3] right-handed frames whose third column is the unit normal ``n`` [N, 3]."""
    a = np.where(np.abs(n[:, 1:2]) < 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(a, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return np.stack([t1, np.cross(n, t1), n], -1)


def _quaternions(frames: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of rotation matrices [N, 3, 3]."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(frames).as_quat()[:, [3, 0, 1, 2]]


def sphere_on_plane(n_sphere: int = 6000, n_plane: int = 6400, half: float = 1.2,
                    sh_degree: int = 1) -> PlyModel:
    """Fibonacci-sphere surfels (radius ``RADIUS`` at ``CENTER``) and a regular grid of
    plane surfels on y = 0 (|x|, |z| < ``half``), each about 0.8 of its spacing wide, opaque
    (opacity 0.98), with albedo/roughness/metallic and a degree-``sh_degree`` "sh"."""
    i = np.arange(n_sphere) + 0.5
    phi = np.arccos(1 - 2 * i / n_sphere)
    th = np.pi * (1 + 5 ** 0.5) * i
    d = np.stack([np.cos(th) * np.sin(phi), np.cos(phi), np.sin(th) * np.sin(phi)], 1)
    m = int(round(n_plane ** 0.5))
    g = (np.arange(m) + 0.5) / m * 2 * half - half
    gx, gz = np.meshgrid(g, g)
    plane = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], 1)
    pos = np.concatenate([CENTER + RADIUS * d, plane])
    nrm = np.concatenate([d, np.tile([0.0, 1.0, 0.0], (len(plane), 1))])
    s_sph = np.sqrt(4 * np.pi * RADIUS ** 2 / n_sphere) * 0.8
    s_pl = 2 * half / m * 0.8
    log_scale = np.log(np.concatenate([np.full((n_sphere, 2), s_sph),
                                       np.full((len(plane), 2), s_pl)]))
    albedo = np.where(pos[:, 1:2] > CENTER[1], [TOP_ALBEDO], [BOTTOM_ALBEDO])
    albedo[n_sphere:] = PLANE_ALBEDO
    n = len(pos)
    k = (sh_degree + 1) ** 2
    rng = np.random.default_rng(0)
    sh = np.zeros((n, k, 3))
    sh[:, 0] = (albedo - 0.5) / 0.28209479177387814
    sh[:, 1:] = 0.05 * rng.standard_normal((n, k - 1, 3))
    channels = {"sh": sh.reshape(n, 3 * k).astype(np.float32),
                "albedo": albedo.astype(np.float32),
                "roughness": np.where(pos[:, 1:2] > 0.01, 0.4, 0.9).astype(np.float32),
                "metallic": np.where(pos[:, 1:2] > 0.01, 0.25, 0.0).astype(np.float32),
                "segment": (pos[:, 1:2] > 0.01).astype(np.float32)}
    return PlyModel(pos.astype(np.float32), log_scale.astype(np.float32),
                    _quaternions(_frames(nrm)).astype(np.float32),
                    np.full(n, np.log(0.98 / 0.02), np.float32), channels)


def box_on_plane_surfels(n: int, plane_half: float, box_half: float, roughness: float):
    """Mitsuba-sampled surfels (``core.sampling``) on a square plane (y = 0, half-width
    ``plane_half``) and a cube of half-width ``box_half`` standing on it, with roughness and
    zero metallic; the relighting and viewer tests' scene of one cast shadow."""
    import mitsuba as mi

    from mi_shadowgs.core.sampling import surfels_on_surface

    plane = mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale([plane_half, plane_half, 1])
    box = mi.ScalarTransform4f().translate([0, box_half, 0]).scale(box_half)
    shapes = [mi.load_dict({"type": "rectangle", "to_world": plane}),
              mi.load_dict({"type": "cube", "to_world": box})]
    surf = surfels_on_surface(shapes, n, sigma_factor=0.7)
    k = surf.count
    surf.channels["roughness"] = mi.TensorXf(np.full((k, 1), roughness, np.float32))
    surf.channels["metallic"] = mi.TensorXf(np.zeros((k, 1), np.float32))
    return surf


def ring_cameras(n: int = 16, size: int = 64, distance: float = 4.0) -> list[Camera]:
    """Cameras around the Y axis at 20-70 degrees elevation, looking at (0, 0.4, 0)."""
    cams = []
    for i in range(n):
        az = 2 * np.pi * i / n
        el = np.radians(20 + 25 * (i % 3))
        o = distance * np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        cams.append(Camera.look_at(o, (0.0, 0.4, 0.0), width=size, height=size, fov_x=0.7))
    return cams


def write_cameras(path: Path, cameras: list[Camera], stem: str) -> None:
    frames = [c.to_frame_json(f"./{stem}/r_{i:03d}") for i, c in enumerate(cameras)]
    path.write_text(json.dumps({"camera_angle_x": cameras[0].fov_x, "w": cameras[0].width,
                                "h": cameras[0].height, "frames": frames}))


def fake_run(root: Path, model: PlyModel | None = None, stage4: bool = True,
             lights=(((0.3, 0.8, 0.5), 2.0), ((-0.5, 0.6, -0.6), 1.0))) -> tuple[Path, Path]:
    """(run, data): a dataset folder with camera files and a ``dataset.json`` naming a base,
    and a run folder whose manifests are those of a finished `mi-shadowgs run` (stage 4 in
    ``material/full`` when ``stage4``) holding ``model``."""
    from mi_shadowgs.config import to_dict
    from mi_shadowgs.dataset.fingerprint import dataset_ref
    from mi_shadowgs.io.ply import write_ply_model
    from mi_shadowgs.io.provenance import Output, Provenance, input_ref
    from mi_shadowgs.presets import CONFIG_NAME, get_config

    data, run = root / "data", root / "run"
    data.mkdir(parents=True)
    write_cameras(data / "transforms_train.json", ring_cameras(16), "train")
    write_cameras(data / "transforms_test.json", ring_cameras(3, size=32)[:3], "test")
    (data / "dataset.json").write_text(json.dumps({
        "format_version": 1, "object": {"center": CENTER.tolist(), "radius": RADIUS},
        "materials": [{"id": 0, "name": "background"}, {"id": 1, "name": "sphere"},
                      {"id": 2, "name": "base"}]}))
    model = sphere_on_plane() if model is None else model
    tree = get_config("cpu-small")  # what a run records: its settings tree
    with Output.open(run, "run", Provenance(dataset=dataset_ref(data), settings=tree.to_dict()),
                     parts=("geometry", "segmentation", "material")) as top:
        top.claim(CONFIG_NAME)
        (run / CONFIG_NAME).write_text(json.dumps(tree.to_dict()))
        top.add_part("geometry")
        geo = run / "geometry"
        with Output.open(geo, "train", Provenance(dataset=dataset_ref(data))) as out:
            write_ply_model(out.path("model.ply"), model)
            out.finish()
        top.add_part("segmentation")  # stage 4 reads segmentation/model.ply, as in a run
        seg = run / "segmentation"
        with Output.open(seg, "segment", Provenance(
                dataset=dataset_ref(data), inputs={"model": input_ref(geo / "model.ply")})) as out:
            write_ply_model(out.path("model.ply"), model)
            out.finish()
        if stage4:
            top.add_part("material/full")
            prov = Provenance(dataset=dataset_ref(data),
                              inputs={"model": input_ref(seg / "model.ply")},
                              settings={"visibility": to_dict(tree.visibility),
                                        "relight": to_dict(tree.relight)})
            with Output.open(run / "material" / "full", "run", prov, part_of=run) as out:
                write_ply_model(out.path("model.ply"), model)
                dirs = np.array([d for d, _ in lights], np.float64)
                dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
                (out.path("light.json")).write_text(json.dumps({
                    "radiance": [0.0] * 128, "active": [0] * len(lights),
                    "directions": dirs.tolist(), "irradiance": [e for _, e in lights],
                    "specular": True}))
                out.finish()
        top.finish()
    return run, data
