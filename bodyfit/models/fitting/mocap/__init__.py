"""Fitting optical motion capture markers (TRC/C3D): the entry point (:mod:`.fitter`, ``fit_markers``),
marker protocols (:mod:`.marker_sets`), virtual markers and scaling (:mod:`.calibration`), subject calibration
(:mod:`.subject`) and inverse kinematics (:mod:`.marker_ik`, :mod:`.marker_solve`).
"""
