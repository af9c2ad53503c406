"""Celery app and tasks: thin adapters (load -> csr_core -> persist)."""

import os

# One BLAS thread per worker process (see services/cli/__init__.py): set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
