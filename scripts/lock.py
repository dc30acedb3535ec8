"""Writes constraints.txt: the exact versions of the packages in .venv (after `make test`'s
set-up, so the dev tools and JAX too), each for the Python minor they were tested on.

scripts/setup.sh installs with `pip -c constraints.txt`, so a fresh machine gets the versions
the suite passed with, not whatever the registry holds that day (a newer NumPy's OpenBLAS once
rounded rows differently and failed two tests of a fresh set-up). The environment marker keeps
other Pythons working: there pip ignores every line and pyproject.toml's ranges apply.

    make lock    (= .venv/bin/python scripts/lock.py), then make test from zero, then commit
"""

from __future__ import annotations

import subprocess
import sys
from datetime import date
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    if Path(sys.prefix).resolve() != (ROOT / ".venv").resolve():
        print(f"lock: run with {ROOT / '.venv' / 'bin' / 'python'}, not {sys.executable}",
              file=sys.stderr)
        return 2
    frozen = subprocess.run(
        [sys.executable, "-m", "pip", "freeze", "--exclude-editable"],
        check=True, capture_output=True, text=True).stdout.split()
    minor = f"{sys.version_info.major}.{sys.version_info.minor}"
    lines = [
        "# The versions `make test` passed with; written by scripts/lock.py (make lock) on",
        f"# {date.today().isoformat()}. Python {minor} only: other Pythons install the newest",
        "# versions pyproject.toml allows.",
        *(f'{pin} ; python_version == "{minor}"' for pin in sorted(frozen, key=str.lower)
          if "==" in pin),
    ]
    (ROOT / "constraints.txt").write_text("\n".join(lines) + "\n")
    print(f"lock: {len(lines) - 3} packages for Python {minor} in constraints.txt")
    return 0


if __name__ == "__main__":
    sys.exit(main())
