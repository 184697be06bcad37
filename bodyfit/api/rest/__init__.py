"""The REST API (FastAPI): one router per resource over the service core."""
