# The CSR service image: `csr serve` (API, migrates at start) and `csr worker` (Celery).
# Build stage: a virtualenv from the hashed lock (its own layer: rebuilt only when requirements.lock
# changes), then the project as a wheel (non-editable). Runtime stage: that virtualenv, Alembic's
# scripts and a non-root user; no compiler, no pip cache, no source tree.
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python -m venv /opt/csr
COPY requirements.lock /tmp/requirements.lock
RUN /opt/csr/bin/pip install --require-hashes --no-deps -r /tmp/requirements.lock
WORKDIR /src
COPY pyproject.toml README.md ./
COPY csr_core ./csr_core
COPY services ./services
COPY workers ./workers
RUN /opt/csr/bin/pip install --no-deps . \
    && /opt/csr/bin/pip check

FROM ${PYTHON_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PATH=/opt/csr/bin:$PATH \
    CSR_DATA_DIR=/data \
    CSR_MIGRATIONS_DIR=/app/migrations
RUN useradd --create-home --uid 1000 --user-group csr \
    && mkdir -p /data && chown csr:csr /data
COPY --from=build /opt/csr /opt/csr
WORKDIR /app
COPY alembic.ini ./
COPY migrations ./migrations
USER csr
# the splicing stage's numba kernels, compiled into the user's numba cache at build time (30-40 s)
RUN python -m csr_core.single_trip.compiled
EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=5s --start-period=30s --retries=5 \
    CMD python -c "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4).status != 200)"
CMD ["csr", "serve", "--host", "0.0.0.0", "--port", "8000"]
