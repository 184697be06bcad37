"""Typed errors raised by the model layer. Each message says what was wrong and how to fix it."""

from __future__ import annotations


class BodyfitError(ValueError):
    """Base class of every input error bodyfit raises on purpose."""


class ShapeError(BodyfitError):
    """An array has the wrong number of dimensions or the wrong size."""


class NonFiniteError(BodyfitError):
    """An array holds NaN or infinite values."""


class UnknownCoordinateError(BodyfitError):
    """A coordinate (DOF) name is not part of the skeleton."""


class CoordinateRangeError(BodyfitError):
    """A coordinate value lies outside its anatomical range."""


class AssetError(BodyfitError):
    """A model asset is missing, unreadable or does not match its manifest."""
