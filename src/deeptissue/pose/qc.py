"""QC figures of the pose stage: the fluid and the axis, the skin at the tip, the bone fit.

Each function writes one PNG (atomically) for the rule's report; nothing is returned.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..rigid import rotation_matrix
from .result import Pose

if TYPE_CHECKING:
    from ..contours import Contours

__all__ = ["plot_axis_qc", "plot_bone_qc", "plot_tip_qc", "travel_marks_mm"]


def travel_marks_mm(pose: Pose) -> dict:
    """Where :func:`plot_tip_qc` draws the travel: depth [mm] along the axis below the skin entry (where the
    axis meets the undeformed skin, ``pose.extra["skin_entry_mm"]``; the start of travel when absent) of
    ``start`` (the start of travel, negative: above the skin), ``skin`` (0) and ``end`` (the tip end: the
    pose's depth)."""
    a = pose.indenter_axis
    entry = np.asarray(pose.extra.get("skin_entry_mm", pose.tip_start_mm), float)
    return {
        "start": float((pose.tip_start_mm - entry) @ a),
        "skin": 0.0,
        "end": float((pose.tip_end_mm - entry) @ a),
    }


def plot_axis_qc(
    path, during: np.ndarray, affine: np.ndarray, pose: Pose, qc: dict, *, title: str = ""
) -> None:
    """Axial and sagittal cross-sections through the indenter COM with the fluid voxels and the axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_path

    affine = np.asarray(affine, float)
    centre = pose.indenter_com_mm if pose.indenter_com_mm is not None else pose.tip_end_mm
    ijk = np.linalg.solve(affine[:3, :3], centre - affine[:3, 3])
    i, k = (int(np.clip(round(ijk[n]), 0, np.shape(during)[n] - 1)) for n in (0, 2))
    sx, sy, sz = np.abs(np.diag(affine[:3, :3]))
    x0, y0, z0 = affine[:3, 3]
    nx, ny, nz = np.shape(during)
    xs = np.sort([x0, x0 + (nx - 1) * affine[0, 0]])
    ys = np.sort([y0, y0 + (ny - 1) * affine[1, 1]])
    zs = np.sort([z0, z0 + (nz - 1) * affine[2, 2]])
    fig, axs = plt.subplots(1, 2, figsize=(11, 5))
    line = centre[None] + np.linspace(-8, 8, 2)[:, None] * pose.indenter_axis
    pts = qc.get("fluid_points_mm")
    axs[0].imshow(
        np.asarray(during)[:, :, k].T,
        origin="lower",
        cmap="gray",
        extent=[xs[0] - sx / 2, xs[1] + sx / 2, ys[0] - sy / 2, ys[1] + sy / 2],
    )
    axs[1].imshow(
        np.asarray(during)[i, :, :].T,
        origin="lower",
        cmap="gray",
        aspect="auto",
        extent=[ys[0] - sy / 2, ys[1] + sy / 2, zs[0] - sz / 2, zs[1] + sz / 2],
    )
    if pts is not None:
        sel = np.abs(pts[:, 2] - affine[2, 3] - k * affine[2, 2]) < sz / 2
        axs[0].plot(pts[sel, 0], pts[sel, 1], ",", color="tab:cyan", alpha=0.5)
        sel = np.abs(pts[:, 0] - affine[0, 3] - i * affine[0, 0]) < sx / 2
        axs[1].plot(pts[sel, 1], pts[sel, 2], "s", ms=2, color="tab:cyan", alpha=0.5)
    for ax, (a, b) in zip(axs, [(0, 1), (1, 2)]):
        ax.plot(line[:, a], line[:, b], "r-", lw=1, label="axis")
        ax.plot(*pose.tip_end_mm[[a, b]], "y+", ms=12, mew=2, label="tip end")
        ax.plot(*pose.tip_start_mm[[a, b]], "gx", ms=10, mew=2, label="tip start")
    axs[0].set(
        title=f"axial z = {zs[0] + k * sz:.1f} mm",
        xlabel="x [mm]",
        ylabel="y [mm]",
        xlim=(xs[0] - sx / 2, xs[1] + sx / 2),
        ylim=(ys[0] - sy / 2, ys[1] + sy / 2),
    )
    axs[1].set(
        title=f"sagittal x = {xs[0] + i * sx:.2f} mm",
        xlabel="y [mm]",
        ylabel="z [mm]",
        xlim=(ys[0] - sy / 2, ys[1] + sy / 2),
        ylim=(zs[0] - sz / 2, zs[1] + sz / 2),
    )
    axs[0].legend(loc="lower left", fontsize=8)
    fig.suptitle(title + " — contrast fluid (cyan) and indenter axis")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def plot_tip_qc(
    path,
    pre: Contours,
    during_contours: Contours,
    pose: Pose,
    *,
    roi_diameter_mm: float = 5.0,
    title: str = "",
) -> None:
    """The skin around the axis with the travel: depth along vs distance from the axis, and the tip's slice.

    Depths are measured along the axis from the skin entry (``pose.extra["skin_entry_mm"]``, where the axis
    meets the undeformed skin; the start of travel when absent): the entry is at 0, the tip end at the
    depth of the title, the start of travel ``start_backoff_mm`` above the skin. ``during_contours`` are
    those the pose was measured on (after the leg's correction between the scans).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_path

    a = pose.indenter_axis
    entry = np.asarray(pose.extra.get("skin_entry_mm", pose.tip_start_mm), float)
    fig, axs = plt.subplots(1, 2, figsize=(11, 5))
    for c, lab, col in [
        (pre.skin, "pre skin", "tab:blue"),
        (during_contours.skin, "during skin", "tab:orange"),
    ]:
        d = c.reshape(-1, 3) - entry
        s = d @ a
        r = np.linalg.norm(d - s[:, None] * a, axis=1)
        sel = r <= roi_diameter_mm / 2
        axs[0].plot(r[sel], s[sel], ".", ms=3, color=col, label=f"{lab} in ROI")
    marks = travel_marks_mm(pose)
    s_start, s_end = marks["start"], marks["end"]
    axs[0].axhline(s_start, color="g", lw=1, ls="--", label=f"start of travel ({s_start:+.2f} mm)")
    axs[0].axhline(0.0, color="tab:blue", lw=1, label="undeformed skin on the axis (0)")
    axs[0].axhline(s_end, color="r", lw=1, label=f"tip end ({s_end:.3f} mm)")
    axs[0].set_ylim(
        s_end + 2.0, min(s_start, 0.0) - 1.0
    )  # the far side of the leg is outside the ROI
    axs[0].set(
        xlabel="distance from axis [mm]",
        ylabel="depth along axis below the undeformed skin [mm]",
        title=f"ROI (⌀ {roi_diameter_mm:g} mm): depth = {pose.depth_mm:.3f} mm, "
        f"travel = {pose.travel_mm:.3f} mm",
    )
    axs[0].legend(fontsize=8)
    k = int(np.argmin(np.abs(during_contours.z_mm - pose.tip_end_mm[2])))
    for c, lab, col in [
        (pre.skin, "pre", "tab:blue"),
        (during_contours.skin, "during", "tab:orange"),
    ]:
        axs[1].plot(
            *np.vstack([c[k], c[k][:1]])[:, :2].T, "-", color=col, lw=1, label=f"{lab} skin"
        )
    line = pose.tip_end_mm[None] + np.linspace(-6, 2, 2)[:, None] * a
    axs[1].plot(line[:, 0], line[:, 1], "r-", lw=0.8)
    axs[1].plot(*pose.tip_start_mm[:2], "gx", ms=10, mew=2, label="start of travel")
    axs[1].plot(*entry[:2], "o", mfc="none", mec="tab:blue", ms=8, label="skin entry")
    axs[1].plot(*pose.tip_end_mm[:2], "r+", ms=12, mew=2, label="tip end")
    axs[1].set(
        aspect="equal",
        xlabel="x [mm]",
        ylabel="y [mm]",
        title=f"slice z = {during_contours.z_mm[k]:.1f} mm",
    )
    axs[1].legend(fontsize=8)
    fig.suptitle(title + " — skin under the indenter: start of travel, skin entry, tip end")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def plot_bone_qc(
    path, pre: Contours, during_contours: Contours, pose: Pose, *, title: str = ""
) -> None:
    """Bone contours (tibia, and the fibula when both states have it) before, after centroid alignment,
    and after the full rigid fit (x-y and y-z views)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_path

    c = pose.bone_com_mm
    dur = during_contours.bone
    shift = np.asarray(pose.extra.get("bone_com_shift_mm", pose.bone_translation_mm), float)
    R = rotation_matrix(pose.bone_rotation_deg)
    fib_pre, fib_dur = pre.fibula_rows, during_contours.fibula_rows
    if len(fib_pre) and len(fib_dur):  # the fibula, moved with the tibia, is drawn with it
        pre_pts = np.concatenate([pre.bone.reshape(-1, 3), fib_pre.reshape(-1, 3)])
        dur = np.concatenate([dur.reshape(-1, 3), fib_dur.reshape(-1, 3)])
    else:
        pre_pts = pre.bone.reshape(-1, 3)
    back = [dur, dur - shift, (dur - c - pose.bone_translation_mm) @ R + c]
    names = ["as imaged", "after centroid alignment", "after rigid fit"]
    fig, axs = plt.subplots(2, 3, figsize=(13, 8))
    for j, (b, name) in enumerate(zip(back, names)):
        for row, (p, q) in enumerate([(0, 1), (1, 2)]):
            ax = axs[row, j]
            ax.plot(
                pre_pts[..., p].ravel(),
                pre_pts[..., q].ravel(),
                ".",
                ms=1,
                color="tab:blue",
                label="pre",
            )
            ax.plot(
                b[..., p].ravel(),
                b[..., q].ravel(),
                ".",
                ms=1,
                color="tab:red",
                label="during, mapped back",
            )
            ax.set(xlabel="xyz"[p] + " [mm]", ylabel="xyz"[q] + " [mm]")
            if row == 0:
                ax.set(aspect="equal", title=name)
    axs[0, 0].legend(fontsize=8, markerscale=6)
    e = pose.extra
    fig.suptitle(
        f"{title} — tibia: rotation {np.round(pose.bone_rotation_deg, 3)} deg, translation "
        f"{np.round(pose.bone_translation_mm, 3)} mm; RMS distance {e.get('bone_rms_initial_mm', np.nan):.3f} → "
        f"{e.get('bone_rms_com_mm', np.nan):.3f} → {e.get('bone_rms_final_mm', np.nan):.3f} mm"
    )
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
