"""Calibration (thesis sections 2.2.3, 2.3.2-2.3.7, 6.3-6.5, 6.9; docs/calibration.md):
start values (:mod:`.dlt`, :mod:`.initial`, :mod:`.start`), control points
(:mod:`.controlpoints`), the object-space bundle adjustment (:mod:`.model`,
:mod:`.kernels`, :mod:`.solver`, :mod:`.bundle`), whether it reached its noise floor
(:mod:`.convergence`), degenerate set-ups (:mod:`.diagnostics`), its uncertainty
(:mod:`.uncertainty`, :mod:`.propagation`, :mod:`.artefact_sensitivity`,
:mod:`.bootstrap`, :mod:`.crossval`), its results (:mod:`.results`) and its file format
(:mod:`.file`). Nothing here reads or writes a run directory or draws.

The package imports none of its modules, so reading a calibration file does not load
the adjustment's compiled kernels.
"""
