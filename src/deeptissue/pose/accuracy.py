"""Accuracy of an estimated pose against a phantom's truth (rule ``pose_accuracy``)."""

from __future__ import annotations

import numpy as np

from ..rigid import rotation_matrix
from .result import Pose, load_pose

__all__ = ["ACCURACY_TOLERANCES", "accuracy_table", "pose_errors", "run_pose_accuracy"]

# Largest error of each quantity that the pose stage accepts on a digital phantom with indenter tilt
# up to 25 deg, depth 1-3 mm, bone rotation up to 3 deg and SNR of at least 12: the tip and the depth
# within one in-plane pixel (0.1 mm), the bone translation within 0.03 mm, the axis within
# 1 deg and the bone rotation within 0.3 deg. ``pose_accuracy.csv`` and the phantom tests check them.
ACCURACY_TOLERANCES = {
    "axis_error_deg": 1.0,
    "tip_end_error_mm": 0.1,
    "depth_error_mm": 0.1,
    "bone_rotation_error_deg": 0.3,
    "bone_translation_error_mm": 0.03,
}


def pose_errors(estimate: Pose, truth: Pose) -> dict:
    """Errors of a pose against the truth (phantom ``truth.json``).

    ``axis_error_deg`` angle between the axes; ``tip_end_error_mm`` / ``tip_start_error_mm`` distances;
    ``depth_error_mm`` |difference|; ``bone_rotation_error_deg`` angle of R_est R_true^T;
    ``bone_translation_error_mm``: the estimated motion re-expressed about the truth's centre
    (t' = t + (R - I)(c_true - c_est), the same motion) minus the true translation.
    """
    from scipy.spatial.transform import Rotation

    cos = float(np.clip(estimate.indenter_axis @ truth.indenter_axis, -1.0, 1.0))
    R_est = rotation_matrix(estimate.bone_rotation_deg)
    R_true = rotation_matrix(truth.bone_rotation_deg)
    rel = Rotation.from_matrix(R_est @ R_true.T).magnitude()
    t_about_truth = estimate.bone_translation_mm + (R_est - np.eye(3)) @ (
        truth.bone_com_mm - estimate.bone_com_mm
    )
    return {
        "axis_error_deg": float(np.degrees(np.arccos(cos))),
        "tip_end_error_mm": float(np.linalg.norm(estimate.tip_end_mm - truth.tip_end_mm)),
        "tip_start_error_mm": float(np.linalg.norm(estimate.tip_start_mm - truth.tip_start_mm)),
        "depth_error_mm": abs(estimate.depth_mm - truth.depth_mm),
        "bone_rotation_error_deg": float(np.degrees(rel)),
        "bone_translation_error_mm": float(
            np.linalg.norm(t_about_truth - truth.bone_translation_mm)
        ),
        "bone_com_error_mm": float(np.linalg.norm(estimate.bone_com_mm - truth.bone_com_mm)),
    }


def accuracy_table(estimate: Pose, truth: Pose) -> list[dict]:
    """Rows ``quantity, error, tolerance, within_tolerance`` of :func:`pose_errors` (CSV-ready)."""
    rows = []
    for k, v in pose_errors(estimate, truth).items():
        tol = ACCURACY_TOLERANCES.get(k)
        rows.append(
            {
                "quantity": k,
                "error": v,
                "tolerance": tol if tol is not None else "",
                "within_tolerance": "" if tol is None else bool(v <= tol),
            }
        )
    return rows


def run_pose_accuracy(*, pose_json, truth_json, csv_path) -> list[dict]:
    """Rule ``pose_accuracy``: errors of ``pose.json`` against the phantom ``truth.json`` as CSV.

    Parameters
    ----------
    pose_json, truth_json : path
        The estimated pose and the phantom's truth (:func:`~deeptissue.pose.load_pose`).
    csv_path : path
        Written with the rows of :func:`accuracy_table`.

    Returns
    -------
    list of dict
        The rows written.
    """
    import csv

    from ..io import atomic_path

    rows = accuracy_table(load_pose(pose_json), load_pose(truth_json))
    with atomic_path(csv_path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return rows
