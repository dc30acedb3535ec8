"""``python -m mi_shadowgs.cli``: the ``mi-shadowgs`` command (used by tests in a subprocess)."""

import sys

from mi_shadowgs.cli import main

sys.exit(main())
