"""What an output was made from, and which files in its folder are ours.

Every folder a command writes (a run, a stage, renders, a dataset) holds a manifest,
``.mi_shadowgs_manifest.json``::

    {"format": 1, "command": "train", "complete": false,
     "dataset": {"path": "/abs/DATA", "fingerprint": "<blake2b>"},
     "inputs": {"model": {"path": "/abs/model.ply", "digest": "<blake2b>"}},
     "settings": {...the stage's resolved settings...},
     "files": ["model.ply", "previews/iter_000100.png", ...], "parts": ["geometry", ...],
     "made_with": [{"variant": "llvm_ad_rgb", "device": "<CPU model> (2 cores)",
                    "threads": 2, "mi_shadowgs": "<git commit>"}]}

- A command writes only into a new (or empty) folder or one whose manifest names the same
  command (``Output.open``), never into a dataset folder, over its own inputs or inside a
  folder that another output lists as its own (``RUN/material/x``).
- An output is reused or continued only when its dataset fingerprint, input digests and
  settings all match (``ProvenanceError`` names what differs otherwise).
- ``--overwrite`` removes only the files (and the ``parts``: sub-folders with their own
  manifests) that the manifest lists; ``files`` is written *before* each file, so it covers
  everything a killed command left behind. Other files stay, and a folder that keeps them
  keeps an emptied manifest (``clear``); a sub-folder made whole again (a run's
  ``report/``) replaces only its listed files (``Output.staged``).
- ``made_with`` says how the folder's files were made (``made_with()``): one entry per
  backend (Mitsuba variant, device, Dr.Jit threads, mi_shadowgs's commit) that wrote into
  it, in order; a stage begun on ``cuda_ad_rgb`` and resumed on ``llvm_ad_rgb`` has two.
  It is a record, not provenance: the two backends' results differ at round-off level, as
  two thread counts do, so it is never compared (``differences``), and an output from before
  the record (no key) is reused as it is, and continued without one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
from collections.abc import Iterator
from pathlib import Path

from mi_shadowgs.io.atomic import remove_stale, staged_dir, write_json

MANIFEST_NAME = ".mi_shadowgs_manifest.json"
FORMAT_VERSION = 1
MADE_WITH = "made_with"  # the manifest's record of the backends that wrote the folder
_CHUNK = 1 << 20
_MAX_LISTED = 8  # differing settings named in one message


class ProvenanceError(ValueError):
    """An output folder cannot be written or reused as asked; the message says why."""


# -- fingerprints -------------------------------------------------------------------------
def file_digest(path: str | os.PathLike) -> str:
    """blake2b-128 of a file's bytes (hex)."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def input_ref(path: str | os.PathLike) -> dict:
    """An ``inputs`` entry of a manifest: absolute path and content digest of a file."""
    return {"path": str(Path(path).resolve()), "digest": file_digest(path)}


@dataclasses.dataclass(frozen=True)
class Provenance:
    """What an output is made from: dataset, input files and resolved settings."""

    dataset: dict | None = None  # dataset_ref(...)
    inputs: dict = dataclasses.field(default_factory=dict)  # name -> input_ref(...)
    settings: dict = dataclasses.field(default_factory=dict)  # JSON values

    def to_json(self) -> dict:
        # Through JSON so that tuples compare equal to the lists a manifest reads back.
        return json.loads(json.dumps({"dataset": self.dataset, "inputs": self.inputs,
                                      "settings": self.settings}))


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


# Settings that only say when to checkpoint: a resume is bit-identical whatever they are, so
# an output made with other values is still the same output.
RESULT_NEUTRAL_SETTINGS = ("checkpoint_every", "checkpoint_seconds",
                           # stage 1 applies these to views without masks through
                           # lambda_dist, lambda_normal and the opacity reset, which are
                           # compared: their effect is recorded there
                           "unmasked_lambda_dist", "unmasked_lambda_normal",
                           "unmasked_opacity_reset", "unmasked_lambda_dark_alpha",
                           # ... and this through densify.max_surfels
                           "unmasked_max_surfels",
                           # stage 4 applies these to segments from chromaticity through
                           # normal_steps and refine_score, which are compared
                           "chromaticity_normal_steps", "chromaticity_refine_score")
