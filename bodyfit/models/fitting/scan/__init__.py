"""Fitting raw scans (meshes or point clouds, any pose, orientation, units or view): the fitter
(:mod:`.fitter`), its phases and settings (:mod:`.config`), the limb grid search (:mod:`.limb_search`),
single-view detection (:mod:`.view`) and the second process it may use (:mod:`.helper`).
"""
