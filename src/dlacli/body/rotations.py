"""Moved to `dlacli.geometry` (the bottom-layer module). This re-export is kept only because
body/skinning.py and avatar/gaussian_map.py still import from here; once they import
dlacli.geometry, delete this file. New code must not import it."""

from dlacli.geometry import (  # noqa: F401
    axis_angle_to_matrix,
    axis_angle_to_quat,
    matrix_to_axis_angle,
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_axis_angle,
    quat_to_matrix,
    skew,
)
