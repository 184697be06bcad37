# syntax=docker/dockerfile:1
# The bodyfit service: REST on 8000, gRPC on 50051, model assets baked in, runs as a non-root user and needs
# no network at run time. Every Python package comes from the hashed lock (requirements/server.txt, made by
# scripts/lock.sh), so the image holds the same versions as the README's install and CI.
#   docker build -t bodyfit .
#   docker run --rm -p 127.0.0.1:8000:8000 -p 127.0.0.1:50051:50051 bodyfit
#   docker build --target ray -t bodyfit-ray .        (Ray head / worker image, see docker-compose.yml)
# Build arguments:
#   BASE           a Debian-based image with Python 3.11 (default python:3.11-slim); a base without Python
#                  (e.g. debian:bookworm) gets python3 and python3-venv from apt
#   TORCH_INDEX    where torch's CPU build comes from (it is not on PyPI)
#   PIP_INDEX_URL  the index of every other package (a PyPI mirror)
# Optional build inputs (the build is the same without them):
#   --build-context torch-wheels=DIR   a folder holding torch's CPU wheel, used before TORCH_INDEX
#   --secret id=ca,src=FILE            a CA bundle for pip, for networks that re-sign TLS
# scripts/check_image.sh builds the image with podman and checks it.
ARG BASE=python:3.11-slim

# Empty: replaced by the folder given with --build-context torch-wheels=DIR.
FROM scratch AS torch-wheels

FROM ${BASE} AS base
RUN if ! python3 -c "import ensurepip, venv" 2>/dev/null; then \
        apt-get update \
        && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends python3 python3-venv \
        && rm -rf /var/lib/apt/lists/*; \
    fi \
    && python3 -c "import sys; assert sys.version_info[:2] == (3, 11), 'the lock is for Python 3.11, not ' + sys.version"

# The locked dependencies in a virtual environment (one layer that changes only with the lock).
FROM base AS deps
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
ARG PIP_INDEX_URL=https://pypi.org/simple
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
COPY requirements/server.txt requirements/
# torch first, on its own and with the lock's hash: its CPU build comes from the local wheel folder when one
# was given, else from TORCH_INDEX.
RUN --mount=type=bind,from=torch-wheels,target=/wheels \
    --mount=type=secret,id=ca \
    if [ -f /run/secrets/ca ]; then export PIP_CERT=/run/secrets/ca; fi; \
    awk '/^torch==/{on=1} on{print; if ($0 !~ /\\$/) exit}' requirements/server.txt > /tmp/torch.txt \
    && grep -q '^torch==' /tmp/torch.txt \
    && if ls /wheels/torch-*.whl >/dev/null 2>&1 \
          && pip install --no-deps --require-hashes --no-index --find-links /wheels -r /tmp/torch.txt; then :; \
       else pip install --no-deps --require-hashes --index-url "$TORCH_INDEX" -r /tmp/torch.txt; fi \
    && rm /tmp/torch.txt
# The rest of the [server] extra (and setuptools, bodyfit's build backend), every file checked against the lock.
RUN --mount=type=secret,id=ca \
    if [ -f /run/secrets/ca ]; then export PIP_CERT=/run/secrets/ca; fi; \
    pip install --no-deps --require-hashes -r requirements/server.txt

# Ray's environment: the service's plus the [ray] extra from requirements/ray.txt (same versions).
FROM deps AS deps-ray
COPY requirements/ray.txt requirements/
RUN --mount=type=secret,id=ca \
    if [ -f /run/secrets/ca ]; then export PIP_CERT=/run/secrets/ca; fi; \
    pip install --no-deps --require-hashes -r requirements/ray.txt

# bodyfit itself as a wheel, built offline with the locked setuptools.
FROM deps AS wheel
COPY pyproject.toml README.md ./
COPY bodyfit ./bodyfit
RUN pip wheel --no-deps --no-build-isolation --no-index --wheel-dir /dist .

# Ray head / worker image for batch upgrades (docker compose --profile ray): the same code and assets as the
# service, so workers run bodyfit tasks.
FROM base AS ray
RUN useradd --create-home --uid 10001 bodyfit
COPY --from=deps-ray /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
COPY --from=wheel /dist /tmp/dist
RUN pip install --no-deps --no-index /tmp/dist/bodyfit-*.whl && rm -rf /tmp/dist
COPY assets /app/assets
ENV BODYFIT_ASSETS=/app/assets PYTHONUNBUFFERED=1
USER bodyfit
WORKDIR /app

# The service (the default target). BODYFIT_HOST / BODYFIT_REST_PORT / BODYFIT_GRPC_PORT move it (e.g. with
# --network host); the other BODYFIT_* limits are read by the server itself (see the README).
FROM base AS service
RUN useradd --create-home --uid 10001 bodyfit
COPY --from=deps /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
COPY --from=wheel /dist /tmp/dist
RUN pip install --no-deps --no-index /tmp/dist/bodyfit-*.whl && rm -rf /tmp/dist
COPY assets /app/assets
ENV BODYFIT_ASSETS=/app/assets \
    BODYFIT_HOST=0.0.0.0 \
    BODYFIT_REST_PORT=8000 \
    BODYFIT_GRPC_PORT=50051 \
    PYTHONUNBUFFERED=1
USER bodyfit
WORKDIR /app
EXPOSE 8000 50051
HEALTHCHECK --interval=15s --timeout=3s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import os, sys, urllib.request; url = 'http://127.0.0.1:%s/readyz' % os.environ.get('BODYFIT_REST_PORT', '8000'); sys.exit(urllib.request.urlopen(url, timeout=2).status != 200)"]
# bodyfit serve reads BODYFIT_HOST, BODYFIT_REST_PORT, BODYFIT_GRPC_PORT and the limits from the environment
CMD ["bodyfit", "serve"]
