"""What the dataset fingerprint of run provenance costs (``mi_shadowgs.dataset.fingerprint``).

Every ``train`` / ``segment`` / ``run`` hashes the dataset's files once per process. This
times that hash on the cpu-small dataset layout (128^2, 64 + 32 views, every ground-truth
buffer) against loading the same splits, which reads the same bytes::

    python -m benchmarks.run_all --out bench-out --only fingerprint
"""

from __future__ import annotations

import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

ROUNDS = 5
# Path-traced noise barely changes the files' sizes; 16 spp keeps generation to ~10 s.
SPP = 16


def _median_seconds(fn, rounds: int = ROUNDS) -> float:
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def run_suite(out: Path, preset: str = "paper", log=print) -> dict:
    """Both presets time the same dataset: the figure of interest is bytes per second."""
    with tempfile.TemporaryDirectory() as tmp:
        return _measure(Path(out), Path(tmp) / "data", log)


def _measure(out: Path, data: Path, log) -> dict:
    from mi_shadowgs.dataset import fingerprint
    from mi_shadowgs.dataset.loader import load_dataset
    from mi_shadowgs.dataset.writer import write_dataset
    from mi_shadowgs.io.atomic import write_json
    from mi_shadowgs.presets import generate_config as get_config
    from mi_shadowgs.scenes import scene_path

    write_dataset(scene_path("default"), data, dataclasses.replace(get_config("cpu-small"),
                                                                  spp=SPP, envmaps="sky"),
                  "cpu-small", seed=0, progress=False)
    files = fingerprint._dataset_files(data.resolve())
    megabytes = sum(st.st_size for _, st in files) / 1e6

    def fresh():
        fingerprint._DIGESTS.clear()  # white box: time the hash, not the in-process cache
        fingerprint.dataset_fingerprint(data)

    hashed = _median_seconds(fresh)
    cached = _median_seconds(lambda: fingerprint.dataset_fingerprint(data))
    loaded = _median_seconds(lambda: (load_dataset(data, "train"), load_dataset(data, "test")),
                             rounds=3)
    row = {"files": len(files), "megabytes": megabytes, "hash_s": hashed, "cached_s": cached,
           "load_s": loaded, "hash_mb_per_s": megabytes / hashed}
    write_json(out / "fingerprint.json", row)
    log(f"[fingerprint] {len(files)} files, {megabytes:.1f} MB: hash {hashed:.3f} s "
        f"({row['hash_mb_per_s']:.0f} MB/s), cached {cached:.3f} s, load {loaded:.2f} s")
    md = ("## Dataset fingerprint (run provenance)\n\n"
          "| files | MB | fingerprint (s) | MB/s | again in-process (s) | load train+test (s) |\n"
          "|---|---|---|---|---|---|\n"
          f"| {len(files)} | {megabytes:.1f} | {hashed:.3f} | {row['hash_mb_per_s']:.0f} | "
          f"{cached:.3f} | {loaded:.2f} |\n")
    return {"markdown": md, **row}
