"""Benchmarks of mi_shadowgs (pytorch3d-style ``bm_*`` modules; never run as tests).

``python -m benchmarks.run_all --out DIR`` (``make bench``) runs them all and writes CSV,
JSON, PNG figures and a markdown summary into DIR.
"""
