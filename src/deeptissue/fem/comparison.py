"""The two contact formulations side by side on the hard cases (the Snakemake target ``contact_comparison``).

``penalty``: :func:`deeptissue.fem.solver.solve_indentation`, the workflow's solver (penalty and augmented
Lagrangian at the facets' quadrature points); ``exact``:
:func:`deeptissue.fem.exact_contact.solve_indentation_exact` (weighted gaps, semi-smooth Newton). Both with
their default settings and a wall-time budget per case. The cases are those of
:func:`deeptissue.fem.verification.hard_cases` and the scenes that cost most: the sphere ending 0.1 mm from
the bone (pinched), a bar tilted 45 deg, a sphere to 2.5 R and an indenter that starts touching the skin.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from ..io import atomic_path
from ..rigid import BoneMotion
from .exact_contact import ExactContactSettings, solve_indentation_exact
from .shapes import distort_interior
from .solver import SolverSettings, solve_indentation
from .verification import _bar_footprint, _limb_indenter, reference_limb

__all__ = ["CASES", "DEMO_VARIANTS", "FORMULATIONS", "comparison_row", "plot_comparison", "variant_row"]

FORMULATIONS = ("penalty", "exact")


def _coarse():
    # the hard cases' limb: 1.6 mm elements, 0.5 mm where the indenter acts
    return reference_limb(1.6, fine_h_mm=0.5)


def _along_bar(tilt_deg, depth_mm=2.0, h_mm=1.6, fine_h_mm=0.5):
    return reference_limb(h_mm, fine_h_mm=fine_h_mm, fine_at_mm=_bar_footprint(tilt_deg, depth_mm))


def _touching():
    # the sphere's start 0.02 mm inside the skin's radius: the solvers back it off before the first increment
    ind = _limb_indenter("sphere", 0.0, 0.02)
    return replace(ind, start_mm=tuple(np.asarray(ind.end_mm) - 0.02 * ind.unit_axis))


# case name -> (mesh, indenter, bone motion); names are file names of the target's outputs
CASES = {
    "sphere_2R": lambda: (_coarse(), _limb_indenter("sphere", 0.0, 3.0), BoneMotion()),
    "bar_15deg": lambda: (_along_bar(15.0), _limb_indenter("bar", 15.0), BoneMotion()),
    "bar_30deg": lambda: (_along_bar(30.0), _limb_indenter("bar", 30.0), BoneMotion()),
    "bar_30deg_coarse": lambda: (_along_bar(30.0, 2.0, 2.0, 0.7), _limb_indenter("bar", 30.0), BoneMotion()),
    "first_touch": lambda: (_coarse(), _limb_indenter("sphere", 0.0, 0.02), BoneMotion()),
    "distorted_mesh": lambda: (distort_interior(reference_limb(2.2, fine_h_mm=0.7), amount=0.15, seed=3, curved=False),
                               _limb_indenter("sphere", 0.0, 2.0), BoneMotion()),
    "bone_rotation": lambda: (_coarse(), _limb_indenter("sphere", 0.0, 1.5),
                              BoneMotion(rotation_deg=(10.0, 5.0, 15.0), centre_mm=(0, 0, 10.0))),
    # the tip ends 0.1 mm from the 1 mm core of the 5 mm limb
    "pinched_0.1mm": lambda: (_coarse(), _limb_indenter("sphere", 0.0, 3.9), BoneMotion()),
    # 1.5 mm deep: at 2 mm the bar's rounded end would reach into the core
    "bar_45deg": lambda: (_along_bar(45.0, 1.5), _limb_indenter("bar", 45.0, 1.5), BoneMotion()),
    "sphere_2.5R": lambda: (_coarse(), _limb_indenter("sphere", 0.0, 3.75), BoneMotion()),
    "zero_clearance": lambda: (_coarse(), _touching(), BoneMotion()),
}


# demo variants solved from the start with both formulations: the pinched bars cost the workflow's solver most
DEMO_VARIANTS = ("rat01_sphere", "rat01_bar", "rat02_bar")


def _solve(formulation, mesh, *, material, indenter, motion, cast=None, indenter_set="patch", max_wall_s):
    if formulation == "exact":
        return solve_indentation_exact(mesh, material=material, indenter=indenter, bone_motion=motion, cast=cast,
                                       settings=ExactContactSettings(max_wall_s=max_wall_s, indenter_set=indenter_set))
    return solve_indentation(mesh, material=material, indenter=indenter, bone_motion=motion, cast=cast,
                             settings=SolverSettings(max_wall_s=max_wall_s, indenter_set=indenter_set))


def _row(r, wall_s, **keys) -> dict:
    its = [h.iterations for h in r.history if h.converged and h.step == 4]
    return dict(**keys, converged=r.converged, reason=r.reason, load_reached=r.load_reached, increments=r.increments,
                newton_iterations=r.newton_iterations,
                median_newton_per_increment=float(np.median(its)) if its else np.nan,
                indenter_force_N=r.indenter_force_N, max_penetration_rel=r.max_penetration_rel, n_dofs=r.n_dofs,
                wall_s=wall_s)


def variant_row(material, *, mesh, pose, cast, animal: str, variant: str, formulation: str, bar_length_mm: float = 10.0,
                max_wall_s: float = 1800.0) -> dict:
    """One study variant (its model, pose and cast) solved from the start with ``formulation``: the row of
    :func:`comparison_row` plus the VOI [mm^3] and bin percentages of the study's default strain statistics."""
    from ..study import variant_indenter
    from ..summary import summarize_solution

    indenter = variant_indenter(pose, variant, bar_length_mm=bar_length_mm)
    set_name = f"patch_{variant}" if f"patch_{variant}" in mesh.facets else "patch"
    t = time.perf_counter()
    r = _solve(formulation, mesh, material=material, indenter=indenter, motion=pose.bone_motion, cast=cast,
               indenter_set=set_name, max_wall_s=max_wall_s)
    row = _row(r, time.perf_counter() - t, case=f"{animal}_{variant}", formulation=formulation)
    if r.converged:
        summary, _ = summarize_solution(mesh, r.displacement_mm, animal=animal, variant=variant)
        row.update(voi_mm3=summary.voi_mm3, **{f"bins_percent.{k}": v for k, v in summary.bins_percent.items()})
    return row