# Settings added after outputs were made, with the value that does what the code did before
# they existed: absent from an older manifest, they count as equal to that value, so an
# older run is still reused (or resumed) when nothing it computed would change.
ADDED_SETTINGS = {"k_select": "labels",  # stage 2: K from the labels (material ids)
                  "silhouette_samples": None,  # used only by k_select "silhouette"
                  "lambda_dark_alpha": 0.0,  # stage 1, views without masks
                  "dark_max": 1.0 / 255.0,  # used only with lambda_dark_alpha > 0
                  "dark_alpha_support": None, "dark_alpha_margin": None,  # ... and these
                  "normal_depth_differences": "central",  # stage 1, 2DGS's differences
                  "normal_steps": 0,  # stage 4's normal phase (none before it)
                  "lr_normal": None, "lambda_normal_prior": None,  # used only by that
                  "normal_hold_planar": None,  # phase
                  "init_consistent_top": 0.05,  # stage 1: the photo-consistent cells' share
                  "prototype_share": 0.25,  # stage 2: the label prototypes' last iterations
                  "outline_weld": 0.25, "sliver_area": 1e-3,  # export: the mesh's welds
                  "min_points": 10,  # import: the SfM points below which cameras set the frame
                  "lambda_ind_floor": 0.0,  # stage 4: no pull on negative indirect light
                  "sh_space": "linear",  # render: a PLY's SH read as linear
                  "world_up": "+y", "ply_frame": "y-up",  # render: the model as stored, Y-up
                  "hull_prune_views": 0,  # stage 1: no prune outside the masks
                  "hull_prune_dilate": None,  # used only by that prune
                  "prototype_iterations": 50,  # stage 2: K-means' steps from the prototypes
                  "detail_prior": 0.0,  # stage 4: no albedo detail within a segment
                  "detail_max": None, "lr_detail": None,  # used only with the detail
                  "detail_edge_px": None,
                  "view_gains": "off",  # stage 1: one exposure for every photo
                  "lr_view_gain": None}  # used only with the view gains
# An ADDED_SETTINGS entry of None is unused while its sibling setting here has the value that
# does what the older code did: then any value of it counts as before.
USED_ONLY_WITH = {"silhouette_samples": "k_select", "lr_normal": "normal_steps",
                  "lambda_normal_prior": "normal_steps", "normal_hold_planar": "normal_steps",
                  "hull_prune_dilate": "hull_prune_views", "detail_max": "detail_prior",
                  "lr_detail": "detail_prior", "detail_edge_px": "detail_prior",
                  "lr_view_gain": "view_gains",
                  "dark_alpha_support": "lambda_dark_alpha",
                  "dark_alpha_margin": "lambda_dark_alpha"}


def _added_as_before(key: str, old: dict, new: dict) -> bool:
    """``key`` is an ``ADDED_SETTINGS`` entry that the older manifest lacks and whose new
    value does what the older code did (None there: any value while the setting is unused,
    ``USED_ONLY_WITH``; e.g. ``silhouette_samples`` unless ``k_select`` is "silhouette")."""
    name = key.rsplit(".", 1)[-1]
    if key in old or name not in ADDED_SETTINGS:
        return False
    before = ADDED_SETTINGS[name]
    if before is None:
        gate = USED_ONLY_WITH[name]
        sibling = key.rsplit(".", 1)[0] + "." + gate if "." in key else gate
        return new.get(sibling, ADDED_SETTINGS[gate]) == ADDED_SETTINGS[gate]
    return new.get(key) == before


