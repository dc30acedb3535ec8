"""Batches of runs on a Ray cluster (``mi-shadowgs batch``): many captures, or the rows of
a validation table, each an ``Item`` of commands run as one Ray task with its resources.

``spec`` reads a batch (a folder of captures or a TOML/JSON file) into items, ``runner``
runs them (``run_batch``: a local Ray runtime or a cluster), ``report`` writes
``batch.csv`` and ``batch.html``. Ray is the optional ``cluster`` extra; nothing here
imports it before a batch runs. docs/cluster.md says how to start a cluster.
"""
