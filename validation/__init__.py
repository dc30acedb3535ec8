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
