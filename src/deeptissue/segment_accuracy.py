"""Accuracy of a segmentation against a phantom's true contours (rule ``segmentation_accuracy``).

The in-plane distance of every segmented contour point to the true boundary, per slice and structure. It
reads contour files only, so the rule does not import the segmentation's image processing.
"""

from __future__ import annotations

import numpy as np

from .contours import STRUCTURES, Contours, load_contours, point_to_polygon_distance
from .io import atomic_path

__all__ = ["contour_accuracy", "write_accuracy"]


def contour_accuracy(seg: Contours, truth: Contours | dict) -> list[dict]:
    """In-plane distances from segmented points to the true contour, per slice and structure.

    Parameters
    ----------
    seg : Contours
        Segmented contours.
    truth : Contours or dict
        The true contours (each curve taken as the closed polygon through its points), or a dict
        ``structure -> list of (m, 2|3) dense polylines per slice`` [mm].

    Returns
    -------
    list of dict
        Rows ``{slice, structure, mean_mm, max_mm}`` (slice counted in ``seg``); the fibula's only
        on the slices where both the segmentation and the truth have one.
    """
    rows = []
    for st in STRUCTURES:
        segs = getattr(seg, st)
        true = truth.get(st) if isinstance(truth, dict) else getattr(truth, st)
        if segs is None or true is None:
            continue
        for k in range(segs.shape[0]):
            t = np.asarray(true[k], float)
            if not np.isfinite(segs[k]).all() or not np.isfinite(t).all():
                continue  # fibula absent from this slice in the segmentation or the truth
            d = point_to_polygon_distance(segs[k, :, :2], t[:, :2])
            rows.append(
                {"slice": k, "structure": st, "mean_mm": float(d.mean()), "max_mm": float(d.max())}
            )
    return rows


def write_accuracy(contours_path, truth_path, csv_path) -> list[dict]:
    """Write the CSV of :func:`contour_accuracy` (slice, structure, mean_mm, max_mm) of a contour file vs a truth file.

    Parameters
    ----------
    contours_path, truth_path : str or Path
        Contour files (:func:`deeptissue.contours.load_contours`), segmented and true.
    csv_path : str or Path
        Output CSV, distances [mm].

    Returns
    -------
    list of dict
        The rows written.
    """
    import pandas as pd

    rows = contour_accuracy(load_contours(contours_path), load_contours(truth_path))
    with atomic_path(csv_path) as tmp:
        pd.DataFrame(rows).to_csv(tmp, index=False, float_format="%.5f")
    return rows
