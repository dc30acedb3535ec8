"""Ground-truth cross-checks, paper tables and speed-vs-error reports (``make validate``)."""

from mi_shadowgs import backend

# Before any drjit use: a libLLVM that Dr.Jit runs, and a variant (or one line saying what to
# install, instead of an abort inside drjit).
backend.ensure_variant()
