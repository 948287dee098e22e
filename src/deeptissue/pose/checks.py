"""Quality checks of one animal's imaging estimates (``results/{animal}/qc/pose_checks.csv``, read with the
segmentation's checks in ``qc/checks.csv``: :func:`deeptissue.segment_checks.merge_checks`).

Every estimate carries its own evidence: how well the during tibia fits the pre tibia, how many slices
the fit used, whether the contour taken for the tibia is one bone from slice to slice, and whether the
indenter's fluid column is a straight cylinder. Each check has a warning and a failure limit measured on
the digital phantoms (see :data:`LIMITS`); a warning is carried into ``pose.json`` (``qc_warnings``) and
from there into every ``summary.json`` and ``voi.csv`` of the animal, a failure stops the pose rule.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..contours import polygon_area_centroid
from ..io import atomic_path
from ..pose_error import PoseError

if TYPE_CHECKING:
    from ..contours import Contours
    from .registration import LegRegistration
    from .result import Pose

__all__ = [
    "LIMITS",
    "Check",
    "LegMovedError",
    "evaluate_checks",
    "failed_message",
    "leg_checks",
    "warnings_of",
    "write_checks",
]


@dataclass(frozen=True)
class Limit:
    """Warning and failure limits of one check (the value is bad above them, or below with ``below``) and the
    advice given when it is not ok."""

    warn: float
    fail: float
    action: str
    below: bool = False


# Limits measured on the digital phantoms. Good: the three demo animals of config/config.yaml (rat01-rat03,
# the test config's rat01 among them; snr 15-25, tilt up to 12 deg, depth 1.5-2.5 mm), rat01 with its
# indenter tilted 60 deg in the slice plane, and the phantoms with the indenter 0.05-0.1 mm from the tibia
# (tests/test_segment_indenter.py). Bad: rat01's pre scan with rat02's during scan (a 6 deg bone rotation
# reported where there is none), rat01 with its indenter tilted 60 deg out of the slice plane (axis 5 deg,
# depth 0.16 mm off) and rat01 scanned on 5 slices (bone translation 0.12 mm off). Each limit lies between
# the two, with the measured values beside it.
LIMITS = {
    # RMS distance of the fitted during tibia from the pre tibia: 0.006-0.012 mm good, 0.090 mm for the pre
    # scan of another animal. Warning at 2.5x, failure at 5x the largest good value.
    "bone_fit_rms_mm": Limit(
        0.03,
        0.06,
        "pre/during mismatch: check that the pre and during scans are of the same "
        "animal and leg, and the segmentation figures of both",
    ),
    # fraction of the during slices whose tibia joins the rigid fit: 1.0 on the demo phantoms, 0.9 with the
    # indenter 0.05 mm from the tibia; the segmentation refuses more than half of the slices hidden.
    "bone_slices_used": Limit(
        0.75,
        0.5,
        "the tibia is hidden by the indenter on many slices: check the during "
        "segmentation figure; the bone motion rests on the other slices",
        below=True,
    ),
    # largest in-plane jump of the tibia's centroid between neighbouring slices per mm of their spacing:
    # 0.022-0.048 mm/mm good (the shaft drifts 0.02 mm/mm); the fibula taken for the tibia jumps by its
    # distance from the tibia, 2-4 mm. Warning at 5x the largest good value, failure at 0.6 mm/mm.
    "tibia_centroid_jump_pre_mm_per_mm": Limit(
        0.25,
        0.6,
        "the contour taken for the tibia jumps between slices "
        "(another structure on some slices?): check the pre segmentation "
        "figure, set segmentation.bone_select or draw an override",
    ),
    "tibia_centroid_jump_during_mm_per_mm": Limit(
        0.25,
        0.6,
        "the contour taken for the tibia jumps between slices "
        "(another structure on some slices?): check the during "
        "segmentation figure, set segmentation.bone_select or draw an "
        "override",
    ),
    # largest change of the tibia's section area between neighbouring slices, |log(A_k+1 / A_k)|: 0.038-0.052
    # good; the fibula (0.5 mm^2) for the tibia (2-4 mm^2) changes it by 1.4-2.1.
    "tibia_area_step_pre": Limit(
        0.25,
        0.6,
        "the tibia's section changes size abruptly between slices: check the "
        "pre segmentation figure",
    ),
    "tibia_area_step_during": Limit(
        0.25,
        0.6,
        "the tibia's section changes size abruptly between slices: check the "
        "during segmentation figure",
    ),
    # length along the axis of the fluid column used for the axis: 9.0-10.7 mm good, 3.4 mm with the
    # indenter tilted 60 deg out of the slice plane. Below 5 mm the cylinder fit cannot run (it leaves 1.5 mm
    # at each end and needs 2 mm) and the axis is the inertia axis of a short blob.
    "fluid_column_length_mm": Limit(
        6.0,
        5.0,
        "too little of the fluid column is in the scan to find the indenter "
        "axis (steep tilt out of the slices, short field of view): check the axis "
        "figure and give pose_override.indenter_axis",
        below=True,
    ),
    # angle between the fluid column's inertia axis and its cylinder fit: 0.03-1.03 deg good (the inertia
    # axis of 1 mm slices is off by up to ~2 deg); NaN when the fit did not run (a warning).
    "axis_inertia_vs_cylinder_deg": Limit(
        2.0,
        4.0,
        "the fluid column's inertia axis and cylinder fit disagree (or "
        "the fit did not run): check the axis figure, give "
        "pose_override.indenter_axis if it is off",
    ),
    # standard errors of the fitted bone rotation (largest component) and translation: 0.0011-0.008 deg and
    # 0.0013-0.0021 mm good; 5 slices 0.014 deg and 0.016 mm; the mismatched pair 0.063 deg and 0.015 mm.
    "bone_rotation_sd_deg": Limit(
        0.02,
        0.2,
        "the bone rotation is poorly determined (few slices or little bone "
        "shape): check pose_bone.png; scan more slices",
    ),
    # the leg's in-plane shift and turn in the cast between the scans (deeptissue.pose.registration), undone
    # before the pose is measured: 0.0003-0.002 mm and no turn on the six phantoms of
    # tests/pose_phantom_cases.py; their during scans moved 2 and 5 pixels (0.195, 0.488 mm) in x or y
    # come back to within 0.003 mm, turned 3 deg to 2.76-2.94 deg (`pose_phantom_cases.py --moves`).
    # A warning says the leg moved (more than half a pixel, or 0.5 deg); beyond 1 mm (10 pixels, a fifth
    # of the leg's radius) or 5 deg the leg did not just settle in the cast, and a rigid correction cannot
    # vouch for the tissue under the indenter.
    "leg_shift_mm": Limit(
        0.05,
        1.0,
        "the leg moved in the cast between the pre and during scans (the pose is corrected for it below "
        "the failure limit): check pose_axis.png and pose_tip.png; beyond the limit rescan with the leg "
        "held in the cast, and check that both scans were taken in one sitting of the animal",
    ),
    "leg_rotation_deg": Limit(
        0.5,
        5.0,
        "the leg turned in the cast between the pre and during scans (the pose is corrected for it below "
        "the failure limit): check pose_axis.png and pose_tip.png; beyond the limit rescan with the leg "
        "held in the cast, and check that both scans were taken in one sitting of the animal",
    ),
    # RMS distance of the far-field during skin (beyond 5 mm of the indenter, deeptissue.pose.LegGuard), after the leg's
    # correction, from the pre skin: 0.008-0.021 mm on the six phantoms, unmoved, moved up to 5 pixels or
    # turned 3 deg; 0.24-0.31 mm with the leg tilted 3 deg out of the slices, which the correction does
    # not undo (rat02, tilt25x-shallow, tilt18-deep-norot; the other three tilted scans are not segmented)
    # (`pose_phantom_cases.py --moves`). Warning at 2.4x, failure at 4.7x the largest good value.
    "leg_skin_residual_mm": Limit(
        0.05,
        0.1,
        "the skin away from the indenter does not lie on the pre skin (the leg tilted or deformed in the "
        "cast between the scans, or the indenter deforms the skin farther than 5 mm from its front): check both "
        "segmentation figures and pose_tip.png; rescan with the leg held in the cast",
    ),
    "bone_translation_sd_mm": Limit(
        0.006,
        0.05,
        "the bone translation is poorly determined (few slices, or a "
        "fibula too short to show the shift along the leg): check pose_bone.png; "
        "scan more slices or set pose.bone_dof: 5",
    ),
}


@dataclass(frozen=True)
class Check:
    """One row of ``checks.csv``: the check's ``name``, its ``value``, the warning ``limit`` and ``fail_limit``,
    ``status`` ok / warn / fail and ``action`` (what to do; empty when ok)."""

    name: str
    value: float
    limit: float
    fail_limit: float
    status: str
    action: str

    def describe(self) -> str:
        """ "name value > limit" (or "<" for a check that is bad below its limit), the limit its status crossed;
        "name not measured" for a NaN value."""
        lim = LIMITS[self.name]
        if not np.isfinite(self.value):
            return f"{self.name} not measured"
        bound = self.fail_limit if self.status == "fail" else self.limit
        return f"{self.name} {self.value:.4g} {'<' if lim.below else '>'} {bound:.4g}"


def _status(name: str, value: float) -> Check:
    lim = LIMITS[name]
    bad = (lambda x: x < lim.fail) if lim.below else (lambda x: x > lim.fail)
    poor = (lambda x: x < lim.warn) if lim.below else (lambda x: x > lim.warn)
    # a value that could not be measured (NaN) is a warning: the estimate stands without its evidence
    status = (
        "warn"
        if not np.isfinite(value)
        else "fail"
        if bad(value)
        else "warn"
        if poor(value)
        else "ok"
    )
    return Check(
        name, float(value), lim.warn, lim.fail, status, "" if status == "ok" else lim.action
    )


def tibia_steps(contours: Contours) -> tuple[float, float]:
    """Largest in-plane jump of the tibia's area centroid between neighbouring slices per mm of their spacing
    [mm/mm], and largest |log| ratio of neighbouring areas; (0, 0) for a single slice."""
    if contours.n_slices < 2:
        return 0.0, 0.0
    ac = [polygon_area_centroid(b[:, :2]) for b in contours.bone]
    area = np.abs([a for a, _ in ac])
    cxy = np.array([c for _, c in ac])
    dz = np.abs(np.diff(contours.z_mm))
    jump = np.linalg.norm(np.diff(cxy, axis=0), axis=1) / np.maximum(dz, 1e-9)
    return float(jump.max()), float(np.abs(np.diff(np.log(np.maximum(area, 1e-12)))).max())


class LegMovedError(PoseError):
    """The leg moved too far in the cast between the scans; ``checks`` holds the leg's rows (:func:`leg_checks`)."""

    def __init__(self, message: str, *, checks: list):
        super().__init__(message)
        self.checks = checks


