"""Pose stage (rule ``pose``): the indenter's axis and travel and the tibia's rigid motion of one animal.

The stage reads the during scan and the contours of both states and writes ``pose.json``
(:class:`Pose`). Its parts:

- :mod:`.result`: the result type and its file (:class:`Pose`, :func:`save_pose`, :func:`load_pose`).
- :mod:`.indenter`: the contrast fluid's component and axis, the final tip, the skin entry.
- :mod:`.registration`: the leg's motion in the cast between the scans, from the far-field skin
  (:func:`register_leg`), undone before the pose is measured.
- :mod:`.scan`: the scans' slice orientation (:func:`check_axial_slices`).
- :mod:`.bone`: the tibia's (and fibula's) rigid-motion fit (:func:`fit_bone_motion`).
- :mod:`.checks`: the QC checks (``checks.csv``).
- :mod:`.qc`: the QC figures.
- :mod:`.estimate`: :func:`estimate_pose` on arrays and :func:`run_pose`, the rule's file glue.
- :mod:`.accuracy`: errors against a phantom's truth (rule ``pose_accuracy``).
"""

from .accuracy import ACCURACY_TOLERANCES, accuracy_table, pose_errors, run_pose_accuracy
from .bone import (
    MIN_FIBULA_SLICES,
    BoneDistance,
    BoneFit,
    bone_centroid_mm,
    dense_surface,
    fit_bone_motion,
    moved_section,
    resolve_bone_dof,
)
from .estimate import (
    PoseFiles,
    PoseOptions,
    check_depth,
    check_tip_in_leg,
    estimate_pose,
    read_override,
    run_pose,
)
from .indenter import (
    CylinderFit,
    FluidComponent,
    IndenterShape,
    TipSearch,
    find_fluid_component,
    fluid_threshold,
    indenter_shape,
    inertia_axis,
    inside_skin_mask,
    line_triangle_hits,
    orient_axis,
    refine_axis_cylinder,
    skin_triangles,
    tip_end_mm,
    voxel_centres_mm,
)
from .qc import plot_axis_qc, plot_bone_qc, plot_tip_qc
from .registration import LegGuard, LegRegistration, register_leg
from .result import Pose, PoseError, load_pose, save_pose
from .scan import MAX_SLICE_OBLIQUITY_DEG, check_axial_slices, slice_obliquity_deg

__all__ = [
    "ACCURACY_TOLERANCES",
    "MAX_SLICE_OBLIQUITY_DEG",
    "MIN_FIBULA_SLICES",
    "BoneDistance",
    "BoneFit",
    "CylinderFit",
    "FluidComponent",
    "IndenterShape",
    "LegGuard",
    "LegRegistration",
    "Pose",
    "PoseError",
    "PoseFiles",
    "PoseOptions",
    "TipSearch",
    "accuracy_table",
    "bone_centroid_mm",
    "check_axial_slices",
    "check_depth",
    "check_tip_in_leg",
    "dense_surface",
    "estimate_pose",
    "find_fluid_component",
    "fit_bone_motion",
    "fluid_threshold",
    "indenter_shape",
    "inertia_axis",
    "inside_skin_mask",
    "line_triangle_hits",
    "load_pose",
    "moved_section",
    "orient_axis",
    "plot_axis_qc",
    "plot_bone_qc",
    "plot_tip_qc",
    "pose_errors",
    "read_override",
    "refine_axis_cylinder",
    "register_leg",
    "resolve_bone_dof",
    "run_pose",
    "run_pose_accuracy",
    "save_pose",
    "skin_triangles",
    "slice_obliquity_deg",
    "tip_end_mm",
    "voxel_centres_mm",
]
