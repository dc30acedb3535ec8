"""Ground-truth cross-checks, paper tables and speed-vs-error reports (``make validate``)."""

from typing import NoReturn

from mi_shadowgs import backend

# Before any drjit use: a libLLVM that Dr.Jit runs, and a variant (or one line saying what to
# install, instead of an abort inside drjit).
backend.ensure_variant()


def fail(message: str) -> NoReturn:
    """Stop a validation command: ``message`` (naming the file, field or option) on stderr,
    exit status 2, as every command of the project exits on bad input."""
    import sys

    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


# A study's folder mark: written when a study takes a new or empty --out, so that a rerun
# (which resumes or replaces its own files) can tell its folder from someone else's.
STUDY_MARK = ".mi_shadowgs_study.json"


def claim_out(out, study: str, earlier: tuple[str, ...] = (), inputs=()):
    """``out`` as study ``study``'s output folder, or exit 2 when it is someone else's: a
    study writes named files into it, and must never write over files it did not write.
    Taken when new or empty (the mark is written), when it holds this study's mark, or when
    it holds one of ``earlier`` (what this study wrote before the mark existed). Like every
    output, it may not lie in a dataset folder nor hold one of ``inputs`` (the files and
    folders the study reads). Returns ``out`` as a Path."""
    import json
    from pathlib import Path

    from mi_shadowgs.io.atomic import write_json
    from mi_shadowgs.io.provenance import ProvenanceError, check_output_location

    out = Path(out)
    try:
        check_output_location(out, inputs)
    except ProvenanceError as exc:
        fail(f"--out: {exc}")
    if out.exists() and not out.is_dir():
        fail(f"--out {out}: exists and is not a folder")
    mark = out / STUDY_MARK
    if mark.is_file():
        try:
            owner = json.loads(mark.read_text()).get("study")
        except (OSError, ValueError, AttributeError):
            owner = None
        if owner != study:
            fail(f"--out {out}: holds the output of {owner or 'an unknown study'}, not of "
                 f"{study}; name another folder")
        return out
    if out.exists() and any(out.iterdir()) and \
            not any((out / name).exists() for name in earlier):
        fail(f"--out {out}: exists and holds files {study} did not write (no {STUDY_MARK}); "
             f"name a new or empty folder")
    out.mkdir(parents=True, exist_ok=True)
    write_json(mark, {"study": study})
    return out
