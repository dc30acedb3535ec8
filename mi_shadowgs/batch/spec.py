"""What a batch runs: its items, read from a folder of captures or a TOML/JSON file.

An ``Item`` is one unit of work with its resources: a few commands (``Step``: a Python
module run with ``-m``) that run one after the other in one Ray task, the run folder they
leave (whose summary gives the batch's figures), and what it needs (CPUs, a GPU). A capture
is an ``import`` (photos) then a ``run``; ``validation.pipeline`` makes items of its own.

A SPEC is either

- a folder of captures, one sub-folder each: a dataset (``mi-shadowgs generate``, an
  earlier ``import``, TensoIR), photos (JPEG/PNG, directly or in ``photos/`` with an
  optional ``masks/`` beside), or a nerfstudio ``transforms.json`` with its images; or
- a ``.toml``/``.json`` file: top-level defaults (``preset``, ``set``, ``seed``,
  ``variant``, ``cpus``) and a list ``items`` of tables, each with ``source`` (relative to
  the file) and optionally ``name``, ``masks`` and the same defaults.

The most specific value wins: an item's, the file's, the command line's, then ``cpu-small``,
one CPU and the default variant. ``set`` lists add up in that order (a later one wins).
Every item's settings are built into the run's settings tree (``mi_shadowgs.presets``)
before anything starts, so that a misspelt setting is an error naming its item, not a
failure an hour later.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

# The folders and files of one capture item under the batch folder.
DATA, RUN = "data", "run"
# Files the batch writes into its folder; no item may be named like them.
BATCH_FILES = ("batch.csv", "batch.html", "batch.json")
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
# The settings a spec gives at its top level and per item.
DEFAULT_KEYS = ("preset", "set", "seed", "variant", "cpus")
ITEM_KEYS = ("name", "source", "masks", *DEFAULT_KEYS)
CLI_MODULE = "mi_shadowgs.cli"


@dataclasses.dataclass(frozen=True)
class Step:
    """One command of an item: ``python -m module *args``."""

    name: str
    """What the step does (``import``, ``run``), named in an error."""
    module: str
    """The Python module run with ``-m`` (its ``main``)."""
    args: tuple[str, ...]
    """Its arguments."""
    creates: str | None = None
    """A folder under the item's folder whose presence means the step is done (written
    atomically); ``inputs`` must be what it was made from."""
    inputs: tuple[str, ...] = ()
    """Files or folders the ``creates`` folder was made from (compared by content)."""


@dataclasses.dataclass(frozen=True)
class Item:
    """One unit of a batch: its steps, in one Ray task with its resources."""

    name: str
    """Its name in the tables (unique in a batch)."""
    folder: str
    """Its folder under the batch folder (its log and the steps' outputs)."""
    run: str
    """The run folder its steps leave, under the batch folder (figures, report)."""
    steps: tuple[Step, ...]
    """Its commands, in order."""
    cpus: int = 1
    """CPUs of its Ray task, and Dr.Jit threads of its commands."""
    gpus: int = 0
    """GPUs of its Ray task (1 for the cuda_ad_rgb variant)."""
    env: tuple[tuple[str, str], ...] = ()
    """Environment variables its commands get."""
    after: tuple[str, ...] = ()
    """Earlier items (names) that must finish first."""
    done: str | None = None
    """A file under the batch folder whose presence means the item is finished (it is then
    not run again)."""
    source: str = ""
    """What it was made from (shown in the tables)."""
    preset: str = ""
    """Its preset (shown in the tables)."""


class SpecError(ValueError):
    """A batch SPEC that cannot be run; the message names the file, item or setting."""


def capture_source(path: Path) -> tuple[str, Path, Path | None]:
    """(kind, source, masks) of one capture: ``dataset`` (the folder), or ``photos`` (a
    photo folder or a nerfstudio ``transforms.json``, and a masks folder or None)."""
    from mi_shadowgs.io.provenance import is_dataset_folder

    if path.is_file():
        if path.suffix.lower() == ".json":
            return "photos", path, None
        raise SpecError(f"{path}: a file; a capture is a folder (or a transforms.json)")
    if not path.is_dir():
        raise SpecError(f"{path}: not found")
    if is_dataset_folder(path):
        return "dataset", path, None
    if (path / "transforms.json").is_file():
        return "photos", path / "transforms.json", None
    if (path / "photos").is_dir():
        masks = path / "masks"
        return "photos", path / "photos", masks if masks.is_dir() else None
    if any(p.suffix.lower() in PHOTO_SUFFIXES for p in path.iterdir() if p.is_file()):
        return "photos", path, None
    raise SpecError(f"{path}: neither a dataset (transforms_*.json, dataset.json) nor photos "
                    "(JPEG/PNG, a photos/ folder, or a transforms.json)")


def check_name(name: Any, where: str) -> str:
    """``name`` as an item's folder name, or SpecError naming ``where``."""
    if (not isinstance(name, str) or not name or name.startswith(".") or "/" in name
            or os.sep in name or name in BATCH_FILES):
        raise SpecError(f"{where}: item name {name!r}: a folder name is needed (not empty, "
                        f"no '/', not starting with '.', not one of {BATCH_FILES})")
    return name


def _settings(entry: dict, defaults: dict, where: str) -> dict:
    """The item's preset, --set list, seed, variant and CPUs, checked against the settings
    tree (an error names ``where``)."""
    from mi_shadowgs.backend import SUPPORTED_VARIANTS
    from mi_shadowgs.presets import build, import_config, parse_sets

    out = {k: entry.get(k, defaults.get(k)) for k in DEFAULT_KEYS}
    out["set"] = [*defaults.get("set", ()), *entry.get("set", ())]
    out["preset"] = out["preset"] or "cpu-small"
    out["cpus"] = 1 if out["cpus"] is None else out["cpus"]
    if isinstance(out["cpus"], bool) or not isinstance(out["cpus"], int) or out["cpus"] < 1:
        raise SpecError(f"{where}: cpus must be a whole number >= 1, got {out['cpus']!r}")
    if out["variant"] is not None and out["variant"] not in SUPPORTED_VARIANTS:
        raise SpecError(f"{where}: variant {out['variant']!r}: one of {SUPPORTED_VARIANTS}")
    if not all(isinstance(s, str) for s in out["set"]):
        raise SpecError(f"{where}: set must be a list of SECTION.FIELD=VALUE strings")
    try:
        build(out["preset"], parse_sets(out["set"]), seed=out["seed"])
        import_config(out["preset"])
    except ValueError as exc:
        raise SpecError(f"{where}: {exc}") from None
    return out


def capture_item(name: str, source: Path, out: Path, settings: dict,
                 masks: Path | None = None, kind: str | None = None) -> Item:
    """The item of one capture: ``import`` (photos) into ``OUT/NAME/data``, then ``run``
    into ``OUT/NAME/run``, at ``settings`` (``_settings``). Paths are absolute: the commands
    may run on another machine of a cluster (a shared file system)."""
    source, folder = source.resolve(), Path(out).resolve() / name
    if kind is None:
        kind, source, found = capture_source(source)
        masks = masks or found
    common: tuple[str, ...] = ("--threads", str(settings["cpus"]))
    if settings["variant"]:
        common += ("--variant", settings["variant"])
    data = source if kind == "dataset" else folder / DATA
    steps = []
    if kind == "photos":
        # a transforms.json names its images relative to its folder: the folder is the input
        photos = source.parent if source.suffix.lower() == ".json" else source
        inputs = (str(photos),) + ((str(masks.resolve()),) if masks else ())
        args = (*common, "import", str(source), "--out", str(data),
                "--preset", settings["preset"], "--no-progress")
        if masks:
            args += ("--masks", str(masks.resolve()))
        steps.append(Step("import", CLI_MODULE, args, creates=DATA, inputs=inputs))
    run = (*common, "run", str(data), "--out", str(folder / RUN), "--preset",
           settings["preset"], "--no-progress")
    for s in settings["set"]:
        run += ("--set", s)
    if settings["seed"] is not None:
        run += ("--seed", str(settings["seed"]))
    steps.append(Step("run", CLI_MODULE, run))
    return Item(name=name, folder=name, run=f"{name}/{RUN}", steps=tuple(steps),
                cpus=settings["cpus"], gpus=int(settings["variant"] == "cuda_ad_rgb"),
                source=str(source), preset=settings["preset"])


def read_spec(spec: str | os.PathLike, out: str | os.PathLike,
              defaults: dict | None = None) -> list[Item]:
    """The items of ``spec`` (a folder of captures, or a TOML/JSON file) for the batch
    folder ``out`` (skipped when it lies in the folder of captures), with the command line's
    ``defaults`` (keys of ``DEFAULT_KEYS``). SpecError names what is wrong."""
    spec, out = Path(spec), Path(out)
    defaults = dict(defaults or {})
    if spec.is_dir():
        entries = [{"name": p.name, "source": str(p)} for p in sorted(spec.iterdir())
                   if p.is_dir() and not p.name.startswith(".")
                   and p.resolve() != out.resolve()]
        if not entries:
            raise SpecError(f"{spec}: holds no capture folders")
        base = spec
    elif spec.is_file():
        top = _read_file(spec)
        entries = top.pop("items")
        defaults = {**defaults, **{k: v for k, v in top.items() if k != "set"},
                    "set": [*defaults.get("set", ()), *top.get("set", ())]}
        base = spec.parent
    else:
        raise SpecError(f"{spec}: not found (a folder of captures or a .toml/.json file)")
    items, seen = [], {}
    for entry in entries:
        source = base / entry["source"]
        where = f"{spec}: item {entry.get('name') or source.stem}"
        name = check_name(entry.get("name") or source.stem, where)
        if name in seen:
            raise SpecError(f"{spec}: two items are named {name!r} ({seen[name]} and "
                            f"{source}); give each its own name")
        seen[name] = source
        settings = _settings(entry, defaults, where)
        try:
            kind, src, masks = capture_source(source)
        except SpecError as exc:
            raise SpecError(f"{where}: {exc}") from None
        if entry.get("masks") is not None:
            if kind != "photos":
                raise SpecError(f"{where}: masks are for photos; {source} is a dataset")
            masks = base / entry["masks"]
            if not masks.is_dir():
                raise SpecError(f"{where}: masks {masks}: not a folder")
        items.append(capture_item(name, src, out, settings, masks, kind))
    return items


def _read_file(path: Path) -> dict:
    """A spec file's top level (checked keys; ``items`` a non-empty list of tables)."""
    try:
        if path.suffix.lower() == ".toml":
            try:
                import tomllib
            except ImportError:  # Python 3.10
                raise SpecError(f"{path}: TOML needs Python 3.11 or later; write the spec "
                                "as JSON") from None
            top = tomllib.loads(path.read_text())
        elif path.suffix.lower() == ".json":
            top = json.loads(path.read_text())
        else:
            raise SpecError(f"{path}: a spec file is .toml or .json")
    except (OSError, ValueError) as exc:
        if isinstance(exc, SpecError):
            raise
        raise SpecError(f"{path}: does not read as {path.suffix[1:].upper()}: {exc}") from None
    if (not isinstance(top, dict) or not isinstance(top.get("items"), list)
            or not top["items"]):
        raise SpecError(f"{path}: needs a non-empty list 'items' (each with a 'source')")
    unknown = sorted(set(top) - {"items", *DEFAULT_KEYS})
    if unknown:
        raise SpecError(f"{path}: unknown key(s) {unknown}; known: {sorted(DEFAULT_KEYS)} "
                        "and items")
    for i, entry in enumerate(top["items"]):
        if not isinstance(entry, dict) or not isinstance(entry.get("source"), str):
            raise SpecError(f"{path}: items[{i}] needs a 'source' (a path)")
        unknown = sorted(set(entry) - set(ITEM_KEYS))
        if unknown:
            raise SpecError(f"{path}: items[{i}]: unknown key(s) {unknown}; known: "
                            f"{sorted(ITEM_KEYS)}")
    return top
