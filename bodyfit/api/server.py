"""Running the service: one process serves REST (uvicorn) and gRPC over one loaded core."""

from __future__ import annotations

import logging

from bodyfit.api.settings import ServiceSettings

LOG = logging.getLogger("bodyfit.server")


def run_server(settings: ServiceSettings) -> None:
    """Load the model once, start gRPC (unless ``grpc_port`` is 0) and serve REST until interrupted."""
    import uvicorn

    from bodyfit.api.metrics import Metrics
    from bodyfit.api.rest.app import create_app
    from bodyfit.service.core import BodyService
    from bodyfit.service.memory import MemoryTrimmer, configure_allocator

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # before any worker thread allocates: large requests' memory goes back to the system afterwards
    configure_allocator()
    trimmer = MemoryTrimmer().start()
    service = BodyService.load(
        settings.assets,
        settings.limits(),
        settings.threads,
        smpl_model=settings.smpl_model,
        scan_processes=settings.scan_processes,
    )
    metrics = Metrics()
    grpc_server = None
    if settings.grpc_port:
        from bodyfit.api.grpc_server import create_grpc_server

        address = f"{settings.host}:{settings.grpc_port}"
        grpc_server, _ = create_grpc_server(service, address, settings, metrics)
        grpc_server.start()
        LOG.info("gRPC on %s:%d", settings.host, settings.grpc_port)
    LOG.info("REST on http://%s:%d (OpenAPI at /docs)", settings.host, settings.rest_port)
    try:
        uvicorn.run(
            create_app(settings, service=service, metrics=metrics),
            host=settings.host,
            port=settings.rest_port,
            log_level="info",
            access_log=False,
        )
    finally:
        if grpc_server is not None:
            grpc_server.stop(grace=5).wait()
        trimmer.stop()
