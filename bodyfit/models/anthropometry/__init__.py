"""Anthropometry: measure bodies of the model, and build bodies from measurements (docs/anthropometry.md)."""
