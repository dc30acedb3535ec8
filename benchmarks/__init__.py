"""Benchmarks of mi_shadowgs (pytorch3d-style ``bm_*`` modules; never run as tests).

``python -m benchmarks.run_all --out DIR`` (``make bench``) runs them all and writes CSV,
JSON, PNG figures and a markdown summary into DIR.
"""

from mi_shadowgs import backend

# Before any drjit use: a libLLVM that Dr.Jit runs, and a variant (or one line saying what to
# install, instead of an abort inside drjit).
backend.ensure_variant()
