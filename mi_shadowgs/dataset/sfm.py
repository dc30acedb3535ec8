"""Structure from motion for ``mi-shadowgs import`` (pycolmap on the CPU): features, matches
and an incremental mapping, run in pieces that are recorded as they finish in a work folder
beside the import's output, so that a killed import resumes; and the cause of a failed
registration in words (no parallax, or too few features)."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mi_shadowgs.dataset.importer import ImportConfig

SFM_STATE = "sfm_state.json"  # the SfM work folder's record of what is done (run_sfm)
MAPPING = "mapping"  # the SfM work folder's models of a mapping in progress
# SfM settings: a work folder made with other values of these is not resumed.
_SFM_SETTINGS = ("exhaustive_max", "sequential_overlap", "max_features", "camera_model",
                 "focal_px", "sfm_chunk_photos", "sfm_chunk_pairs")


def sfm_work_folder(out: Path) -> Path:
    """Where the SfM of an import into ``out`` keeps its work until the dataset is written:
    beside ``out`` (which does not exist until then), so that a killed import resumes."""
    return out.parent / f".{out.name}.sfm"


def sfm_key(photos: list[Path], config: ImportConfig) -> str:
    """The photos' names and contents and the SfM settings: a work folder of another key
    holds another import's features and is not resumed."""
    import hashlib

    from mi_shadowgs.io.provenance import file_digest

    settings = {k: getattr(config, k) for k in _SFM_SETTINGS}
    payload = {"photos": [[p.name, file_digest(p)] for p in photos], "settings": settings,
               "seed": config.frame.seed}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def open_sfm_work(work: Path, key: str) -> dict:
    """The work folder's state: resumed when it holds this key, started afresh when it holds
    another import's (ours: it has our state file), refused when it is someone else's."""
    from mi_shadowgs.dataset.importer import CaptureError
    from mi_shadowgs.io.atomic import write_json

    state_path = work / SFM_STATE
    if work.exists():
        try:
            state = json.loads(state_path.read_text())
        except (OSError, ValueError):
            raise CaptureError(f"{work}: a folder that import did not write (no readable "
                               f"{SFM_STATE}) is where its SfM work goes; move it") from None
        if state.get("key") == key:
            return state
        shutil.rmtree(work)  # another import's work: features of other photos or settings
    work.mkdir(parents=True)
    state = {"key": key, "extracted": [], "matched_pairs": 0, "mapped": False}
    write_json(state_path, state)
    return state


