"""REST (FastAPI) and gRPC transports over :mod:`bodyfit.service`, with schemas and error mapping."""
