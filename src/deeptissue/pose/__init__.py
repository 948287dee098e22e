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

import importlib

#: Each public name and the submodule that defines it. A submodule is imported when one of its names is
#: first asked for (:func:`__getattr__`), so a job that only reads or writes ``pose.json`` (:mod:`.result`),
#: as every solve does, does not import the estimation's SciPy, scikit-image, nibabel and Matplotlib modules.
_EXPORTS = {
    "ACCURACY_TOLERANCES": "accuracy",
    "accuracy_table": "accuracy",
    "pose_errors": "accuracy",
    "run_pose_accuracy": "accuracy",
    "PoseFiles": "estimate",
    "PoseOptions": "estimate",
    "check_depth": "estimate",
    "check_tip_in_leg": "estimate",
    "estimate_pose": "estimate",
    "read_override": "estimate",
    "run_pose": "estimate",
    "TipSearch": "indenter",
    "line_triangle_hits": "indenter",
    "skin_triangles": "indenter",
    "tip_end_mm": "indenter",
    "plot_axis_qc": "qc",
    "plot_bone_qc": "qc",
    "plot_tip_qc": "qc",
    "LegGuard": "registration",
    "LegRegistration": "registration",
    "register_leg": "registration",
    "Pose": "result",
    "load_pose": "result",
    "save_pose": "result",
    "MAX_SLICE_OBLIQUITY_DEG": "scan",
    "check_axial_slices": "scan",
    "slice_obliquity_deg": "scan",
}


def __getattr__(name: str):
    """The public ``name`` from its submodule (:data:`_EXPORTS`), imported on first use."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})


__all__ = sorted(_EXPORTS)
