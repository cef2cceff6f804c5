"""Characterisation and sim-to-real gap maths: capture data, plane fits, noise statistics, diagnosis.

No files, no rerun: the commands in ``elevmap.commands`` read capture sets and call these functions.

* :mod:`.capture_data` -- one capture's frames, geometry and pixel regions (:class:`CaptureData`).
* :mod:`.characterization` -- the paper's characterisation: plane fits, axial and lateral noise, the
  sigma_z model fit.
* :mod:`.detection` -- finding a target board in an image (OpenCV, imported by its callers only).
* :mod:`.diagnosis` -- per-stratum gap statistics, the noise floor, forward selection of effects.
"""