def differences(manifest: dict, provenance: Provenance,
                compare: tuple[str, ...] = ("dataset", "inputs", "settings")) -> list[str]:
    """What differs between an existing output and ``provenance``, one phrase per item."""
    new = provenance.to_json()
    out = []
    if "dataset" in compare:
        old_d, new_d = manifest.get("dataset") or {}, new["dataset"] or {}
        if old_d.get("fingerprint") != new_d.get("fingerprint"):
            if old_d.get("path") == new_d.get("path"):
                out.append(f"the dataset {new_d.get('path')} changed since (fingerprint "
                           f"{str(old_d.get('fingerprint'))[:12]} then, "
                           f"{str(new_d.get('fingerprint'))[:12]} now)")
            else:
                out.append(f"it was made from dataset {old_d.get('path')} (fingerprint "
                           f"{str(old_d.get('fingerprint'))[:12]}), not {new_d.get('path')} "
                           f"(fingerprint {str(new_d.get('fingerprint'))[:12]})")
    if "inputs" in compare:
        old_i, new_i = manifest.get("inputs") or {}, new["inputs"]
        for name in sorted(set(old_i) | set(new_i)):
            a, b = old_i.get(name) or {}, new_i.get(name) or {}
            if a.get("digest") != b.get("digest"):
                out.append(f"its input {name} differs ({a.get('path')}, digest "
                           f"{str(a.get('digest'))[:12]} then; {b.get('path')}, digest "
                           f"{str(b.get('digest'))[:12]} now)")
    if "settings" in compare:
        old_s, new_s = _flatten(manifest.get("settings") or {}), _flatten(new["settings"])
        keys = sorted(k for k in set(old_s) | set(new_s) if old_s.get(k) != new_s.get(k)
                      and k.rsplit(".", 1)[-1] not in RESULT_NEUTRAL_SETTINGS
                      and not _added_as_before(k, old_s, new_s))
        phrases = [f"{k}: {json.dumps(old_s.get(k))} there, {json.dumps(new_s.get(k))} now"
                   for k in keys[:_MAX_LISTED]]
        if len(keys) > _MAX_LISTED:
            phrases.append(f"and {len(keys) - _MAX_LISTED} more")
        if phrases:
            out.append("other settings (" + "; ".join(phrases) + ")")
    return out


# -- where a command may write ------------------------------------------------------------
def is_dataset_folder(path: str | os.PathLike) -> bool:
    """A folder holding a dataset: ``transforms_*.json``, ``dataset.json`` or TensoIR views."""
    p = Path(path)
    return p.is_dir() and (any(p.glob("transforms_*.json")) or (p / "dataset.json").is_file()
                           or any(p.glob("train_*/metadata.json"))
                           or any(p.glob("test_*/metadata.json")))


def check_output_location(folder: str | os.PathLike, inputs=(),
                          writes_dataset: bool = False, command: str | None = None,
                          part_of: str | os.PathLike | None = None) -> None:
    """Refuse an output folder that is a file or lies under one (it could never be made),
    one inside a dataset folder, one that holds an input, or one inside what another output
    wrote (``_check_not_inside_an_output``). ``writes_dataset``: the output is a dataset
    (``generate``), so ``folder`` itself may be one; its ancestors still may not.
    ``command`` writes it; ``part_of``: the output whose part it is (a run's stage 4).
    """
    from mi_shadowgs.io.outlock import file_in_the_way

    folder = Path(folder).resolve()
    if (blocked := file_in_the_way(folder)) is not None:
        raise ProvenanceError(blocked)
    for p in (folder.parents if writes_dataset else (folder, *folder.parents)):
        if is_dataset_folder(p):
            where = "is" if p == folder else "is inside"
            raise ProvenanceError(f"{folder}: {where} the dataset folder {p}; outputs never go "
                                  "into a dataset: choose another folder")
    for item in inputs:
        item = Path(item).resolve()
        if item == folder or folder in item.parents:
            raise ProvenanceError(f"{folder}: the output folder holds the input {item}, which "
                                  "the output would overwrite: choose another folder")
    _check_not_inside_an_output(folder, command, part_of)


