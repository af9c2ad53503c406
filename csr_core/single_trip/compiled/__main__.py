"""``python -m csr_core.single_trip.compiled``: compile every kernel into numba's cache (``warm_up``)."""

import sys

from csr_core.single_trip.compiled.warm_up import main

sys.exit(main())
