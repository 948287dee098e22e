"""Pose stage (rule ``pose``): the indenter's axis and travel and the tibia's rigid motion of one animal.

The stage reads the during scan and the contours of both states and writes ``pose.json``
(:class:`Pose`). Its parts:

- :mod:`.result`: the result type and its file (:class:`Pose`, :func:`save_pose`, :func:`load_pose`).
- :mod:`.indenter`: the final tip and the skin entry, on the contrast fluid's axis
  (:mod:`deeptissue.fluid`, below the segmentation, which masks the indenter with it).
- :mod:`.registration`: the leg's motion in the cast between the scans, from the far-field skin
  (:func:`register_leg`), undone before the pose is measured.
- :mod:`.scan`: the scans' slice orientation (:func:`check_axial_slices`).
- the tibia's (and fibula's) rigid-motion fit is :mod:`deeptissue.bone_motion` (below the segmentation, which
  fills the slices where the tibia touches the indenter with it); errors are :class:`deeptissue.pose_error.PoseError`.
- :mod:`.checks`: the QC checks (``checks.csv``).
- :mod:`.qc`: the QC figures.
- :mod:`.estimate`: :func:`estimate_pose` on arrays and :func:`run_pose`, the rule's file glue.
- :mod:`.accuracy`: errors against a phantom's truth (rule ``pose_accuracy``).
"""

from .accuracy import ACCURACY_TOLERANCES, accuracy_table, pose_errors, run_pose_accuracy
from .estimate import (
    PoseFiles,
    PoseOptions,
    check_depth,
    check_tip_in_leg,
    estimate_pose,
    read_override,
    run_pose,
)
from .indenter import TipSearch, line_triangle_hits, skin_triangles, tip_end_mm
from .qc import plot_axis_qc, plot_bone_qc, plot_tip_qc
from .registration import LegGuard, LegRegistration, register_leg
from .result import Pose, load_pose, save_pose
from .scan import MAX_SLICE_OBLIQUITY_DEG, check_axial_slices, slice_obliquity_deg

__all__ = [
    "ACCURACY_TOLERANCES",
    "MAX_SLICE_OBLIQUITY_DEG",
    "LegGuard",
    "LegRegistration",
    "Pose",
    "PoseFiles",
    "PoseOptions",
    "TipSearch",
    "accuracy_table",
    "check_axial_slices",
    "check_depth",
    "check_tip_in_leg",
    "estimate_pose",
    "line_triangle_hits",
    "load_pose",
    "plot_axis_qc",
    "plot_bone_qc",
    "plot_tip_qc",
    "pose_errors",
    "read_override",
    "register_leg",
    "run_pose",
    "run_pose_accuracy",
    "save_pose",
    "skin_triangles",
    "slice_obliquity_deg",
    "tip_end_mm",
]