def _check_not_inside_an_output(folder: Path, command: str | None, part_of) -> None:
    """Refuse ``folder`` when it lies inside a folder that an enclosing output's manifest
    lists as its own (the first folder of a listed file or part: ``RUN/material/x``,
    ``RUN/report/x``): the output's later calls would remove it (``--overwrite``) or read it
    as their own. A listed part itself (``RUN/geometry``) is written by its own command
    (``train``, ``segment``), or by the enclosing command only as that output's part
    (``part_of``): a run's stage 4, ``RUN/material/full``, is not a run of its own. A new
    folder beside an output's files (``RUN/relit``) is free."""
    part_of = Path(part_of).resolve() if part_of is not None else None
    for above in folder.parents:
        try:
            manifest = read_manifest(above)
        except (OSError, ProvenanceError):
            manifest = None  # not ours to judge; the command that reads it will say so
        if manifest is None:
            continue
        rel = folder.relative_to(above)
        listed = [str(n) for n in manifest["files"] + list(manifest.get("parts") or [])]
        if rel.parts[0] not in {Path(n).parts[0] for n in listed if Path(n).parts}:
            continue
        if rel.as_posix() in (manifest.get("parts") or []) and command is not None and (
                command != manifest.get("command") or part_of == above):
            continue
        raise ProvenanceError(
            f"{folder}: lies inside {above / rel.parts[0]}, which `mi-shadowgs "
            f"{manifest.get('command')}` wrote ({above / MANIFEST_NAME} lists it); outputs "
            "never go inside another output: choose another folder")


def read_manifest(folder: str | os.PathLike) -> dict | None:
    """The folder's manifest, or None when it has none."""
    path = Path(folder) / MANIFEST_NAME
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ProvenanceError(f"{path}: malformed manifest: {exc}") from None
    if (not isinstance(manifest, dict) or manifest.get("format") != FORMAT_VERSION
            or not isinstance(manifest.get("files"), list)):
        raise ProvenanceError(f"{path}: not a mi_shadowgs manifest of format {FORMAT_VERSION}")
    return manifest


def _inside(folder: Path, name: str) -> Path:
    path = (folder / name).resolve()
    if folder.resolve() not in path.parents:
        raise ProvenanceError(f"{folder / MANIFEST_NAME}: lists {name!r}, outside the folder")
    return path


def _prune_empty(folder: Path, below: Path) -> None:
    """Remove ``folder`` and its parents while they are empty, stopping at ``below``."""
    below = below.resolve()
    folder = folder.resolve()
    while (folder != below and below in folder.parents and folder.is_dir()
           and not any(folder.iterdir())):
        folder.rmdir()
        folder = folder.parent


def clear(folder: str | os.PathLike, manifest: dict | None = None,
          keep_mark: bool = False) -> None:
    """Remove what the manifest lists (files, their stale temporaries, parts) and itself;
    folders left empty go too. Files the manifest does not list stay. With ``keep_mark``
    (every part) a folder that keeps such files keeps an emptied manifest (no files, no
    provenance): the folder is still its command's to write into (``run --overwrite`` makes
    a run's stages again beside a user's notes there), which a folder of someone else's
    files without one is not."""
    folder = Path(folder)
    manifest = read_manifest(folder) if manifest is None else manifest
    if manifest is None:
        return
    for sub in manifest.get("parts", []):
        clear(_inside(folder, sub), keep_mark=True)
    dirs = set()
    for name in manifest["files"]:
        path = _inside(folder, name)
        remove_stale(path)
        path.unlink(missing_ok=True)
        dirs.add(path.parent)
    remove_stale(folder / MANIFEST_NAME)
    (folder / MANIFEST_NAME).unlink(missing_ok=True)
    for d in sorted(dirs, key=lambda p: len(p.parts), reverse=True):
        if d != folder.resolve():
            remove_stale(d)  # e.g. a killed atomic_dir of figures/
        _prune_empty(d, folder)
    for sub in manifest.get("parts", []):
        _prune_empty(_inside(folder, sub), folder)
    if keep_mark and folder.is_dir() and _foreign_entries(folder, ()):
        write_json(folder / MANIFEST_NAME, {
            "format": FORMAT_VERSION, "command": manifest.get("command"), "complete": False,
            "dataset": None, "inputs": {}, "settings": {}, "files": [], "parts": []})


