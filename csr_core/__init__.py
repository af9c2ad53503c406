"""CSR core: the pure reconstruction algorithm (paper: CSR, Li Auto).

Pure functions and frozen dataclasses over numpy arrays. This package never imports the
web, database or queue layers (fastapi, sqlalchemy, celery, redis, services, workers);
``tests/unit/test_core_purity.py`` fails if it does.
"""

__version__ = "0.1.0"
