# The CSR service image: `csr serve` (API, migrates at start) and `csr worker` (Celery).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    CSR_DATA_DIR=/data

WORKDIR /app
COPY pyproject.toml README.md alembic.ini ./
COPY csr_core ./csr_core
COPY services ./services
COPY workers ./workers
COPY migrations ./migrations
# editable: the migrations are found next to the `services` package
RUN pip install -e '.[ops]' \
    && useradd --create-home --uid 1000 csr \
    && mkdir -p /data && chown csr /data

USER csr
# the splicing stage's numba kernels, compiled into the user's numba cache at build time (30-40 s)
RUN python -m csr_core.single_trip.compiled
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=5 \
    CMD python -c "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status != 200)"
CMD ["csr", "serve", "--host", "0.0.0.0", "--port", "8000"]