def _foreign_entries(folder: Path, parts: tuple[str, ...]) -> list[str]:
    """Entries of a folder without a manifest that are not ours to write beside."""
    manifest_tmp = f".{MANIFEST_NAME}."  # a killed first manifest write
    return sorted(p.name for p in folder.iterdir()
                  if p.name not in parts and not p.name.startswith(manifest_tmp))


class Output:
    """One command's output folder, created lazily; its manifest lists every file before the
    file is written. Use as a context manager: a block that fails before writing any file
    leaves no folder (or manifest) of its own behind."""

    def __init__(self, folder: Path, command: str, provenance: Provenance,
                 manifest: dict | None):
        self.folder = folder
        self.command = command
        self.reused = manifest is not None  # an existing output of the same provenance
        self._provenance = provenance
        self._manifest = manifest or {"format": FORMAT_VERSION, "command": command,
                                      "complete": False, **provenance.to_json(),
                                      "files": [], "parts": []}
        self._existing_root = next(p for p in (folder, *folder.parents) if p.exists())
        self._keep_mark = False
        # The backends that wrote the folder before this call (none: a new output, or one
        # from before the record); this call's joins them at its first write (``_save``).
        self.made_before = recorded_backends(self._manifest) if self.reused else []
        self._recorded = False

    @classmethod
    def open(cls, folder: str | os.PathLike, command: str, provenance: Provenance, *,
             overwrite: bool = False, reuse: bool = False, inputs=(), parts=(),
             compare: tuple[str, ...] = ("dataset", "inputs", "settings"),
             continue_flag: str | None = None, writes_dataset: bool = False,
             part_of: str | os.PathLike | None = None) -> Output:
        """Claim ``folder`` for ``command``.

        A previous output of the same command is removed (``overwrite``), reused when its
        provenance matches on ``compare`` (``reuse``; ProvenanceError naming what differs
        otherwise), or refused. ``inputs`` are files the output must not overwrite;
        ``parts`` are sub-folders other commands may have written first (a run's stages);
        ``writes_dataset``, ``part_of``: see ``check_output_location``.
        """
        folder = Path(folder)
        check_output_location(folder, inputs, writes_dataset, command, part_of)
        manifest = read_manifest(folder) if folder.exists() else None
        if manifest is None and folder.exists():
            foreign = _foreign_entries(folder, tuple(parts))
            if foreign:
                raise ProvenanceError(
                    f"{folder}: holds files that mi-shadowgs did not write (no {MANIFEST_NAME};"
                    f" e.g. {foreign[0]}); choose a new or empty folder")
        if manifest is not None and manifest.get("command") != command:
            raise ProvenanceError(f"{folder}: holds the output of `mi-shadowgs "
                                  f"{manifest.get('command')}`, not of `mi-shadowgs {command}`;"
                                  " choose another folder")
        emptied = (manifest is not None and not manifest["files"]
                   and not manifest.get("parts"))
        if emptied:
            manifest = None  # nothing written yet, or emptied by ``clear``: a new output
        if manifest is not None and overwrite:
            clear(folder, manifest, keep_mark=True)  # a kill now: still ours beside the rest
            manifest, emptied = None, True
        if manifest is not None and not reuse:
            hint = f"{continue_flag} to continue it or " if continue_flag else ""
            raise ProvenanceError(f"{folder}: already holds an output of `mi-shadowgs "
                                  f"{command}`: pass {hint}--overwrite to replace it")
        if manifest is not None:
            diff = differences(manifest, provenance, compare)
            if diff:
                raise ProvenanceError(f"{folder}: " + "; ".join(diff) +
                                      ". Pass --overwrite to start over (it removes only the "
                                      "files mi-shadowgs listed there)")
        out = cls(folder, command, provenance, manifest)
        out._keep_mark = emptied  # a failure before any file leaves the folder as it found it
        return out

    @property
    def complete(self) -> bool:
        return bool(self._manifest["complete"])

    @property
    def files(self) -> list[str]:
        return list(self._manifest["files"])

    def _save(self) -> None:
        if not self._recorded:
            self._recorded = True
            self._record_backend()
        write_json(self.folder / MANIFEST_NAME, self._manifest)

    def _record_backend(self) -> None:
        """Add this process's backend (``made_with()``) to the record when it differs from
        the last entry: a new output starts the record; an output continued from before the
        record (no key) stays without one, which says nothing rather than something false."""
        now = made_with()
        if not self.reused:
            self._manifest[MADE_WITH] = [now]
        elif self.made_before and self.made_before[-1] != now:
            self._manifest[MADE_WITH] = [*self.made_before, now]

    def claim(self, *names: str) -> None:
        """List files (paths relative to the folder) before writing them."""
        new = [n for n in names if n not in self._manifest["files"]]
        if new or not (self.folder / MANIFEST_NAME).is_file():
            self._manifest["files"].extend(new)
            self._manifest["complete"] = False
            self._save()

    def path(self, name: str) -> Path:
        """``folder / name``, claimed, its parent folder made."""
        self.claim(name)
        (self.folder / name).parent.mkdir(parents=True, exist_ok=True)
        return self.folder / name

    def add_part(self, name: str) -> None:
        """Own the sub-folder ``name`` (with a manifest of its own) for ``--overwrite``."""
        if name not in self._manifest["parts"]:
            self._manifest["parts"].append(name)
            self._manifest["complete"] = False
        self._save()

    @contextlib.contextmanager
    def staged(self, name: str) -> Iterator[Path]:
        """Make the files of the sub-folder ``name`` (a run's ``report/``, a fit's
        ``figures/``) in a temporary folder, then move them in: each is listed first and
        replaces the earlier file of that name, and the earlier files listed there that were
        not made again go. Files there that the manifest does not list stay (a user's notes:
        the folder was replaced whole before); one of them with the name of a file made is
        refused by name, before anything is moved."""
        dest = self.folder / name
        earlier = {n for n in self._manifest["files"] if n.startswith(f"{name}/")}
        with staged_dir(dest) as tmp:
            yield tmp
            made = sorted(p.relative_to(tmp).as_posix() for p in tmp.rglob("*")
                          if p.is_file())
            names = [f"{name}/{m}" for m in made]
            for n in names:
                if n not in earlier and (self.folder / n).exists():
                    raise ProvenanceError(
                        f"{self.folder / n}: exists and mi-shadowgs did not write it (its "
                        f"{self.folder / MANIFEST_NAME} does not list it); not writing over "
                        "it: move it away")
            self.claim(*names)
            for m in made:
                (dest / m).parent.mkdir(parents=True, exist_ok=True)
                os.replace(tmp / m, dest / m)
            for n in sorted(earlier - set(names)):
                (self.folder / n).unlink(missing_ok=True)

    def finish(self) -> None:
        """Mark the output complete: every listed file is written. A reused output takes
        this call's provenance only now (e.g. a run's new ablations, where only its dataset
        is compared): a call that fails first leaves the manifest as the earlier call made it.
        """
        now = self._provenance.to_json()
        self._manifest.update({k: now[k] for k in ("dataset", "inputs", "settings")})
        self._manifest["complete"] = True
        self._save()

    def __enter__(self) -> Output:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None or self.reused or not (self.folder / MANIFEST_NAME).is_file():
            return
        if any(_inside(self.folder, n).exists() for n in self._manifest["files"]):
            return  # partial work stays for a rerun (resume) or --overwrite
        # Parts keep their own manifests (a stage written before the failure stays usable).
        clear(self.folder, {**self._manifest, "parts": []}, keep_mark=self._keep_mark)
        _prune_empty(self.folder, self._existing_root)


