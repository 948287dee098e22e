"""The pose stage: indenter pose, depth and tibia motion of one animal, and the rule's file glue.

:func:`estimate_pose` combines the indenter (:mod:`.indenter`), the leg's registration between the
scans (:mod:`.registration`) and the bone fit (:mod:`.bone`) on arrays, with any quantity given by hand
in ``pose_override``; :func:`run_pose` reads the rule's inputs, writes ``pose.json``, the QC checks
(:mod:`.checks`) and the QC figures (:mod:`.qc`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..bone_motion import (
    BoneDistance,
    BoneFit,
    bone_centroid_mm,
    fit_bone_motion,
    resolve_bone_dof,
)
from ..contours import load_contours
from ..fluid import FluidComponent, FluidSearch, inside_skin_mask, orient_axis
from ..imaging import load_nifti
from ..pose_error import PoseError, _where
from .checks import (
    LegMovedError,
    contour_checks,
    evaluate_checks,
    failed_message,
    leg_checks,
    warnings_of,
    write_checks,
)
from .indenter import TipSearch, line_triangle_hits, skin_triangles, tip_end_mm
from .qc import plot_axis_qc, plot_bone_qc, plot_tip_qc
from .registration import LegGuard, LegRegistration, register_leg
from .result import Pose, save_pose
from .scan import check_axial_slices

if TYPE_CHECKING:
    from ..contours import Contours

__all__ = [
    "PoseFiles",
    "PoseOptions",
    "check_depth",
    "check_tip_in_leg",
    "estimate_pose",
    "read_override",
    "run_pose",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PoseOptions:
    """Settings of :func:`estimate_pose` (config section ``pose``); see the schema for each key."""

    # the fluid search's keys, with its defaults (deeptissue.fluid.FluidSearch, shared with the segmentation)
    fluid_threshold: float | None = FluidSearch.fluid_threshold
    fluid_threshold_ratio: float = FluidSearch.fluid_threshold_ratio
    min_component_mm3: float = FluidSearch.min_component_mm3
    ambiguity_ratio: float = FluidSearch.ambiguity_ratio
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


def read_override(override: dict | None, *, animal: str = "") -> dict:
    """The config ``pose_override`` of an animal as arrays (None values dropped), each checked.

    Raises :class:`PoseError` naming the key for an unknown key, a value that is not 3 finite numbers, or
    an ``indenter_axis`` of zero length.
    """
    out = {}
    for key, value in (override or {}).items():
        if value is None:
            continue
        if key not in _OVERRIDE_KEYS:
            raise PoseError(
                f"{_where(animal)}unknown pose_override key {key!r}; known: {', '.join(_OVERRIDE_KEYS)}"
            )
        try:
            v = np.asarray(value, float)
        except (TypeError, ValueError):
            v = np.full(0, np.nan)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise PoseError(
                f"{_where(animal)}pose_override.{key} must be 3 finite numbers, got {value!r}: "
                "correct it or remove it to use the automatic estimate"
            )
        if key == "indenter_axis" and np.linalg.norm(v) < 1e-9:
            raise PoseError(
                f"{_where(animal)}pose_override.indenter_axis {value!r} has zero length: give the direction "
                "from the indenter into the leg, or remove it to use the axis of the contrast fluid"
            )
        out[key] = v
    return out


def check_tip_in_leg(tip_mm: np.ndarray, during_contours: Contours, *, animal: str = "") -> None:
    """Refuse a hand-given ``pose_override.tip_end_mm`` (3,) [mm] outside the leg of the during scan: beyond
    half a slice from the imaged slab, or farther in-plane from the skin's centre on its slice than any skin
    vertex of that slice."""
    z = during_contours.z_mm
    k = int(np.argmin(np.abs(z - tip_mm[2])))
    half = 0.5 * (float(np.median(np.abs(np.diff(z)))) if len(z) > 1 else 1.0)
    skin = during_contours.skin[k, :, :2]
    centre = skin.mean(axis=0)
    reach = float(np.linalg.norm(skin - centre, axis=1).max())
    off = float(np.linalg.norm(tip_mm[:2] - centre))
    if abs(tip_mm[2] - z[k]) <= half and off <= reach:
        return
    raise PoseError(
        f"{_where(animal)}pose_override.tip_end_mm {np.round(tip_mm, 3).tolist()} lies outside the leg of the "
        f"during scan ({off:.3g} mm from the leg's centre at z = {z[k]:.3g} mm, where the skin reaches "
        f"{reach:.3g} mm; slices z = {z.min():.3g} to {z.max():.3g} mm): give the tip at full indentation, "
        "inside the leg, in world mm of the during scan"
    )


def _locate_fluid(
    during: np.ndarray,
    affine: np.ndarray,
    during_contours: Contours,
    options: PoseOptions,
    animal: str,
) -> tuple[FluidComponent, dict]:
    """The contrast fluid in the during scan (its own frame) and its diagnostics for ``pose.json``."""
    mask = inside_skin_mask(np.shape(during), affine, during_contours.skin)
    search = FluidSearch(**{k: getattr(options, k) for k in FluidSearch.__dataclass_fields__})
    fluid = search.find(during, affine, mask, animal=animal)
    m = fluid.moments_mm2
    # evidence for the QC checks: the column's length along the axis, and how far the cylinder fit turned
    # the inertia axis (NaN when the fit did not run or was rejected: the axis is the inertia axis)
    s_col = (fluid.points_mm - fluid.com_mm) @ fluid.axis
    extra = dict(
        fluid_threshold=fluid.threshold,
        fluid_volume_mm3=fluid.volume_mm3,
        fluid_candidate_volumes_mm3=list(fluid.candidate_volumes_mm3[:5]),
        fluid_elongation=float(np.sqrt(m[2] / max(m[0], 1e-12))),
        fluid_column_length_mm=float(s_col.max() - s_col.min()),
    )
    if fluid.axis_inertia is not None:
        refined = not np.array_equal(fluid.axis_inertia, fluid.axis)
        cos = abs(float(fluid.axis_inertia @ fluid.axis)) / float(
            np.linalg.norm(fluid.axis_inertia)
        )
        extra["axis_inertia_vs_cylinder_deg"] = (
            float(np.degrees(np.arccos(min(cos, 1.0)))) if refined else float("nan")
        )
    return fluid, extra


@dataclass(frozen=True)
class _Indenter:
    """The indenter on the pre scan's frame: ``axis`` (3,) into the leg, the fluid's ``com_mm`` (3,) and its
    ``front_mm`` along the axis from it (None without the fluid), and ``points_mm`` (n, 3) of the fluid."""

    axis: np.ndarray
    com_mm: np.ndarray | None
    front_mm: float | None
    points_mm: np.ndarray | None


def _register(
    fluid: FluidComponent | None,
    override: dict,
    pre: Contours,
    during_contours: Contours,
    animal: str,
) -> tuple[LegRegistration, _Indenter]:
    """The leg's registration between the scans (the guard around the indenter's front in the during scan)
    and the indenter moved onto the pre scan; :class:`LegMovedError` when the leg moved too far."""
    if "indenter_axis" in override:
        axis = override["indenter_axis"] / np.linalg.norm(override["indenter_axis"])
    else:
        leg_centre = during_contours.skin.reshape(-1, 3).mean(axis=0)
        axis = orient_axis(fluid.axis, from_mm=fluid.com_mm, toward_mm=leg_centre)
    if fluid is None:
        front, guard = None, override["tip_end_mm"]
    else:
        front = float(np.max((fluid.points_mm - fluid.com_mm) @ axis))
        guard = fluid.com_mm + front * axis
    leg = register_leg(pre.skin, during_contours.skin, LegGuard(guard), animal=animal)
    rows = leg_checks(leg)
    failed = [c for c in rows if c.status == "fail"]
    if failed:
        raise LegMovedError(
            f"{_where(animal)}" + "; ".join(f"{c.describe()} ({c.action})" for c in failed),
            checks=rows,
        )
    if fluid is None:
        return leg, _Indenter(leg.direction_to_pre(axis), None, None, None)
    return leg, _Indenter(
        leg.direction_to_pre(axis), leg.to_pre(fluid.com_mm), front, leg.to_pre(fluid.points_mm)
    )


def _travel(
    tip_end: np.ndarray, ind: _Indenter, pre: Contours, backoff_mm: float, animal: str
) -> tuple[np.ndarray, np.ndarray]:
    """The skin entry and the start of travel: the line through the tip along the axis meets the pre skin at
    the crossing nearest the indenter (its fluid's COM, or 5 mm back from the tip); the start lies
    ``backoff_mm`` back from there."""
    ref = ind.com_mm if ind.com_mm is not None else tip_end - 5.0 * ind.axis
    t_hits = line_triangle_hits(tip_end, ind.axis, skin_triangles(pre.skin))
    if t_hits.size == 0:
        raise PoseError(
            f"{_where(animal)}the indenter axis does not meet the undeformed (pre) skin surface; "
            "give pose_override.tip_start_mm or indenter_axis"
        )
    hits = tip_end + t_hits[:, None] * ind.axis
    surface = hits[np.argmin(np.linalg.norm(hits - ref, axis=1))]
    return surface, surface - backoff_mm * ind.axis


def check_depth(
    depth_mm: float, tip_end: np.ndarray, pre: Contours, *, given: bool, animal: str = ""
) -> None:
    """Refuse a depth that no indentation gives: not finite, not below the undeformed skin (<= 0), or deeper
    than the leg's radius at the tip's slice (mean distance of the pre skin from its centroid).

    ``given``: the tip came from ``pose_override.tip_end_mm`` (named in the message).
    """
    k = int(np.argmin(np.abs(pre.z_mm - tip_end[2])))
    skin = pre.skin[k]
    radius = float(np.mean(np.linalg.norm(skin[:, :2] - skin[:, :2].mean(axis=0), axis=1)))
    if np.isfinite(depth_mm) and 0 < depth_mm <= radius:
        return
    source = (
        f"pose_override.tip_end_mm {np.round(tip_end, 3).tolist()}"
        if given
        else f"the tip found on the deformed skin at {np.round(tip_end, 3).tolist()} mm"
    )
    fix = (
        "correct pose_override.tip_end_mm (world mm of the during scan, inside the leg)"
        if given
        else "check the pose figures and give pose_override.tip_end_mm"
    )
    raise PoseError(
        f"{_where(animal)}{source} gives an indentation depth of {depth_mm:.4g} mm below the undeformed "
        f"skin; a tip inside the leg lies between 0 and the leg's radius ({radius:.3g} mm at z = "
        f"{pre.z_mm[k]:.3g} mm): {fix}"
    )


def _bone(pre: Contours, dur: Contours, options: PoseOptions, animal: str) -> tuple[BoneFit, dict]:
    """The tibia's fitted motion (:class:`~deeptissue.bone_motion.BoneFit`) and its diagnostics."""
    dof, why = resolve_bone_dof(options.bone_dof, pre, dur)
    log.info("%s%s", _where(animal), why)
    fit = fit_bone_motion(
        pre.bone,
        dur.bone,
        fibula_pre_mm=pre.fibula,
        fibula_during_mm=dur.fibula,
        distance=BoneDistance(options.bone_method, options.bone_surface_step_mm),
        dof=dof,
        during_slices=dur.bone_seen if pre.n_slices == dur.n_slices else None,
        animal=animal,
    )
    extra = dict(
        bone_slices_used=[int(dur.bone_seen.sum()), dur.n_slices],
        bone_dof_reason=why,
        bone_fibula_slices=list(fit.fibula_slices),
        bone_method=fit.method,
        bone_dof=fit.dof,
        bone_com_shift_mm=fit.com_shift_mm,
        bone_rms_initial_mm=fit.rms_initial_mm,
        bone_rms_com_mm=fit.rms_com_mm,
        bone_rms_final_mm=fit.rms_final_mm,
        bone_fit_evaluations=fit.n_evaluations,
        bone_fit_sd=fit.parameter_sd,
    )
    return fit, extra


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
    """Indenter pose, depth and tibia motion of one animal, on the pre scan's frame.

    The contrast fluid is found in the during scan; the leg's in-plane motion between the scans is fitted
    to the skin outside a guard around the indenter's front (:class:`LegGuard`) (:func:`register_leg`) and undone
    on everything the during scan shows (fluid, skin, tibia, fibula), so the pose is measured against the
    pre scan's leg. Quantities given in ``override`` replace the automatic ones, and the ones that depend on
    them are computed from them; ``indenter_axis`` and ``tip_end_mm`` are read in the during scan and moved
    with it, ``tip_start_mm`` lies on the pre scan. With both ``indenter_axis`` and ``tip_end_mm`` given the
    fluid is not needed at all.

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
        ``bone_translation_mm`` given by hand (config ``pose_override``, :func:`read_override`).
    animal : str
        Named in messages.

    Returns
    -------
    pose : Pose
        With the fit diagnostics and the leg's correction (``leg_*``) in ``extra``.
    qc : dict
        Intermediate arrays for the QC figures (fluid points, ROI front, centroid shift, the during
        contours and affine on the pre scan's frame).

    Raises
    ------
    PoseError
        Naming the animal and the reason, when the scan cannot be read; :class:`LegMovedError` (with the
        leg's check rows) when the leg moved too far between the scans.
    """
    ov = read_override(override, animal=animal)
    affine = np.asarray(affine, float)
    extra: dict = {"overrides": sorted(ov)}
    if "tip_end_mm" in ov:
        check_tip_in_leg(ov["tip_end_mm"], during_contours, animal=animal)
    fluid = None
    if not ("indenter_axis" in ov and "tip_end_mm" in ov):
        fluid, fluid_extra = _locate_fluid(during, affine, during_contours, options, animal)
        extra.update(fluid_extra)
    leg, ind = _register(fluid, ov, pre, during_contours, animal)
    extra.update(leg.to_extra())
    dur = leg.correct(during_contours)
    qc: dict = {"fluid_points_mm": ind.points_mm, "during_contours": dur}
    qc["affine_on_pre"] = leg.matrix_to_pre() @ affine

    if "tip_end_mm" in ov:
        tip_end = leg.to_pre(ov["tip_end_mm"])
    else:
        tip_end, info = tip_end_mm(
            dur.skin,
            TipSearch(
                axis=ind.axis,
                com_mm=ind.com_mm,
                front_mm=ind.front_mm,
                roi_diameter_mm=options.roi_diameter_mm,
                reach_mm=options.roi_reach_mm,
            ),
            head_radius_mm=options.head_radius_mm,
            method=options.tip_method,
            animal=animal,
        )
        extra.update(info)
        qc["roi_front_mm"] = ind.front_mm
    if "tip_start_mm" in ov:
        tip_start = ov["tip_start_mm"]
        surface = tip_start + options.start_backoff_mm * ind.axis
    else:
        surface, tip_start = _travel(tip_end, ind, pre, options.start_backoff_mm, animal)
    depth = float((tip_end - surface) @ ind.axis)
    check_depth(depth, tip_end, pre, given="tip_end_mm" in ov, animal=animal)
    extra["skin_entry_mm"] = surface

    if "bone_rotation_deg" in ov and "bone_translation_mm" in ov:
        com_pre, rot, trans = (
            bone_centroid_mm(pre.bone),
            ov["bone_rotation_deg"],
            ov["bone_translation_mm"],
        )
    else:
        fit, bone_extra = _bone(pre, dur, options, animal)
        extra.update(bone_extra)
        com_pre = fit.motion.centre_mm
        rot = ov.get("bone_rotation_deg", fit.motion.rotation_deg)
        trans = ov.get("bone_translation_mm", fit.motion.translation_mm)
        qc["bone_com_shift_mm"] = fit.com_shift_mm
    pose = Pose(
        indenter_axis=ind.axis,
        tip_start_mm=tip_start,
        tip_end_mm=tip_end,
        depth_mm=depth,
        bone_com_mm=com_pre,
        bone_rotation_deg=rot,
        bone_translation_mm=trans,
        indenter_com_mm=ind.com_mm,
        extra=extra,
    )
    return pose, qc


@dataclass(frozen=True)
class PoseFiles:
    """The files of rule ``pose``.

    Inputs: ``during_nifti`` the during scan, ``pre_nifti`` the pre scan (its slice orientation is checked
    and it is named in messages; None: not checked, the pre contours are named), ``pre_contours`` and
    ``during_contours`` (:func:`deeptissue.contours.save_contours`). Outputs: ``pose_json``
    (:func:`~deeptissue.pose.save_pose`), the QC figures ``axis_png``, ``tip_png``, ``bone_png``, and
    ``checks_csv`` (:func:`~deeptissue.pose.checks.write_checks`; None: evaluated, not written).
    """

    during_nifti: Path
    pre_contours: Path
    during_contours: Path
    pose_json: Path
    axis_png: Path
    tip_png: Path
    bone_png: Path
    checks_csv: Path | None = None
    pre_nifti: Path | None = None


def failed_checks_path(checks_csv: Path) -> Path:
    """Where a refused animal's checks are kept: ``checks_failed.csv`` beside ``checks.csv``, a file the rule
    does not declare, so that Snakemake, which removes a failed rule's outputs, leaves it."""
    p = Path(checks_csv)
    return p.with_name(f"{p.stem}_failed{p.suffix}")


def _record_checks(checks: list, checks_csv: Path | None, animal: str, *, failed: bool) -> None:
    """Write ``checks.csv`` (unless None), and for a refused animal the same rows to ``checks_failed.csv``
    (removed again by the next run that passes); log every row."""
    if checks_csv is not None:
        write_checks(checks_csv, checks)
        kept = failed_checks_path(checks_csv)
        if failed:
            write_checks(kept, checks)
        else:
            kept.unlink(missing_ok=True)
    for c in checks:
        ok = c.status == "ok"
        log.log(
            logging.INFO if ok else logging.WARNING,
            "%s check %s",
            animal,
            f"{c.name} {c.value:.4g} ok" if ok else f"{c.describe()} ({c.status})",
        )


def run_pose(
    files: PoseFiles,
    *,
    options: dict | None = None,
    override: dict | None = None,
    animal: str = "",
) -> Pose:
    """Rule ``pose``: read the during NIfTI and both contour files, write ``pose.json``, the QC figures and the
    QC checks (:mod:`.checks`); a failed check stops the rule after ``checks_csv`` is written.

    Both scans must have axial slices (:func:`~deeptissue.pose.scan.check_axial_slices`).

    Parameters
    ----------
    files : PoseFiles
        Inputs and outputs.
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
        When a check fails (the leg moved too far between the scans among them): naming the animal, both
        scans and the value against its limit.
    """
    f = files
    vol = load_nifti(
        f.during_nifti, animal=animal
    )  # unreadable or not 3D: ImagingError naming both
    check_axial_slices(vol.affine, where=f"{_where(animal)}during scan {f.during_nifti}")
    if f.pre_nifti is not None:
        pre_affine = load_nifti(f.pre_nifti, animal=animal).affine
        check_axial_slices(pre_affine, where=f"{_where(animal)}pre scan {f.pre_nifti}")
    data = vol.data.astype(float)
    pre = load_contours(f.pre_contours)
    dur = load_contours(f.during_contours)
    opts = PoseOptions.from_config(options)
    pre_file = f.pre_nifti or f.pre_contours
    try:
        pose, qc = estimate_pose(
            data, vol.affine, pre, dur, options=opts, override=override, animal=animal
        )
    except LegMovedError as exc:
        checks = exc.checks + contour_checks(pre, dur)
        _record_checks(checks, f.checks_csv, animal, failed=True)
        raise PoseError(
            failed_message(checks, animal=animal, pre_file=pre_file, during_file=f.during_nifti)
        ) from exc
    checks = evaluate_checks(pose, pre, dur)
    message = failed_message(checks, animal=animal, pre_file=pre_file, during_file=f.during_nifti)
    _record_checks(checks, f.checks_csv, animal, failed=bool(message))
    if message:
        raise PoseError(message)
    pose = replace(pose, extra={**pose.extra, "qc_warnings": warnings_of(checks)})
    plot_axis_qc(f.axis_png, data, qc["affine_on_pre"], pose, qc, title=animal)
    plot_tip_qc(
        f.tip_png,
        pre,
        qc["during_contours"],
        pose,
        roi_diameter_mm=opts.roi_diameter_mm,
        title=animal,
    )
    plot_bone_qc(f.bone_png, pre, qc["during_contours"], pose, title=animal)
    save_pose(f.pose_json, pose)
    return pose
