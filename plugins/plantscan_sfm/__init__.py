"""Calibrate a turntable rig from the plant photos themselves (structure from motion).

``features``: SIFT features and verified matches with pycolmap, tracks;
``initialise``: the turntable's axis, focal length and camera poses from
two-view geometry; ``bundle``: the turntable-constrained bundle adjustment
(pyceres); ``scale``: metric scale and the plate height; ``plugin``: the
``sfm`` calibrator; ``baseline``: COLMAP's own unconstrained reconstruction,
for comparison.
"""