def _git(path: str | os.PathLike | None, *args: str) -> str:
    """``git args`` in the checkout holding ``path`` (default: this package), its output."""
    import subprocess

    where = Path(path) if path is not None else Path(__file__).resolve().parents[1]
    return subprocess.run(["git", "-C", str(where), *args], capture_output=True, text=True,
                          timeout=20, check=True).stdout.strip()


def git_commit(path: str | os.PathLike | None = None) -> str:
    """The commit of the git checkout holding ``path`` (default: this package), with
    ``+changes`` when its tracked files differ from it; "unknown" outside a checkout or
    without git."""
    import subprocess

    try:
        commit = _git(path, "rev-parse", "HEAD")
        dirty = _git(path, "status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return commit + (" +changes" if dirty else "") if commit else "unknown"


def uncommitted_digest(path: str | os.PathLike | None = None) -> str | None:
    """blake2b-128 of the checkout's uncommitted changes to tracked files (``git diff
    HEAD``), which ``git_commit``'s "+changes" does not tell apart; None when there are none
    or outside a checkout."""
    import subprocess

    try:
        diff = _git(path, "diff", "HEAD", "--binary")
    except (OSError, subprocess.SubprocessError):
        return None
    return hashlib.blake2b(diff.encode(), digest_size=16).hexdigest() if diff else None


def device_name(variant: str) -> str:
    """The device a variant runs on: the GPU's name on ``cuda_*`` (``nvidia-smi``), else the
    CPU model (``/proc/cpuinfo``) and its core count; "unknown" when neither can be read."""
    import subprocess

    if variant.startswith("cuda"):
        try:
            names = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                   capture_output=True, text=True, timeout=20,
                                   check=True).stdout.split("\n")
            return names[0].strip() or "unknown GPU"
        except (OSError, subprocess.SubprocessError):
            return "unknown GPU"
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if (line.lower().startswith(("model name", "hardware", "processor\t: "))
                    and ":" in line and not line.split(":", 1)[1].strip().isdigit()):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model} ({os.cpu_count()} cores)"


