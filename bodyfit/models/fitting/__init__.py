"""Fitting the body model to data, one capability per subpackage:

* :mod:`.registered` -- meshes in our topology or SMPL's (known correspondence);
* :mod:`.scan` -- raw scans: meshes or point clouds in any pose, orientation, units or view;
* :mod:`.sequence` -- sequences of registered meshes, with rest-pose offsets;
* :mod:`.mocap` -- optical motion capture markers (TRC/C3D);
* :mod:`.retarget` -- skeletal motion (BVH) onto our skeleton;
* :mod:`.common` -- what they share: the batched L-BFGS optimiser, fit reports, mesh geometry, nearest
  neighbours and the non-rigid refinement.

File formats are read in :mod:`bodyfit.io`. The model objects hold buffers only; every fitter keeps its
optimisation state to itself and returns its parameters with a
:class:`~bodyfit.models.fitting.common.report.FitReport`.

The flat modules left in this package (``scan_fit``, ``scan_io``, ``markers`` ...) are deprecated shims
that re-export their names from the new paths; they will be removed in the next release.
"""
