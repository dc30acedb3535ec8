"""A study's work in units that survive a kill.

A unit is one piece of a study's work that is worth keeping on its own: a variant's stage-4
fit, one model scored against ray tracing, one dataset at one view size. Each is an output
folder of its own, ``OUT/units/<name>/``, with a manifest of what it was made from
(``mi_shadowgs.io.provenance``: the dataset's fingerprint, the input files' digests, the
settings). A rerun of the study

- reuses a finished unit whose dataset, inputs and settings match;
- continues an unfinished one (from its ``checkpoint/`` when the unit's work has one, or
  from the start when it is short);
- exits 2 naming what differs otherwise, so a study never mixes results made from other
  inputs or settings. ``overwrite`` removes the unit's own files first.

The study writes its tables (``summary.json`` and the like) from its units at the end, each
atomically; the units stay beside them, so a second call with the same arguments only
gathers.
"""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Callable, Iterator
from pathlib import Path

from mi_shadowgs.io.atomic import atomic_dir, write_json
from mi_shadowgs.io.provenance import Output, Provenance, ProvenanceError
from validation import fail

UNITS = "units"
RESULT = "result.json"
SMOKE = "quick-"  # a smoke run's (--quick) unit names start with it


def open_unit(out: str | Path, name: str, study: str, provenance: Provenance, *,
              overwrite: bool = False, inputs=()) -> Output:
    """The unit ``OUT/units/<name>/`` of ``study``: claimed, reused or continued as the
    module says; exit 2 naming the folder and the difference when it was made otherwise.
    ``inputs``: files the unit must not hold (its model, its dataset)."""
    try:
        return Output.open(Path(out) / UNITS / name, study, provenance, overwrite=overwrite,
                           reuse=True, inputs=inputs)
    except ProvenanceError as exc:
        fail(f"{exc} (a unit of {study})")


def finished(unit: Output) -> dict | None:
    """A finished unit's result, or None while it is still to be done."""
    path = unit.folder / RESULT
    if not (unit.complete and path.is_file()):
        return None
    return json.loads(path.read_text())


def finish(unit: Output, result: dict) -> dict:
    """Record ``result`` (JSON values) and mark the unit finished."""
    write_json(unit.path(RESULT), result)
    unit.finish()
    return result


def run_unit(out: str | Path, name: str, study: str, provenance: Provenance,
             work: Callable[[Output], dict], *, overwrite: bool = False,
             inputs=()) -> dict:
    """The result of unit ``name``: the recorded one when the unit is finished with the same
    provenance, else ``work(unit)``'s (which may write files through ``unit.path`` and keep a
    checkpoint with ``mi_shadowgs.stages.common.checkpoint_hooks``), recorded."""
    unit = open_unit(out, name, study, provenance, overwrite=overwrite, inputs=inputs)
    done = finished(unit)
    if done is not None:
        return done
    with unit:
        return finish(unit, work(unit))


def settings_of(**values) -> dict:
    """Settings for a unit's provenance: ``values`` as JSON (tuples as lists, paths as
    strings), so that a rerun's settings compare equal to the recorded ones."""
    return json.loads(json.dumps(values, default=str))


def unit_name(*parts) -> str:
    """A unit's folder name made of ``parts`` (a case's name, a method, a size): in each part
    every run of characters other than letters, digits, '.', '_' and '-' becomes one '_';
    the parts are joined by '-'. Distinct texts can map to one name ("a b", "a_b"): a study
    whose names come from free text checks that its names differ."""
    return "-".join(re.sub(r"[^A-Za-z0-9._-]+", "_", str(p)).strip("_") or "_" for p in parts)


def smoke_name(name: str, quick: bool) -> str:
    """Unit ``name`` of a smoke run (``quick``) or a full one: a smoke run's units are its own
    (``SMOKE``), so a full run into the same folder after it (``make validate`` after a quick
    one) makes its own instead of being refused for the smaller settings."""
    return SMOKE + name if quick else name


@contextlib.contextmanager
def staged_folder(unit: Output, name: str) -> Iterator[Path]:
    """The unit's sub-folder ``name`` for work that writes files of its own choosing (a
    benchmark suite into its folder): yields a temporary sibling, moved into place whole when
    the block succeeds (``atomic_dir``), each of its files listed in the unit's manifest just
    before (so that ``overwrite`` removes them). A kill leaves only the temporary, which the
    next try removes."""
    unit.claim()  # the manifest first: a kill never leaves the unit folder without one
    with atomic_dir(unit.folder / name, overwrite=True) as tmp:
        yield tmp
        unit.claim(*sorted(f"{name}/{p.relative_to(tmp).as_posix()}"
                           for p in tmp.rglob("*") if p.is_file()))