def comparison_row(material, case: str, formulation: str, *, max_wall_s: float = 900.0) -> dict:
    """Solve ``case`` of :data:`CASES` with ``formulation`` ('penalty' or 'exact'); one row of the table."""
    if case not in CASES:
        raise ValueError(f"contact comparison: unknown case {case!r} (cases: {sorted(CASES)})")
    if formulation not in FORMULATIONS:
        raise ValueError(f"contact comparison: unknown formulation {formulation!r} (one of {FORMULATIONS})")
    mesh, indenter, motion = CASES[case]()
    t = time.perf_counter()
    r = _solve(formulation, mesh, material=material, indenter=indenter, motion=motion, max_wall_s=max_wall_s)
    return _row(r, time.perf_counter() - t, case=case, formulation=formulation)


def plot_comparison(df: pd.DataFrame, path) -> None:
    """Newton iterations and wall time per case, one bar per formulation; a hatched bar did not converge."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(dict.fromkeys(df["case"]))
    fig, axes = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    x = np.arange(len(cases))
    for j, form in enumerate(FORMULATIONS):
        d = df[df["formulation"] == form].set_index("case").reindex(cases)
        for ax, col in zip(axes, ("newton_iterations", "wall_s")):
            bars = ax.bar(x + (j - 0.5) * 0.4, d[col].to_numpy(float), 0.4, label=form)
            for b, ok in zip(bars, d["converged"].fillna(False).astype(bool)):
                if not ok:
                    b.set_hatch("//")
                    b.set_alpha(0.5)
    axes[0].set_ylabel("Newton iterations")
    axes[1].set_ylabel("wall time [s]")
    axes[1].set_xticks(x, cases, rotation=30, ha="right")
    axes[0].legend(title="contact (hatched: not converged)")
    axes[0].set_title("Contact formulations on the hard cases")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
