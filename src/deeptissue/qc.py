"""Quality-control figures of the imaging stage."""

from __future__ import annotations

import numpy as np

from .contours import Contours
from .imaging import Volume
from .io import atomic_path

__all__ = ["plot_segmentation"]


def plot_segmentation(
    vol: Volume,
    contours: Contours,
    path,
    *,
    truth: Contours | None = None,
    accuracy: list[dict] | None = None,
    title: str = "",
) -> None:
    """Every slice of ``vol`` with the skin (red), tibia (green) and fibula (yellow, where found)
    contours; truth dashed (cyan). A slice whose tibia touches the indenter (``bone_hidden``) says that its tibia
    is the pre tibia moved rigidly.

    Drawn in voxel index space (so any affine works), zoomed to the skin contours; the PNG is
    written atomically. With ``accuracy`` rows (see :func:`deeptissue.segment.contour_accuracy`)
    the title carries the mean/max distance to the truth per structure.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = vol.n_slices
    ncol = min(5, n)
    nrow = int(np.ceil(n / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3 * ncol, 3 * nrow), squeeze=False)
    allpts = vol.voxel(contours.skin.reshape(-1, 3))
    lo = np.floor(allpts[:, :2].min(0)) - 8
    hi = np.ceil(allpts[:, :2].max(0)) + 8
    for k, ax in enumerate(axes.ravel()):
        ax.set_axis_off()
        if k >= n:
            continue
        img = vol.data[:, :, k]
        ax.imshow(
            img.T,
            origin="lower",
            cmap="gray",
            vmin=0,
            vmax=float(np.percentile(vol.data, 99.5)),
            interpolation="nearest",
        )
        for name, col in (("skin", "r"), ("bone", "lime"), ("fibula", "yellow")):
            seg = getattr(contours, name)
            if seg is not None and np.isfinite(seg[k]).all():
                c = vol.voxel(seg[k])
                c = np.vstack([c, c[:1]])
                ax.plot(c[:, 0], c[:, 1], "-", color=col, lw=0.8)
                ax.plot(c[0, 0], c[0, 1], "o", color=col, ms=2)
            true = None if truth is None else getattr(truth, name)
            if true is not None and np.isfinite(true[k]).all():
                t = vol.voxel(true[k])
                t = np.vstack([t, t[:1]])
                ax.plot(t[:, 0], t[:, 1], "--", color="cyan", lw=0.6)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        hidden = contours.bone_hidden is not None and contours.bone_hidden[k]
        ax.set_title(
            f"slice {k + vol.index_offset[2]}"
            + (" (tibia at the indenter: from pre)" if hidden else ""),
            fontsize=8,
        )
    sup = title
    if accuracy:
        parts = []
        for st in ("skin", "bone", "fibula"):
            rows = [r for r in accuracy if r["structure"] == st]
            if rows:
                parts.append(
                    f"{st}: mean {np.mean([r['mean_mm'] for r in rows]):.3f} mm, "
                    f"max {np.max([r['max_mm'] for r in rows]):.3f} mm"
                )
        sup += "  |  vs truth  " + "; ".join(parts)
    fig.suptitle(sup, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)
