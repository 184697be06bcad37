# The bodyfit service: REST on 8000, gRPC on 50051, model assets baked in, runs as a non-root user.
#   docker build -t bodyfit .
#   docker run --rm -p 8000:8000 -p 50051:50051 bodyfit
FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# The CPU build of torch, pinned (the default wheel pulls CUDA libraries the service does not use).
RUN pip install --index-url https://download.pytorch.org/whl/cpu "torch==2.13.0"
WORKDIR /src
COPY pyproject.toml README.md ./
COPY bodyfit ./bodyfit
RUN pip install ".[server]"

# Ray head / worker image for batch upgrades (docker compose --profile ray): the service's environment plus
# ray, so workers run bodyfit tasks with the same code and assets.
FROM build AS build-ray
RUN pip install ".[server,ray]"

FROM python:3.11-slim AS ray
RUN useradd --create-home --uid 10001 bodyfit
COPY --from=build-ray /opt/venv /opt/venv
COPY --chown=bodyfit:bodyfit assets /app/assets
ENV PATH=/opt/venv/bin:$PATH BODYFIT_ASSETS=/app/assets PYTHONUNBUFFERED=1
USER bodyfit
WORKDIR /app

# The service (the default target).
FROM python:3.11-slim AS service
RUN useradd --create-home --uid 10001 bodyfit
COPY --from=build /opt/venv /opt/venv
COPY --chown=bodyfit:bodyfit assets /app/assets
ENV PATH=/opt/venv/bin:$PATH \
    BODYFIT_ASSETS=/app/assets \
    BODYFIT_HOST=0.0.0.0 \
    PYTHONUNBUFFERED=1
USER bodyfit
WORKDIR /app
EXPOSE 8000 50051
HEALTHCHECK --interval=15s --timeout=3s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import urllib.request, sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=2).status != 200)"]
CMD ["bodyfit", "serve", "--host", "0.0.0.0"]