def leg_checks(leg: LegRegistration) -> list[Check]:
    """The rows of the leg's registration between the scans: its shift, its turn and the far-field skin's
    residual distance after the correction."""
    return [
        _status("leg_shift_mm", leg.shift_mm),
        _status("leg_rotation_deg", abs(leg.rotation_deg)),
        _status("leg_skin_residual_mm", leg.residual_mm),
    ]


def contour_checks(pre: Contours, during: Contours) -> list[Check]:
    """The rows of the contour stacks alone: the tibia's centroid jumps and area steps of both states."""
    rows = []
    for state, c in (("pre", pre), ("during", during)):
        jump, area = tibia_steps(c)
        rows.append(_status(f"tibia_centroid_jump_{state}_mm_per_mm", jump))
        rows.append(_status(f"tibia_area_step_{state}", area))
    return rows


def evaluate_checks(pose: Pose, pre: Contours, during: Contours) -> list[Check]:
    """The checks of one animal from its pose (``extra``: the fit's diagnostics) and both contour stacks.

    Checks whose evidence is absent (a quantity given by hand in ``pose_override``) are left out.
    """
    e = pose.extra
    rows = []
    if "leg_shift_mm" in e:
        rows.append(_status("leg_shift_mm", e["leg_shift_mm"]))
        rows.append(_status("leg_rotation_deg", abs(e["leg_rotation_deg"])))
        rows.append(_status("leg_skin_residual_mm", e["leg_skin_residual_mm"]))
    if "bone_rms_final_mm" in e:
        rows.append(_status("bone_fit_rms_mm", e["bone_rms_final_mm"]))
    if "bone_slices_used" in e:
        used, total = e["bone_slices_used"]
        rows.append(_status("bone_slices_used", used / max(total, 1)))
    rows += contour_checks(pre, during)
    if e.get("fluid_column_length_mm") is not None:
        rows.append(_status("fluid_column_length_mm", e["fluid_column_length_mm"]))
    if e.get("axis_inertia_vs_cylinder_deg") is not None:
        rows.append(_status("axis_inertia_vs_cylinder_deg", e["axis_inertia_vs_cylinder_deg"]))
    sd = e.get("bone_fit_sd")
    if sd is not None and len(sd) >= 3:
        sd = np.asarray(sd, float)
        rows.append(_status("bone_rotation_sd_deg", float(np.max(sd[:3]))))
        if len(sd) > 3:
            rows.append(_status("bone_translation_sd_mm", float(np.max(sd[3:]))))
    return rows


def warnings_of(checks: list[Check]) -> list[str]:
    """ "name value > limit" of every check with status warn."""
    return [c.describe() for c in checks if c.status == "warn"]


def failed_message(checks: list[Check], *, animal: str, pre_file, during_file) -> str | None:
    """The message that stops the rule (None when no check failed): the animal, both scans and each failed
    check's value against its limit, with what to do."""
    failed = [c for c in checks if c.status == "fail"]
    if not failed:
        return None
    parts = "; ".join(f"{c.describe()} ({c.action})" for c in failed)
    return f"animal {animal}: pre {pre_file}, during {during_file}: failed QC check(s): {parts}"


def write_checks(path, checks: list[Check]) -> None:
    """Write ``checks.csv``: columns check, value, limit, fail_limit, status, action (atomically)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["check", "value", "limit", "fail_limit", "status", "action"])
            for c in checks:
                w.writerow(
                    [
                        c.name,
                        f"{c.value:.6g}",
                        f"{c.limit:g}",
                        f"{c.fail_limit:g}",
                        c.status,
                        c.action,
                    ]
                )
