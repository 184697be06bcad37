"""Python SDK and command-line interface. Depends on the wire contract only, not on the server code."""
