"""Ground-truth cross-checks, paper tables and speed-vs-error reports (``make validate``)."""

import mi_shadowgs  # noqa: F401  (before any drjit import: finds libLLVM, selects the variant)
