"""Quality-control figures of the imaging stage."""

from __future__ import annotations

import textwrap

import numpy as np

from .contours import Contours
from .imaging import LegSplit, Volume
from .io import atomic_path

__all__ = ["LEFT_OUT", "plot_segmentation"]

#: the start of a reason in ``failed`` that marks a slice left out at an end of the stack (framed orange), not failed
LEFT_OUT = "left out: "

# structure -> (colour, line width, label): the skin drawn wide enough to see on a bright leg edge
_STYLE = {
    "skin": ("red", 1.4, "skin"),
    "bone": ("lime", 1.1, "tibia"),
    "fibula": ("yellow", 1.1, "fibula"),
}


def _per_slice(contours, n: int) -> dict:
    """``{structure: [(m, 3) world mm or None per slice]}`` of a :class:`Contours` or such a dict."""
    if isinstance(contours, dict):
        return {st: list(contours.get(st) or [None] * n) for st in _STYLE}
    out = {}
    for st in _STYLE:
        arr = getattr(contours, st)
        out[st] = [
            None if arr is None or not np.isfinite(arr[k]).all() else arr[k] for k in range(n)
        ]
    return out


def _draw_split(ax, split: LegSplit, k: int) -> None:
    """The leg split on slice ``k``: the kept leg's outline where it was cut from the body (magenta) and the two
    legs' centres."""
    if split is None or k not in split.parted:
        return
    cut = split.body[:, :, k] & ~split.kept[:, :, k]
    ax.contour(cut.T.astype(float), levels=[0.5], colors="magenta", linewidths=0.9)
    (ci, cj), other = split.centres[k]
    ax.plot([ci], [cj], "+", color="magenta", ms=6)
    ax.plot([other[0]], [other[1]], "x", color="magenta", ms=6)


def _accuracy_title(title: str, accuracy: list[dict] | None) -> str:
    if not accuracy:
        return title
    parts = []
    for st in _STYLE:
        rows = [r for r in accuracy if r["structure"] == st]
        if rows:
            parts.append(
                f"{st}: mean {np.mean([r['mean_mm'] for r in rows]):.3f} mm, "
                f"max {np.max([r['max_mm'] for r in rows]):.3f} mm"
            )
    return title + "  |  vs truth  " + "; ".join(parts)


def plot_segmentation(
    vol: Volume,
    contours,
    path,
    *,
    truth: Contours | None = None,
    accuracy: list[dict] | None = None,
    failed: dict | None = None,
    split: LegSplit | None = None,
    title: str = "",
) -> None:
    """Every slice of ``vol`` with the skin (red), tibia (green) and fibula (yellow, where found) contours, a
    legend; truth dashed (cyan). ``contours`` is a :class:`Contours` or, for a failed run, ``{structure: [(m, 3)
    or None per slice]}``. A slice in ``failed`` (``{slice index in vol: reason}``) has a red frame and its reason
    in the title, an orange one when the reason starts with :data:`LEFT_OUT` (``segmentation.end_slices``); a slice whose tibia touches the indenter (``bone_hidden``) says that its tibia is the pre tibia
    moved rigidly; with ``split`` (:func:`deeptissue.imaging.split_legs`) the cut between touching legs is drawn
    (magenta) with both legs' centres.

    Drawn in voxel index space (so any affine works), zoomed to the skin contours (the whole slice where there
    are none); the PNG is written atomically. With ``accuracy`` rows (see
    :func:`deeptissue.segment_accuracy.contour_accuracy`) the title carries the mean/max distance to the truth per structure.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    n = vol.n_slices
    failed = failed or {}
    segs = _per_slice(contours, n)
    ncol = min(5, n)
    nrow = int(np.ceil(n / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3 * ncol, 3 * nrow + 0.6), squeeze=False)
    skins = [s for s in segs["skin"] if s is not None]
    if skins:
        allpts = vol.voxel(np.vstack(skins))
        lo = np.floor(allpts[:, :2].min(0)) - 8
        hi = np.ceil(allpts[:, :2].max(0)) + 8
    else:
        lo, hi = np.zeros(2), np.array(vol.data.shape[:2], float) - 1
    vmax = float(np.percentile(vol.data, 99.5))
    hidden = contours.bone_hidden if isinstance(contours, Contours) else None
    for k, ax in enumerate(axes.ravel()):
        ax.set_xticks([])
        ax.set_yticks([])
        if k >= n:
            ax.set_axis_off()
            continue
        ax.imshow(vol.data[:, :, k].T, origin="lower", cmap="gray", vmin=0, vmax=vmax)
        for st, (col, lw, _) in _STYLE.items():
            if segs[st][k] is not None:
                c = vol.voxel(segs[st][k])
                c = np.vstack([c, c[:1]])
                ax.plot(c[:, 0], c[:, 1], "-", color=col, lw=lw)
            true = None if truth is None else getattr(truth, st)
            if true is not None and np.isfinite(true[k]).all():
                t = vol.voxel(true[k])
                t = np.vstack([t, t[:1]])
                ax.plot(t[:, 0], t[:, 1], "--", color="cyan", lw=0.6)
        _draw_split(ax, split, k)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        label = f"slice {k + vol.index_offset[2]}"
        if hidden is not None and hidden[k]:
            label += " (tibia at the indenter: from pre)"
        colour = "black"
        if k in failed:
            why = str(failed[k])
            left = why.startswith(LEFT_OUT)
            colour = "darkorange" if left else "red"
            # wrapped to the panel's width: a long reason runs into the next panel's title otherwise
            reason = textwrap.wrap(why.removeprefix(LEFT_OUT), 34, max_lines=3, placeholder=" …")
            label += "\n" + "\n".join([("LEFT OUT" if left else "FAILED") + ":", *reason])
            for side in ax.spines.values():
                side.set_edgecolor(colour)
                side.set_linewidth(3)
        ax.set_title(label, fontsize=7, color=colour)
    handles = [Line2D([], [], color=c, lw=lw, label=lab) for c, lw, lab in _STYLE.values()]
    if truth is not None:
        handles.append(Line2D([], [], color="cyan", ls="--", lw=0.8, label="truth"))
    if split is not None and split.parted:
        handles.append(Line2D([], [], color="magenta", lw=0.9, label="cut between the legs"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    sup = _accuracy_title(title, accuracy)
    n_left = sum(str(why).startswith(LEFT_OUT) for why in failed.values())
    if len(failed) > n_left:
        sup += f"  |  FAILED on {len(failed) - n_left} slice(s), framed red"
    if n_left:
        sup += f"  |  {n_left} slice(s) at the ends left out, framed orange"
    fig.suptitle(sup, fontsize=10)
    # half an inch at the top for the suptitle, which tight_layout does not keep clear of the panels' titles
    fig.tight_layout(rect=(0, 0.04, 1, 1 - 0.5 / fig.get_figheight()))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