@functools.cache
def _made_with(variant: str | None, threads: int | None) -> tuple:
    from mi_shadowgs import __version__

    commit = git_commit()
    entry = {"variant": variant}
    if variant is not None:
        entry["device"] = device_name(variant)
    if threads is not None:
        entry["threads"] = threads
    entry["mi_shadowgs"] = commit if commit != "unknown" else f"version {__version__}"
    return tuple(entry.items())


def made_with() -> dict:
    """How this process makes outputs (a manifest's ``made_with`` entry): the active
    Mitsuba variant, its device (``device_name``), Dr.Jit's thread count on LLVM, and
    mi_shadowgs's commit (``git_commit``; its version outside a checkout). The device and
    commit are read once per process."""
    import mitsuba as mi

    variant = mi.variant()
    threads = None
    if variant is not None and variant.startswith("llvm"):
        import drjit as dr

        threads = int(dr.thread_count())
    return dict(_made_with(variant, threads))


def recorded_backends(manifest: dict | None) -> list[dict]:
    """The entries of a manifest's ``made_with`` record, oldest first; [] for a manifest
    from before the record (or one whose record is not a list of objects)."""
    record = (manifest or {}).get(MADE_WITH)
    if isinstance(record, dict):
        record = [record]
    if not isinstance(record, list) or not all(isinstance(e, dict) for e in record):
        return []
    return [dict(e) for e in record]


def recorded_variants(manifest: dict | None) -> list[str]:
    """The distinct variants of a manifest's record, in the order they first wrote."""
    return variants_of(recorded_backends(manifest))


def variants_of(entries: list[dict]) -> list[str]:
    """The distinct variants of ``made_with`` entries (``recorded_backends``, or an
    ``Output``'s ``made_before``), in the order they first wrote."""
    out = []
    for entry in entries:
        v = entry.get("variant")
        if isinstance(v, str) and v not in out:
            out.append(v)
    return out
