"""Fitting the body model to data: registered meshes, raw scans, sequences and mocap markers.

The model objects hold buffers only; every fitter keeps its optimisation state to itself and returns its
parameters with a :class:`~bodyfit.models.fitting.report.FitReport`.
"""
