"""Test-wide settings: one BLAS thread per process, as the `csr` command and the workers use."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
