"""Pose stage (rule ``pose``): the indenter's axis and travel and the tibia's rigid motion of one animal.

The stage reads the during scan and the contours of both states and writes ``pose.json``
(:class:`Pose`). Its parts:

- :mod:`.result`: the result type and its file (:class:`Pose`, :func:`save_pose`, :func:`load_pose`).
- :mod:`.indenter`: the contrast fluid's component and axis, the final tip, the skin entry.
- :mod:`.bone`: the tibia's (and fibula's) rigid-motion fit (:func:`fit_bone_motion`).
- :mod:`.qc`: the QC figures.
- :mod:`.estimate`: :func:`estimate_pose` on arrays and :func:`run_pose`, the rule's file glue.
- :mod:`.accuracy`: errors against a phantom's truth (rule ``pose_accuracy``).
"""

from .accuracy import ACCURACY_TOLERANCES, accuracy_table, pose_errors, run_pose_accuracy
from .bone import (
    MIN_FIBULA_SLICES,
    BoneFit,
    bone_centroid_mm,
    dense_surface,
    fit_bone_motion,
    moved_section,
    resolve_bone_dof,
)
from .estimate import PoseOptions, estimate_pose, run_pose
from .indenter import (
    FluidComponent,
    IndenterShape,
    find_fluid_component,
    fluid_threshold,
    indenter_shape,
    inertia_axis,
    inside_skin_mask,
    line_triangle_hits,
    orient_axis,
    refine_axis_cylinder,
    skin_entry_mm,
    skin_triangles,
    tip_end_mm,
    voxel_centres_mm,
)
from .qc import plot_axis_qc, plot_bone_qc, plot_tip_qc
from .result import Pose, PoseError, load_pose, save_pose

__all__ = [
    "ACCURACY_TOLERANCES",
    "MIN_FIBULA_SLICES",
    "BoneFit",
    "FluidComponent",
    "IndenterShape",
    "Pose",
    "PoseError",
    "PoseOptions",
    "accuracy_table",
    "bone_centroid_mm",
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
    "refine_axis_cylinder",
    "resolve_bone_dof",
    "run_pose",
    "run_pose_accuracy",
    "save_pose",
    "skin_entry_mm",
    "skin_triangles",
    "tip_end_mm",
    "voxel_centres_mm",
]
