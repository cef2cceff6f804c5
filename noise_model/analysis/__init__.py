"""Characterisation and sim-to-real gap maths: capture data, plane fits, noise statistics, diagnosis.

No files, no rerun: the commands in ``elevmap.commands`` read capture sets and call these functions.

* :mod:`.capture_data` -- one capture's frames, geometry and pixel regions (:class:`CaptureData`).
* :mod:`.planes` -- camera-frame planes and their fits (total least squares, robust, along rays, RANSAC
  on a region): one :class:`~.planes.PlaneFit`.
* :mod:`.characterization` -- the paper's characterisation: axial and lateral noise, the sigma_z model fit.
* :mod:`.family_fit` -- the disparity family's fit and both families' held-out errors (blocks of distance, angle).
* :mod:`.detection` -- finding a target board in an image (OpenCV, imported by its callers only).
* :mod:`.effect_fits` -- one fit per depth effect of :mod:`noise_model.sim.effects` (one ``FitSpec`` each).
* :mod:`.diagnosis` -- the sim-to-real gap: strata and per-stratum sums (numba + NumPy reference), the
  noise floor, forward selection of effects, and ``diagnose`` (the library half of ``elevmap gap``).
"""
