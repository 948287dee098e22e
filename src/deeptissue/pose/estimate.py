"""The pose stage: indenter pose, depth and tibia motion of one animal, and the rule's file glue.

:func:`estimate_pose` combines the indenter (:mod:`.indenter`) and the bone fit (:mod:`.bone`) on
arrays, with any quantity given by hand in ``pose_override``; :func:`run_pose` reads the rule's
inputs, writes ``pose.json`` and the QC figures (:mod:`.qc`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .bone import bone_centroid_mm, fit_bone_motion, resolve_bone_dof
from .indenter import (
    find_fluid_component,
    fluid_threshold,
    inside_skin_mask,
    line_triangle_hits,
    orient_axis,
    skin_triangles,
    tip_end_mm,
)
from .qc import plot_axis_qc, plot_bone_qc, plot_tip_qc
from .result import Pose, PoseError, _where, save_pose

if TYPE_CHECKING:
    from ..contours import Contours

__all__ = ["PoseOptions", "estimate_pose", "run_pose"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PoseOptions:
    """Settings of :func:`estimate_pose` (config section ``pose``); see the schema for each key."""

    fluid_threshold: float | None = None
    fluid_threshold_ratio: float = 1.6
    min_component_mm3: float = 1.0
    ambiguity_ratio: float = 0.5
    roi_diameter_mm: float = 5.0
    roi_reach_mm: float = 1.5
    head_radius_mm: float = 1.5
    tip_method: str = "sphere"
    start_backoff_mm: float = 1.0
    bone_method: str = "surface"
    bone_dof: int | str = "auto"
    bone_surface_step_mm: float = 0.05

    @classmethod
    def from_config(cls, section: dict | None) -> PoseOptions:
        """The options of a config section ``pose`` (None: all defaults); keys that are not options are ignored."""
        known = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in (section or {}).items() if k in known})


_OVERRIDE_KEYS = (
    "indenter_axis",
    "tip_end_mm",
    "tip_start_mm",
    "bone_rotation_deg",
    "bone_translation_mm",
)


def estimate_pose(
    during: np.ndarray,
    affine: np.ndarray,
    pre: Contours,
    during_contours: Contours,
    *,
    options: PoseOptions = PoseOptions(),
    override: dict | None = None,
    animal: str = "",
) -> tuple[Pose, dict]:
    """Indenter pose, depth and tibia motion of one animal.

    Quantities given in ``override`` replace the automatic ones, and the ones that depend on them are
    computed from them (the start from the hand axis and tip, etc.). With both ``indenter_axis`` and
    ``tip_end_mm`` given the fluid is not needed at all.

    Parameters
    ----------
    during : (I, J, K) array
        Intensities of the during scan.
    affine : (4, 4) array
        Voxel index -> world mm of ``during``.
    pre, during_contours : Contours
        Skin, tibia and fibula contours of both states (:class:`~deeptissue.contours.Contours`).
    options : PoseOptions
        Settings (config section ``pose``).
    override : dict or None
        Any of ``indenter_axis``, ``tip_end_mm``, ``tip_start_mm``, ``bone_rotation_deg``,
        ``bone_translation_mm`` given by hand (config ``pose_override``); None values are ignored.
    animal : str
        Named in messages.

    Returns
    -------
    pose : Pose
        With the fit diagnostics in ``extra``.
    qc : dict
        Intermediate arrays for the QC figures (fluid points, ROI front, centroid shift).

    Raises
    ------
    PoseError
        Naming the animal and the reason, when the scan cannot be read.
    ValueError
        For an unknown ``override`` key.
    """
    override = {k: np.asarray(v, float) for k, v in (override or {}).items() if v is not None}
    unknown = set(override) - set(_OVERRIDE_KEYS)
    if unknown:
        raise ValueError(f"{_where(animal)}unknown pose_override key(s) {sorted(unknown)}")
    extra: dict = {"overrides": sorted(override)}
    qc: dict = {}
    leg_centre = during_contours.skin.reshape(-1, 3).mean(axis=0)
    affine = np.asarray(affine, float)

    fluid = None
    if not ("indenter_axis" in override and "tip_end_mm" in override):
        mask = inside_skin_mask(np.shape(during), affine, during_contours.skin)
        thr = options.fluid_threshold
        if thr is None:
            thr = fluid_threshold(during, mask, ratio=options.fluid_threshold_ratio)
        fluid = find_fluid_component(
            during,
            affine,
            threshold=thr,
            exclude_mask=mask,
            min_volume_mm3=options.min_component_mm3,
            ambiguity_ratio=options.ambiguity_ratio,
            animal=animal,
        )
        m = fluid.moments_mm2
        extra.update(
            fluid_threshold=fluid.threshold,
            fluid_volume_mm3=fluid.volume_mm3,
            fluid_candidate_volumes_mm3=list(fluid.candidate_volumes_mm3[:5]),
            fluid_elongation=float(np.sqrt(m[2] / max(m[0], 1e-12))),
        )
        # evidence for the QC checks: the column's length along the axis, and how far the cylinder fit turned
        # the inertia axis (NaN when the fit did not run or was rejected: the axis is the inertia axis)
        s_col = (fluid.points_mm - fluid.com_mm) @ fluid.axis
        extra["fluid_column_length_mm"] = float(s_col.max() - s_col.min())
        if fluid.axis_inertia is not None:
            refined = not np.array_equal(fluid.axis_inertia, fluid.axis)
            cos = abs(float(fluid.axis_inertia @ fluid.axis)) / float(
                np.linalg.norm(fluid.axis_inertia)
            )
            extra["axis_inertia_vs_cylinder_deg"] = (
                float(np.degrees(np.arccos(min(cos, 1.0)))) if refined else float("nan")
            )
        qc["fluid_points_mm"] = fluid.points_mm

    if "indenter_axis" in override:
        axis = override["indenter_axis"] / np.linalg.norm(override["indenter_axis"])
    else:
        axis = orient_axis(fluid.axis, from_mm=fluid.com_mm, toward_mm=leg_centre)
    com = fluid.com_mm if fluid is not None else None

    if "tip_end_mm" in override:
        tip_end = override["tip_end_mm"]
    else:
        front = float(np.max((fluid.points_mm - com) @ axis))
        tip_end, info = tip_end_mm(
            during_contours.skin,
            axis=axis,
            com_mm=com,
            front_mm=front,
            roi_diameter_mm=options.roi_diameter_mm,
            reach_mm=options.roi_reach_mm,
            head_radius_mm=options.head_radius_mm,
            method=options.tip_method,
            animal=animal,
        )
        extra.update(info)
        qc["roi_front_mm"] = front

    if "tip_start_mm" in override:
        tip_start = override["tip_start_mm"]
        surface = tip_start + options.start_backoff_mm * axis
    else:
        # the line of travel: through the final tip along the axis; the skin crossing nearest the
        # indenter (the fluid COM, or the tip when the fluid was not used)
        ref = com if com is not None else tip_end - 5.0 * axis
        t_hits = line_triangle_hits(tip_end, axis, skin_triangles(pre.skin))
        if t_hits.size == 0:
            raise PoseError(
                f"{_where(animal)}the indenter axis does not meet the undeformed (pre) skin surface; "
                "give pose_override.tip_start_mm or indenter_axis"
            )
        hits = tip_end + t_hits[:, None] * axis
        surface = hits[np.argmin(np.linalg.norm(hits - ref, axis=1))]
        tip_start = surface - options.start_backoff_mm * axis
    depth = float((tip_end - surface) @ axis)
    extra["skin_entry_mm"] = surface

    if "bone_rotation_deg" in override and "bone_translation_mm" in override:
        com_pre = bone_centroid_mm(pre.bone)
        rot, trans = override["bone_rotation_deg"], override["bone_translation_mm"]
    else:
        dof, why = resolve_bone_dof(options.bone_dof, pre, during_contours)
        log.info("%s%s", _where(animal), why)
        fit = fit_bone_motion(
            pre.bone,
            during_contours.bone,
            fibula_pre_mm=pre.fibula,
            fibula_during_mm=during_contours.fibula,
            method=options.bone_method,
            dof=dof,
            surface_step_mm=options.bone_surface_step_mm,
            during_slices=during_contours.bone_seen
            if pre.n_slices == during_contours.n_slices
            else None,
            animal=animal,
        )
        extra["bone_slices_used"] = [
            int(during_contours.bone_seen.sum()),
            during_contours.n_slices,
        ]
        extra["bone_dof_reason"] = why
        extra["bone_fibula_slices"] = list(fit.fibula_slices)
        com_pre = fit.motion.centre_mm
        rot = override.get("bone_rotation_deg", fit.motion.rotation_deg)
        trans = override.get("bone_translation_mm", fit.motion.translation_mm)
        extra.update(
            bone_method=fit.method,
            bone_dof=fit.dof,
            bone_com_shift_mm=fit.com_shift_mm,
            bone_rms_initial_mm=fit.rms_initial_mm,
            bone_rms_com_mm=fit.rms_com_mm,
            bone_rms_final_mm=fit.rms_final_mm,
            bone_fit_evaluations=fit.n_evaluations,
            bone_fit_sd=fit.parameter_sd,
        )
        qc["bone_com_shift_mm"] = fit.com_shift_mm

    pose = Pose(
        indenter_axis=axis,
        tip_start_mm=tip_start,
        tip_end_mm=tip_end,
        depth_mm=depth,
        bone_com_mm=com_pre,
        bone_rotation_deg=rot,
        bone_translation_mm=trans,
        indenter_com_mm=com,
        extra=extra,
    )
    return pose, qc


def run_pose(
    *,
    during_nifti,
    pre_contours,
    during_contours,
    pose_json,
    axis_png,
    tip_png,
    bone_png,
    checks_csv=None,
    pre_nifti=None,
    options: dict | None = None,
    override: dict | None = None,
    animal: str = "",
) -> Pose:
    """Rule ``pose``: read the during NIfTI and both contour files, write ``pose.json``, the QC figures and the
    QC checks (:mod:`.checks`); a failed check stops the rule after ``checks_csv`` is written.

    Parameters
    ----------
    during_nifti : path
        The during scan (3D NIfTI).
    pre_contours, during_contours : path
        Contour files of both states (:func:`deeptissue.contours.save_contours`).
    pose_json : path
        Written by :func:`~deeptissue.pose.save_pose`.
    axis_png, tip_png, bone_png : path
        QC figures of the axis, the tip and the bone fit.
    checks_csv : path or None
        ``checks.csv`` (:func:`~deeptissue.pose.checks.write_checks`); None: the checks are evaluated and
        acted on, not written.
    pre_nifti : path or None
        The pre scan, named with ``during_nifti`` when a check fails.
    options : dict or None
        Config section ``pose`` (:meth:`PoseOptions.from_config`).
    override : dict or None
        Config ``pose_override`` of the animal (see :func:`estimate_pose`).
    animal : str
        Named in messages and figure titles.

    Returns
    -------
    Pose
        The pose written to ``pose_json``, with the warnings of the checks in ``extra["qc_warnings"]``.

    Raises
    ------
    PoseError
        When a check fails: naming the animal, both scans and the value against its limit.
    """
    from dataclasses import replace

    from ..contours import load_contours
    from ..imaging import load_nifti
    from .checks import evaluate_checks, failed_message, warnings_of, write_checks

    vol = load_nifti(
        during_nifti, animal=animal
    )  # an unreadable or not-3D file: ImagingError naming both
    data = vol.data.astype(float)
    pre = load_contours(pre_contours)
    dur = load_contours(during_contours)
    opts = PoseOptions.from_config(options)
    pose, qc = estimate_pose(
        data, vol.affine, pre, dur, options=opts, override=override, animal=animal
    )
    checks = evaluate_checks(pose, pre, dur)
    if checks_csv is not None:
        write_checks(checks_csv, checks)
    for c in checks:
        log.log(
            logging.INFO if c.status == "ok" else logging.WARNING,
            "%s check %s",
            animal,
            c.describe() if c.status != "ok" else f"{c.name} {c.value:.4g} ok",
        )
    message = failed_message(
        checks, animal=animal, pre_file=pre_nifti or pre_contours, during_file=during_nifti
    )
    if message:
        raise PoseError(message)
    pose = replace(pose, extra={**pose.extra, "qc_warnings": warnings_of(checks)})
    plot_axis_qc(axis_png, data, vol.affine, pose, qc, title=animal)
    plot_tip_qc(tip_png, pre, dur, pose, roi_diameter_mm=opts.roi_diameter_mm, title=animal)
    plot_bone_qc(bone_png, pre, dur, pose, title=animal)
    save_pose(pose_json, pose)
    return pose
