"""Checks of one state's segmentation, for every animal (``results/{animal}/qc/segmentation_checks_{state}.csv``),
and every check of one animal in one table (``results/{animal}/qc/checks.csv``, :func:`merge_checks`).

A segmentation carries its own evidence that the contour taken for the tibia is the tibia on every slice: its
section changes slowly along the leg, its centroid does not jump, it is not a fraction of another dark region's
area, it is larger than the fibula, and the skin lies on the edge of the leg. The checks run on scans without
an indenter too (a ``pre``-only animal has no pose stage), and a failure stops the segmentation rule naming
every failing slice. :func:`merge_checks` puts the segmentation checks of each state and, for an animal with a
``during`` scan, the pose stage's (``pose_checks.csv``, :mod:`deeptissue.pose.checks`) in one file, so that every
animal's QC is read in one place.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from skimage.measure import find_contours

from .contours import Contours, polygon_area_centroid
from .imaging import Volume, body_mask
from .io import atomic_path

__all__ = [
    "CHECKS_COLUMNS",
    "SegmentationCheck",
    "failed_checks_message",
    "merge_checks",
    "segmentation_checks",
    "write_checks",
]

# Failure limits. The tibia's section area and centroid from slice to slice are those of the pose stage's checks
# (deeptissue.pose.checks.LIMITS, measured on the digital phantoms): |log(A_k / A_k-1)| 0.04-0.05 and a centroid
# drift of 0.02-0.05 mm per mm of slice spacing on good phantoms, 1.4-2.1 and 2-4 mm/mm where the fibula is
# taken for the tibia. The human calf_ankle scan (config/calf_ankle.yaml, slices 5-30) reaches 0.22 and 0.51 mm/mm
# (the latter where the tibia flares into the ankle, slice 6; 0.36 from slice 12 on).
AREA_STEP_MAX = 0.6
JUMP_MAX_MM_PER_MM = 0.6
# the tibia is the larger long bone: at least half of any other dark region on its slice (the 'anterior' choice
# takes the most anterior of those at least half as large) and larger than the fibula
OTHER_RATIO_MIN = 0.5
FIBULA_RATIO_MIN = 1.0
# the skin on the leg's edge: the median distance of its points from the edge of the body (the non-zero region of
# a masked scan, the tissue above the noise otherwise), at most one pixel plus the smoothing width
SKIN_EDGE_PX = 1.0

ACTIONS = {
    "tibia_area_step": "the tibia's section changes size abruptly: check the segmentation figure; another "
    "structure may be taken for it (set segmentation.bone_open_mm or bone_select, or draw an override)",
    "tibia_centroid_jump_mm_per_mm": "the contour taken for the tibia jumps between slices: check the "
    "segmentation figure, set segmentation.bone_select or draw an override",
    "tibia_other_ratio": "another dark region is more than twice the tibia's area on this slice: the tibia may be "
    "cut short or the wrong structure taken; check the figure and segmentation.bone_open_mm",
    "tibia_fibula_ratio": "the fibula is larger than the tibia: the two may be swapped; check the figure, set "
    "segmentation.bone_select: anterior or draw an override",
    "skin_to_mask_mm": "the skin lies off the edge of the leg: check the figure, segmentation.skin_level and "
    "skin_close_mm (a masked scan's broken skin ring)",
    "slices_left_out": "slices of the file outside crop_mm are not segmented",
    "slice_left_out": "this slice at an end of the stack cannot be segmented and is left out "
    "(segmentation.end_slices: leave_out): the model uses the slices kept; draw it in an overrides file to keep it",
}


#: the checks that warn past their limit and never stop the rule
WARN_ONLY = frozenset({"slice_left_out"})


@dataclass(frozen=True)
class SegmentationCheck:
    """One check on one slice (``slice`` -1: the whole scan); ``limit`` is a maximum, or a minimum with ``below``;
    a check of :data:`WARN_ONLY` past its limit warns and does not stop the rule."""

    name: str
    slice: int
    value: float
    limit: float
    below: bool = False

    @property
    def warn(self) -> bool:
        """Whether the check only warns (:data:`WARN_ONLY`)."""
        return self.name in WARN_ONLY

    @property
    def status(self) -> str:
        """``ok``, ``fail`` (``warn`` for a warning check), or ``n/a`` for a value that cannot be computed (NaN: no
        fibula on the slice)."""
        if not np.isfinite(self.value):
            return "n/a"
        bad = self.value < self.limit if self.below else self.value > self.limit
        if not bad:
            return "ok"
        return "warn" if self.warn else "fail"


def _skin_to_edge_mm(vol: Volume, skin: np.ndarray, body: np.ndarray, k: int) -> float:
    """Median distance [mm] of the skin points of slice ``k`` from the body's edge on that slice."""
    edges = find_contours(body[:, :, k].astype(float), 0.5)
    if not edges:
        return float("nan")
    pts = np.vstack(edges)
    xy = vol.world(np.column_stack([pts, np.full(len(pts), k)]))[:, :2]
    d, _ = cKDTree(xy).query(skin[k, :, :2])
    return float(np.median(d))