def run_sfm(image_dir: Path, names: list[str], work: Path, config: ImportConfig,
            size: tuple[int, int], timings: dict, state: dict, progress: bool = False):
    """pycolmap SfM on the CPU; the reconstruction with the most registered images.

    Features are extracted ``sfm_chunk_photos`` photos at a time and matched
    ``sfm_chunk_pairs`` pairs at a time (the pairs pycolmap's exhaustive or sequential
    pairing gives), each piece recorded in ``state`` (``work/SFM_STATE``) once the database
    holds it; the mapping is recorded when its models are written. A rerun after a kill
    continues from the last piece (the database's features and matches are COLMAP's; a
    piece cut short is redone, COLMAP skipping what it already holds); the mapping continues
    from its last written models (``incremental_mapping``). One camera for all photos: the
    pieces after the first reuse the first piece's."""
    import pycolmap
    from tqdm import tqdm

    from mi_shadowgs.dataset.importer import CaptureError
    from mi_shadowgs.io.atomic import write_json

    db = work / "database.db"

    def record():
        write_json(work / SFM_STATE, state)

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = config.threads
    extraction.sift.max_num_features = config.max_features
    done = set(state["extracted"])
    todo = [n for n in names if n not in done]
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    if config.focal_px is not None:
        w, h = size
        extra = ",0" if config.camera_model in ("SIMPLE_RADIAL", "RADIAL") else ""
        reader.camera_params = f"{config.focal_px},{w / 2},{h / 2}{extra}"
    camera = None  # the photos' one camera: the database's once a piece has made it
    t = time.perf_counter()
    for i in tqdm(range(0, len(todo), config.sfm_chunk_photos), desc="SfM features",
                  unit="chunk", disable=not progress or not todo):
        if camera is None and (camera := _first_camera(db)) is not None:
            reader.existing_camera_id = camera
        chunk = todo[i:i + config.sfm_chunk_photos]
        pycolmap.extract_features(db, image_dir, image_names=chunk,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        state["extracted"] += chunk
        record()
    timings["extract_s"] = time.perf_counter() - t
    t = time.perf_counter()
    pairs, timings["matcher"] = _sfm_pairs(db, len(names), config)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.threads
    start = state["matched_pairs"]
    for i in tqdm(range(start, len(pairs), config.sfm_chunk_pairs), desc="SfM matches",
                  unit="chunk", disable=not progress or start >= len(pairs)):
        chunk = pairs[i:i + config.sfm_chunk_pairs]
        listing = work / "pairs.txt"
        listing.write_text("".join(f"{a} {b}\n" for a, b in chunk))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(listing)
        pycolmap.match_image_pairs(db, matching_options=matching, pairing_options=pairing,
                                   device=pycolmap.Device.cpu)
        state["matched_pairs"] = i + len(chunk)
        record()
    timings["match_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if state["mapped"]:  # its last write of the models is the finished mapping's
        recs = {i: pycolmap.Reconstruction(str(d))
                for i, d in enumerate(_saved_models(work / MAPPING))}
    else:
        recs = incremental_mapping(db, image_dir, work, config)
        state["mapped"] = True
        record()
    timings["map_s"] = time.perf_counter() - t
    if not recs:
        raise CaptureError(f"{image_dir}: SfM registered 0 of {len(names)} photos; dropped: "
                           f"{', '.join(names[:12])}{' ...' if len(names) > 12 else ''}. "
                           f"{registration_advice(db)}")
    return max(recs.values(), key=lambda r: r.num_reg_images())


# Two-view geometries of photos that match but were taken from one place: COLMAP sees a
# homography of a turn (or of a copy), which no triangulation can use.
_NO_PARALLAX = ("PANORAMIC", "PLANAR_OR_PANORAMIC")
_MATCHED_INLIERS = 15  # COLMAP's default minimum of inliers for a verified pair
TOO_FEW_FEATURES = ("The photos share too few features: photograph the object on a textured "
                    "background (a printed mat, newspaper) with more overlap between photos")


def registration_advice(db: Path | None) -> str:
    """Why SfM registered too few photos, from its database's verified pairs: no parallax
    (pairs that match well, but as one view turned or copied: identical photos, or a camera
    that only turned) or too few features (pairs that hardly match)."""
    import pycolmap

    if db is None or not db.is_file():
        return TOO_FEW_FEATURES
    database = pycolmap.Database.open(str(db))
    try:
        _, geometries = database.read_two_view_geometries()
    finally:
        database.close()
    matched = [g for g in geometries if len(g.inlier_matches) >= _MATCHED_INLIERS]
    no_parallax = {int(getattr(pycolmap.TwoViewGeometryConfiguration, n)) for n in _NO_PARALLAX}
    turned = [g for g in matched if int(g.config) in no_parallax]
    if not matched or len(turned) < 0.5 * len(matched):
        return TOO_FEW_FEATURES
    return (f"The photos match well ({len(matched)} of {len(geometries)} pairs) but show no "
            f"parallax: {len(turned)} of those pairs are one view turned, or copies of one "
            "photo, and SfM cannot place cameras that did not move. Walk around the object "
            "between photos (do not only turn the camera), and give each view once")


def incremental_mapping(db: Path, image_dir: Path, work: Path, config: ImportConfig) -> dict:
    """pycolmap's incremental mapping of the database ``db``: {index: Reconstruction}.

    Its models so far are written to ``work/MAPPING`` between two photo registrations,
    within ``checkpoint_seconds`` of the last write and at SIGINT/SIGTERM
    (``mi_shadowgs.io.interrupt``); a rerun continues them (COLMAP's mapper extends the
    first model it is given, then starts new ones), so a kill loses at most that much of
    the mapping. The cameras equal an unkilled mapping's to pycolmap's own spread."""
    import pycolmap

    from mi_shadowgs.io.atomic import atomic_dir
    from mi_shadowgs.io.interrupt import CheckpointClock, raise_pending

    saved = work / MAPPING
    manager = pycolmap.ReconstructionManager()
    for model in _saved_models(saved):
        manager.read(str(model))
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = config.threads
    options.random_seed = config.frame.seed
    options.image_path = str(image_dir)
    clock = CheckpointClock(0, config.checkpoint_seconds)

    def save() -> None:
        with atomic_dir(saved, overwrite=True) as tmp:
            manager.write(str(tmp))
        clock.saved()

    def on_registration() -> None:
        if clock.due():
            save()
            raise_pending("SfM mapping")

    database = pycolmap.Database.open(str(db))
    try:
        pipeline = pycolmap.IncrementalPipeline(options, database, manager)
        pipeline.add_callback(pycolmap.IncrementalPipelineCallback.NEXT_IMAGE_REG_CALLBACK,
                              on_registration)
        with clock.running():
            pipeline.run()
    finally:
        database.close()
    save()  # the finished mapping, which a rerun after a later kill reads back
    return {i: manager.get(i) for i in range(manager.size())}


def _saved_models(folder: Path) -> list[Path]:
    """The model folders (0, 1, ...) a ReconstructionManager wrote into ``folder``, in
    order; none when it does not exist."""
    if not folder.is_dir():
        return []
    return sorted((d for d in folder.iterdir() if d.name.isdigit()), key=lambda d: int(d.name))


def _first_camera(db: Path) -> int | None:
    """The camera of the database's photos (one for all), or None before any."""
    import pycolmap

    if not db.is_file():
        return None
    database = pycolmap.Database.open(str(db))
    try:
        images = database.read_all_images()
        return int(images[0].camera_id) if images else None
    finally:
        database.close()


def _sfm_pairs(db: Path, count: int, config: ImportConfig) -> tuple[list[tuple[str, str]], str]:
    """The photo pairs to match, by name, as pycolmap pairs them: every pair up to
    ``exhaustive_max`` photos, else sequential with ``sequential_overlap``."""
    import pycolmap

    database = pycolmap.Database.open(str(db))
    try:
        names = {im.image_id: im.name for im in database.read_all_images()}
        if count <= config.exhaustive_max:
            generator = pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(),
                                                         database)
            how = "exhaustive"
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = config.sequential_overlap
            generator = pycolmap.SequentialPairGenerator(pairing, database)
            how = f"sequential (overlap {config.sequential_overlap})"
        return [(names[a], names[b]) for a, b in generator.all_pairs()], how
    finally:
        database.close()
