"""Pieces the fitters share: the batched L-BFGS optimiser (:mod:`.lbfgs`), fit reports
(:mod:`.report`), mesh geometry (:mod:`.surface`: normals, closest points, Laplacian), nearest-neighbour
search (:mod:`.nearest`) and the non-rigid per-vertex refinement (:mod:`.nonrigid`).
"""