def segmentation_checks(
    vol: Volume, contours: Contours, info: dict, *, smooth_mm: float, n_file_slices: int
) -> list[SegmentationCheck]:
    """The checks of the module docstring on every slice of ``contours``, segmented from ``vol`` (the image the
    skin was traced on, one leg), with ``info`` from :func:`deeptissue.segment.segment_volume`; ``smooth_mm`` is
    the segmentation's smoothing width, ``n_file_slices`` the number of slices in the file."""
    off = vol.index_offset[2]
    dz = float(np.linalg.norm(vol.affine[:3, 2]))
    px = float(np.sqrt(np.prod(vol.pixel_mm)))
    body = body_mask(vol)
    out = [
        SegmentationCheck(
            "slices_left_out", -1, float(n_file_slices - contours.n_slices), n_file_slices
        )
    ]
    # a slice left out at an end of the stack (segmentation.end_slices: leave_out): 1, a warning
    out += [
        SegmentationCheck("slice_left_out", int(k), 1.0, 0.0)
        for k in sorted(info.get("left_out", {}))
    ]
    area = np.array([polygon_area_centroid(b[:, :2])[0] for b in contours.bone])
    cen = np.array([polygon_area_centroid(b[:, :2])[1] for b in contours.bone])
    for k in range(contours.n_slices):
        kf = k + off
        if k > 0:
            out.append(
                SegmentationCheck(
                    "tibia_area_step", kf, float(abs(np.log(area[k] / area[k - 1]))), AREA_STEP_MAX
                )
            )
            jump = float(np.linalg.norm(cen[k] - cen[k - 1])) / dz
            out.append(
                SegmentationCheck("tibia_centroid_jump_mm_per_mm", kf, jump, JUMP_MAX_MM_PER_MM)
            )
        ratio = info["slices"][k].get("tibia_other_ratio", float("nan"))
        out.append(SegmentationCheck("tibia_other_ratio", kf, float(ratio), OTHER_RATIO_MIN, True))
        fib = float("nan")
        if contours.fibula is not None and np.isfinite(contours.fibula[k]).all():
            fib = area[k] / polygon_area_centroid(contours.fibula[k, :, :2])[0]
        out.append(SegmentationCheck("tibia_fibula_ratio", kf, fib, FIBULA_RATIO_MIN, True))
        out.append(
            SegmentationCheck(
                "skin_to_mask_mm",
                kf,
                _skin_to_edge_mm(vol, contours.skin, body, k),
                SKIN_EDGE_PX * px + smooth_mm,
            )
        )
    return out


def failed_checks_message(checks: list[SegmentationCheck], where: str) -> str | None:
    """One message naming every failed check with its slices and what to do, or None when none failed."""
    bad: dict = {}
    for c in checks:
        if c.status == "fail":
            bad.setdefault(c.name, []).append(c)
    if not bad:
        return None
    parts = []
    for name, cs in bad.items():
        worst = min(cs, key=lambda c: c.value) if cs[0].below else max(cs, key=lambda c: c.value)
        parts.append(
            f"{name} on slice(s) {', '.join(str(c.slice) for c in cs)} (worst {worst.value:.3g}, "
            f"{'minimum' if worst.below else 'maximum'} {worst.limit:g}): {ACTIONS[name]}"
        )
    return f"{where}: failed segmentation check(s): " + "; ".join(parts)


def write_checks(path, checks: list[SegmentationCheck]) -> None:
    """Write the checks as CSV (columns check, slice, value, limit, status, action), atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["check", "slice", "value", "limit", "status", "action"])
            for c in checks:
                w.writerow(
                    [
                        c.name,
                        c.slice,
                        f"{c.value:.6g}",
                        f"{c.limit:g}",
                        c.status,
                        ACTIONS[c.name] if c.status in ("fail", "warn") else "",
                    ]
                )


#: the columns of an animal's ``checks.csv``
CHECKS_COLUMNS = ("stage", "check", "slice", "value", "limit", "fail_limit", "status", "action")


def _read_rows(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def merge_checks(path, *, segmentation: dict, pose=None) -> int:
    """Write every check of one animal to ``path`` (columns :data:`CHECKS_COLUMNS`, atomically) and return the
    number of rows: the rows of each state's segmentation checks (``segmentation``: ``{state: csv}``, stage
    ``segmentation_{state}``; their ``limit`` is the failure limit, the warning limit of a check that only warns)
    and of the pose checks (``pose``: its ``checks.csv`` or None for an animal without a ``during`` scan; stage
    ``pose``, no slice). ``status`` and ``action`` are copied as each stage wrote them."""
    rows = []
    for state, src in segmentation.items():
        for r in _read_rows(src):
            warn_only = r["check"] in WARN_ONLY
            rows.append(
                {
                    **r,
                    "stage": f"segmentation_{state}",
                    "limit": r["limit"] if warn_only else "",
                    "fail_limit": "" if warn_only else r["limit"],
                }
            )
    if pose is not None:
        rows += [{**r, "stage": "pose", "slice": ""} for r in _read_rows(pose)]
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=CHECKS_COLUMNS)
            w.writeheader()
            w.writerows({k: r[k] for k in CHECKS_COLUMNS} for r in rows)
    return len(rows)
