"""Verification and benchmark cases of the FE core (run by the Snakemake target ``verify``).

Each case function builds its own gmsh geometry, solves and returns a pandas DataFrame; the numbers
are compared with analytical truths (Hertz, rigid motion, homogeneous deformation), never with
the code under test. :func:`verification_summary` turns the CSV files of the ``verify_*`` rules into
one row per check (value, limit, status) and :func:`failed_checks` lists the ones that fail, which
makes the target ``verify`` fail.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd

from ..adapt import AdaptSettings
from ..fem.assembly import as_material_law
from ..fem.indenters import Indenter
from ..fem.solver import (
    IncrementSettings,
    NewtonSettings,
    SolverSettings,
    solve_indentation,
    solve_prescribed,
)
from ..io import atomic_path
from ..mesh import TetMesh
from ..rigid import BoneMotion
from .cylinder import REFERENCE_MESH, CylinderMesh, mesh_convergence
from .shapes import block_mesh, cored_cylinder_mesh, distort_interior

# states inside the load step are recorded as points of a curve: converge them like end states
ACCURATE = NewtonSettings(rtol=1e-7, rtol_intermediate=1e-7)


def small_strain_moduli(material) -> tuple[float, float]:
    """(E [MPa], nu) of the law at F = I: E = 9 K mu / (3 K + mu), nu = (3K - 2mu) / (2 (3K + mu))."""
    law = as_material_law(material)
    K, mu = law.bulk_mpa, law.mu_mpa
    return 9 * K * mu / (3 * K + mu), (3 * K - 2 * mu) / (2 * (3 * K + mu))


def hertz_force_N(material, radius_mm: float, depth_mm) -> np.ndarray:
    """Hertz force of a rigid sphere on an elastic half-space: 4/3 E/(1-nu^2) sqrt(R) d^1.5 [N]."""
    E, nu = small_strain_moduli(material)
    return 4.0 / 3.0 * E / (1 - nu**2) * np.sqrt(radius_mm) * np.asarray(depth_mm, float) ** 1.5


def _block_with_top_patch(size, h, h_fine, r_fine, centre, growth=None):
    m = block_mesh(
        size,
        h_mm=h,
        refine_point_mm=centre,
        refine_h_mm=h_fine,
        refine_radius_mm=r_fine,
        refine_growth=growth,
    )
    return TetMesh(m.nodes_mm, m.tets, {"bone": m.facets["bottom"], "patch": m.facets["top"]})


@dataclass(frozen=True)
class HertzBlock:
    """The block of :func:`hertz_curve` and its mesh: ``block_mm`` (x, y, z) [mm], element size ``h_mm``
    [mm], refined to ``h_fine_mm`` [mm] within ``fine_radius_mm`` [mm] of the first contact point and
    graded at ``growth`` [mm/mm] (the defaults are explained in :func:`hertz_curve`)."""

    block_mm: tuple[float, float, float] = (40.0, 40.0, 20.0)
    h_mm: float = 6.0
    h_fine_mm: float = 0.1
    fine_radius_mm: float = 0.4
    growth: float = 0.5


def hertz_curve(
    material,
    *,
    radius_mm=1.5,
    max_depth_mm=0.15,
    block: HertzBlock = HertzBlock(),
    max_increment=0.25,
    accurate=True,
) -> pd.DataFrame:
    """Sphere (radius R) pressed into the centre of a block whose bottom is fixed.

    Returns depth_mm, force_N, hertz_N, rel_error per converged increment (depth from first touch),
    and attrs n_dofs, wall_s, converged.

    Default block 40 x 40 x 20 mm: at depth 0.1 R the contact radius a = sqrt(R d) = 0.47 mm is
    1/85 of the block width and 1/42 of its depth, so the bonded-layer correction of Hertz
    (Dimitriadis et al. 2002, ~1.0 a/h for nu = 0.45) stays near 2 % at 0.1 R and below 1.5 % at
    0.05 R; 0.1 mm P2 facets within 0.4 mm of the first contact point, growing at 0.5 mm/mm to 6 mm
    (gmsh needs the gentle grading to honour the refinement).
    """
    lx, ly, lz = block.block_mm
    top = (lx / 2, ly / 2, lz)
    m = _block_with_top_patch(
        block.block_mm, block.h_mm, block.h_fine_mm, block.fine_radius_mm, top, block.growth
    )
    ind = Indenter(
        "sphere",
        axis=(0, 0, -1),
        start_mm=(lx / 2, ly / 2, lz + 1e-3),
        end_mm=(lx / 2, ly / 2, lz - max_depth_mm),
        radius_mm=radius_mm,
    )
    st = SolverSettings(
        increments=IncrementSettings(
            max_increment=max_increment,
            initial_increment=max_increment,
            first_touch_mm=max_depth_mm * max_increment,
        ),
        newton=ACCURATE if accurate else NewtonSettings(),
    )
    r = solve_indentation(
        m, material=material, indenter=ind, bone_motion=BoneMotion(), settings=st
    )
    rows = [
        (lz - h.tip_mm[2], h.indenter_force_N) for h in r.history if h.converged and h.step == 4
    ]
    df = pd.DataFrame(rows, columns=["depth_mm", "force_N"])
    df = df[df.depth_mm > 0].reset_index(drop=True)
    df["hertz_N"] = hertz_force_N(material, radius_mm, df.depth_mm)
    df["rel_error"] = df.force_N / df.hertz_N - 1
    df.attrs.update(n_dofs=r.n_dofs, wall_s=r.wall_s, converged=r.converged, reason=r.reason)
    return df


def locking_check(
    material,
    *,
    d_values_mm2_per_n=(57.0, 5.7, 0.57),
    radius_mm=1.5,
    depth_rel=0.1,
    h_fine_mm=0.15,
    fine_radius_mm=0.6,
) -> pd.DataFrame:
    """Does the displacement formulation lock at the study's compressibility? The same Hertz indentation
    (to depth_rel x R, one mesh) for the given D values: a locking element would show a force error
    against Hertz that grows as D -> 0 (nu -> 0.5) on the same mesh.

    Returns d_mm2_per_n, nu, depth_mm, force_N, hertz_N, rel_error, n_dofs, converged.
    """

    rows = []
    for d in d_values_mm2_per_n:
        mat = replace(material, d_mm2_per_n=float(d))
        df = hertz_curve(
            mat,
            radius_mm=radius_mm,
            max_depth_mm=depth_rel * radius_mm,
            block=HertzBlock(h_fine_mm=h_fine_mm, fine_radius_mm=fine_radius_mm),
        )
        cols = ["depth_mm", "force_N", "hertz_N", "rel_error"]
        last = {c: float(df[c].iloc[-1]) if len(df) else np.nan for c in cols}
        rows.append(
            dict(
                d_mm2_per_n=float(d),
                nu=small_strain_moduli(mat)[1],
                **last,
                n_dofs=df.attrs.get("n_dofs"),
                converged=df.attrs.get("converged"),
            )
        )
    return pd.DataFrame(rows)


def rigid_motion_cases(material) -> pd.DataFrame:
    """Bone rotations of 15 and 90 degrees (plus a translation) with free ends: strain must vanish."""
    m = cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.0)
    rows = []
    for angle in (15.0, 90.0):
        motion = BoneMotion(
            rotation_deg=tuple(angle * np.array([0.6, -0.48, 0.64])),
            centre_mm=(0.5, -0.2, 3.0),
            translation_mm=(0.3, -0.4, 0.2),
        )
        r = solve_indentation(m, material=material, indenter=None, bone_motion=motion)
        exact = motion.apply(m.nodes_mm)
        F = r.deformation_gradient
        E = 0.5 * (np.swapaxes(F, -1, -2) @ F - np.eye(3))
        rows.append(
            dict(
                case=f"rigid bone {angle:g} deg",
                converged=r.converged,
                max_abs_green_strain=float(np.abs(E).max()),
                max_position_error_mm=float(np.abs(m.nodes_mm + r.displacement_mm - exact).max()),
            )
        )
    return pd.DataFrame(rows)


def patch_cases(material) -> pd.DataFrame:
    """Homogeneous deformation on distorted meshes (straight-sided and curved P2 tets)."""
    F0 = np.array([[1.12, 0.05, 0.0], [0.02, 0.93, 0.04], [0.03, 0.0, 1.06]])
    rows = []
    for curved in (False, True):
        m = distort_interior(
            block_mesh((3.0, 2.0, 2.0), h_mm=0.8),
            amount=0.1 if curved else 0.3,
            seed=1,
            curved=curved,
        )
        st = SolverSettings(quadrature_order=3 if curved else 2)
        r = solve_prescribed(
            m,
            material=material,
            bc_sets=list(m.facets),
            displacement_mm=lambda X, s: s * X @ (F0 - np.eye(3)).T,
            settings=st,
        )
        rows.append(
            dict(
                case=f"patch test, {'curved' if curved else 'straight'} distorted",
                converged=r.converged,
                max_displacement_error_mm=float(
                    np.abs(r.displacement_mm - m.nodes_mm @ (F0 - np.eye(3)).T).max()
                ),
                max_F_error=float(np.abs(r.deformation_gradient - F0).max()),
            )
        )
    return pd.DataFrame(rows)


def reference_limb(h_mm=1.0, *, fine_h_mm=None, fine_at_mm=(5.0, 0.0, 10.0)) -> TetMesh:
    """The reference limb: 20 mm long cylinder of 10 mm diameter around a 2 mm rigid core.

    fine_h_mm: element size within 2.5 mm of fine_at_mm, a point or a segment (two points).
    """
    kw = (
        {}
        if fine_h_mm is None
        else dict(refine_point_mm=fine_at_mm, refine_h_mm=fine_h_mm, refine_radius_mm=2.5)
    )
    return cored_cylinder_mesh(length_mm=20.0, radius_mm=5.0, core_radius_mm=1.0, h_mm=h_mm, **kw)


def _limb_indenter(kind="sphere", tilt_deg=0.0, depth_mm=2.0) -> Indenter:
    """The indenter of :func:`_indent_limb`: tip ending at (5 - depth, 0, 10), travelling along -x
    tilted by tilt_deg about y (toward +z), starting 0.5 mm clear of the skin; an 8 mm bar."""
    a = np.radians(tilt_deg)
    axis = np.array([-np.cos(a), 0.0, np.sin(a)])  # tilted toward +z about the y axis
    end = np.array([5.0 - depth_mm, 0.0, 10.0])
    start = end - (depth_mm + 0.5) * axis
    return Indenter(
        kind, axis=tuple(axis), start_mm=tuple(start), end_mm=tuple(end), bar_length_mm=8.0
    )


def _bar_footprint(tilt_deg, depth_mm=2.0):
    """The segment swept by the lower line of the tilted bar of :func:`_indent_limb` at its end state:
    the hard-case mesh is refined along it, as the model stage refines along a bar's travel."""
    ind = _limb_indenter("bar", tilt_deg, depth_mm)
    a = np.radians(tilt_deg)
    # ind.bar_direction() in closed form; kept so, because gmsh meshes the 30 deg case differently
    # when the segment's end moves by 2e-16 mm (14 050 against 14 104 nodes)
    along = np.array([np.sin(a), 0.0, np.cos(a)])
    end, half = np.asarray(ind.end_mm), ind.bar_half_length_mm * along
    return (tuple(end - half), tuple(end + half))


def _indent_limb(
    mesh,
    material,
    *,
    kind="sphere",
    tilt_deg=0.0,
    depth_mm=2.0,
    settings=SolverSettings(),
    bone_motion=BoneMotion(),
):
    """Indent the reference limb at (5, 0, 10) along -x, tilted by tilt_deg about y (:func:`_limb_indenter`)."""
    return solve_indentation(
        mesh,
        material=material,
        indenter=_limb_indenter(kind, tilt_deg, depth_mm),
        bone_motion=bone_motion,
        settings=settings,
    )


def _touching_indenter() -> Indenter:
    """The sphere of the first-touch case started 0.02 mm inside the skin: the solver backs it off before the
    first increment (start_clearance_mm)."""
    ind = _limb_indenter("sphere", 0.0, 0.02)
    return replace(ind, start_mm=tuple(np.asarray(ind.end_mm) - 0.02 * ind.unit_axis))


def hard_cases(material, *, max_wall_s: float = 1800.0) -> pd.DataFrame:
    """Cases that must converge with the default settings (no hand tuning); each has a wall-time
    budget of ``max_wall_s`` so that one stuck case cannot hold up the target."""
    # coarse limb (1.6 mm) with 0.5 mm elements where the indenter acts (as the model stage refines the patch)
    coarse = reference_limb(1.6, fine_h_mm=0.5)
    budget = SolverSettings(max_wall_s=max_wall_s)

    # a bar is refined along its footprint (its rounded ends concentrate strain too), not only at its centre
    def along_bar(tilt_deg, h_mm=1.6, fine_h_mm=0.5, depth_mm=2.0):
        return reference_limb(
            h_mm, fine_h_mm=fine_h_mm, fine_at_mm=_bar_footprint(tilt_deg, depth_mm)
        )

    def sphere(depth_mm, mesh=coarse, **kw):
        return lambda: _indent_limb(mesh, material, depth_mm=depth_mm, settings=budget, **kw)

    def bar(tilt_deg, depth_mm=2.0, mesh=None):
        return lambda: _indent_limb(
            mesh or along_bar(tilt_deg, depth_mm=depth_mm),
            material,
            kind="bar",
            tilt_deg=tilt_deg,
            depth_mm=depth_mm,
            settings=budget,
        )

    cases = {
        "sphere to depth 2R (3 mm)": sphere(3.0),
        # 0.25 mm from the 1 mm core of the 5 mm limb
        "sphere to depth 2.5R (3.75 mm)": sphere(3.75),
        # the tip ends 0.1 mm from the core: the tissue pinched between indenter and bone
        "sphere pinched 0.1 mm from the bone": sphere(3.9),
        "bar tilted 15 deg, 2 mm": bar(15.0),
        "bar tilted 30 deg, 2 mm": bar(30.0),
        # the same squeeze on a coarser mesh (19 101 DOFs)
        "bar tilted 30 deg, 2 mm, 2.0 / 0.7 mm mesh": bar(30.0, mesh=along_bar(30.0, 2.0, 0.7)),
        # 1.5 mm deep: at 2 mm the bar's rounded end would reach into the core
        "bar tilted 45 deg, 1.5 mm": bar(45.0, 1.5),
        "first touch (0.02 mm)": sphere(0.02),
        "first touch at zero clearance (start 0.02 mm inside the skin)": lambda: solve_indentation(
            coarse,
            material=material,
            indenter=_touching_indenter(),
            bone_motion=BoneMotion(),
            settings=budget,
        ),
        "coarse distorted mesh, sphere 2 mm": sphere(
            2.0,
            mesh=distort_interior(
                reference_limb(2.2, fine_h_mm=0.7), amount=0.15, seed=3, curved=False
            ),
        ),
        "bone rotation 20 deg + sphere 1.5 mm": sphere(
            1.5, bone_motion=BoneMotion(rotation_deg=(10.0, 5.0, 15.0), centre_mm=(0, 0, 10.0))
        ),
    }
    rows = []
    for name, run in cases.items():
        t = time.perf_counter()
        r = run()
        rows.append(
            dict(
                case=name,
                converged=r.converged,
                reason=r.reason,
                load_reached=r.load_reached,
                increments=r.increments,
                newton_iterations=r.newton_iterations,
                active_set_changes=r.extra.get("active_set_changes"),
                indenter_force_N=r.indenter_force_N,
                max_penetration_rel=r.max_penetration_rel,
                n_dofs=r.n_dofs,
                wall_s=time.perf_counter() - t,
            )
        )
    return pd.DataFrame(rows)


def benchmark(material, *, h_mm=1.0) -> pd.DataFrame:
    """Reference indentation (limb Ø10 mm x 20 mm around a Ø2 mm core, sphere to 2 mm, ~1 mm elements):
    DOFs, load reached, increments, iterations and where the wall time goes."""
    m = reference_limb(h_mm)
    t = time.perf_counter()
    r = _indent_limb(m, material, depth_mm=2.0)
    wall = time.perf_counter() - t
    return pd.DataFrame(
        [
            dict(
                case="reference sphere 2 mm",
                converged=r.converged,
                n_dofs=r.n_dofs,
                n_free_dofs=r.n_free_dofs,
                n_tets=len(m.tets),
                load_reached=r.load_reached,
                increments=r.increments,
                newton_iterations=r.newton_iterations,
                wall_s=wall,
                assembly_s=r.assembly_s,
                linear_solve_s=r.linear_solve_s,
                contact_s=r.contact_s,
                other_s=wall - r.assembly_s - r.linear_solve_s - r.contact_s,
                indenter_force_N=r.indenter_force_N,
            )
        ]
    )


def _write_csv(df: pd.DataFrame, path) -> None:

    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False)


def write_hertz_verification(material, *, hertz_csv, radius_mm=1.5) -> None:
    """Hertz check to depth 0.1 R on the refined 40 x 40 x 20 mm block (hertz_csv: depth_mm, force_N,
    hertz_N, rel_error)."""
    _write_csv(hertz_curve(material, radius_mm=radius_mm, max_depth_mm=0.1 * radius_mm), hertz_csv)


def write_hertz_curve(material, *, hertz_csv, curve_csv, figure_png, radius_mm=1.5) -> None:
    """Force-depth curve to 2 R (coarser mesh) and the plot of both curves against Hertz.

    curve_csv: depth_mm, force_N, hertz_N, rel_error, status ('converged' per converged increment;
    a last row 'not converged: <reason>' at the target depth if the solve stopped short).
    """

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    small = pd.read_csv(hertz_csv)
    big = hertz_curve(
        material,
        radius_mm=radius_mm,
        max_depth_mm=2 * radius_mm,
        block=HertzBlock(h_mm=6.0, h_fine_mm=0.3, fine_radius_mm=1.5, growth=0.5),
        max_increment=0.05,
        accurate=True,
    )
    big["status"] = "converged"
    if not big.attrs.get("converged", False):
        big.loc[len(big)] = dict(
            depth_mm=2 * radius_mm,
            force_N=np.nan,
            hertz_N=float(hertz_force_N(material, radius_mm, 2 * radius_mm)),
            rel_error=np.nan,
            status=f"not converged: {big.attrs.get('reason', '')}",
        )
    _write_csv(big, curve_csv)
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for a, df, title in (
        (ax[0], small, "depth <= 0.1 R (fine mesh)"),
        (ax[1], big.dropna(), "to depth 2 R"),
    ):
        d = np.linspace(0, 2 * radius_mm if df is not small else df.depth_mm.max(), 200)
        a.plot(d, hertz_force_N(material, radius_mm, d), "k-", label="Hertz (small strain)")
        a.plot(df.depth_mm, df.force_N, "o", ms=4, label="FE (Ogden)")
        a.set_xlabel("indentation depth [mm]")
        a.set_ylabel("force [N]")
        a.set_title(title)
        a.legend()
    fig.tight_layout()

    with atomic_path(figure_png) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def write_case_verification(material, *, checks_csv, hard_csv) -> None:
    """Patch tests and rigid bone motion (checks_csv), hard convergence cases (hard_csv)."""
    checks = pd.concat([patch_cases(material), rigid_motion_cases(material)], ignore_index=True)
    _write_csv(checks, checks_csv)
    _write_csv(hard_cases(material), hard_csv)


def write_cylinder_verification(material, *, curve_csv, voi_csv, meshes=None) -> None:
    """The cylinder scene (:mod:`deeptissue.verification.cylinder`) on the default mesh and the reference mesh
    (``meshes``: :class:`~deeptissue.verification.cylinder.CylinderMesh` list, the finest last; default the
    study's 1.6 / 0.8 mm and :data:`~deeptissue.verification.cylinder.REFERENCE_MESH`): curve_csv (mesh,
    depth_mm, force_N, ...), voi_csv (mesh, depth_mm, voi_mm3, voi_err_mm3, bins_percent.*, bins_err_pp.*, ...)."""

    curve, voi = mesh_convergence(
        material, [CylinderMesh(), REFERENCE_MESH] if meshes is None else meshes
    )
    _write_csv(curve, curve_csv)
    _write_csv(voi, voi_csv)


def write_locking_check(material, *, locking_csv) -> None:
    """The u-p decision, measured: :func:`locking_check` at D = 57, 5.7 and 0.57 mm^2/N (locking_csv)."""
    _write_csv(locking_check(material), locking_csv)


def write_benchmark(material, *, benchmark_csv, h_mm=1.0) -> None:
    """Reference indentation benchmark (one row: DOFs, increments, iterations, time split)."""
    _write_csv(benchmark(material, h_mm=h_mm), benchmark_csv)


# --- summary of the verification CSVs -------------------------------------------------------------

SUMMARY_COLUMNS = ["check", "value", "limit", "status", "note"]

# Hertz force error limit [-] at depth <= 0.1 R (hertz.csv, locking.csv): the finite 40 x 40 x 20 mm
# block stiffens the response by about 2 % at 0.1 R (bonded-layer correction, see hertz_curve), so a
# correct solve lies within 3 %; a wrong modulus, a locking element or a missed contact is off by more.
HERTZ_REL_LIMIT = 0.03
# patch tests: a homogeneous deformation is represented exactly, so the error is rounding [mm, -]
PATCH_LIMIT = 1e-9
# rigid bone motion: positions [mm] and Green strain [-] to the solver's tolerance
RIGID_LIMIT = 1e-7
# load parameter of a finished indentation (the solver's load steps run from 0 to 4)
LOAD_DONE = 4.0
# radius of the Hertz sphere of rule verify_hertz and verify_hertz_curve [mm]
HERTZ_RADIUS_MM = 1.5

# Checks that fail on the project's machine for a known reason: status ``known-failure`` instead of
# ``fail`` (a passing check stays ``pass``). Remove an entry once its check passes again.
_PINCH = (
    "open hard case: the tissue pinched against the rigid core stalls in the last increments (active-set "
    "changes without descent; the force stops growing) on the project's machine"
)
KNOWN_FAILURES = {
    "hard case: sphere pinched 0.1 mm from the bone": _PINCH,
    # 0.25 mm from the core: the same crushed element as the pinch (det F 0.06 at stretches 1.19, 1.02, 0.05)
    "hard case: sphere to depth 2.5R (3.75 mm)": (
        "open hard case: the sphere ends 0.25 mm from the rigid core and crushes the element between them "
        "(det F 0.06); the end state's Newton stalls at a fixed active set as in the pinched sphere, at "
        "t = 3.9998 on the project's machine"
    ),
}

# cylinder scene, each fixed mesh and each adaptive run against the finest fixed mesh: the accuracy goal
# of the study's numbers (force within 0.5 % from 0.5 to 3 mm; VOI within 2 % and every bin within 1 pp
# at 1.5, 2 and 3 mm), and the error estimate's goal (the true VOI error within 2 x the estimate)
CYLINDER_FORCE_LIMIT = 0.005
# an adaptive run stops when its own estimates meet the study's goal, so it is held to that goal in truth:
# its force within 2 % (deeptissue.adapt.AdaptSettings); the VOI and bins have the same limits as above
ADAPTIVE_FORCE_LIMIT = AdaptSettings().force_goal_percent / 100
CYLINDER_VOI_LIMIT = 0.02
CYLINDER_BINS_LIMIT_PP = 1.0
ESTIMATE_FACTOR = 2.0

# the default mesh on the cylinder scene misses the goal against the 0.4 mm mesh (the solves converge;
# the finer mesh moves the numbers): the scene asks for a finer mesh than the default
_CYLINDER_MESH_REASON = (
    "the default mesh is too coarse for this scene (the solve converges, the finer mesh "
    "moves the number): what mesh refinement from the error estimate is for"
)
KNOWN_FAILURES.update(
    {
        f"cylinder: 1.6 / 0.8 mm mesh: force at {d:g} mm: |F / F_finest - 1|": _CYLINDER_MESH_REASON
        for d in (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
    }
)
KNOWN_FAILURES.update(
    {
        f"cylinder: 1.6 / 0.8 mm mesh: bins at {d:g} mm: max |p - p_finest| [pp]": _CYLINDER_MESH_REASON
        for d in (1.5, 2.0, 3.0)
    }
)
KNOWN_FAILURES.update(
    {
        f"cylinder: 1.6 / 0.8 mm mesh: VOI at {d:g} mm: |VOI / VOI_finest - 1|": _CYLINDER_MESH_REASON
        for d in (1.5, 2.0)
    }
)

# effectivity of the adaptive passes' own estimates (estimate / true error against the finest fixed mesh):
# the goal is 1 to 3 and never below 0.8 (a little under the error is within the reference's own; above 3 the
# loop refines further than the goal needs). Only where the true error is above what the reference
# resolves: the force 0.1 % (the finest adaptive passes and the 1.2 / 0.4 mm mesh differ by 0.05-0.07 % at
# 2 to 3 mm), the VOI 0.5 % and the bins 0.25 pp (the reference's own VOI estimate is 0.27-0.49 mm³, 1-5 %)
EFFECTIVITY_MIN, EFFECTIVITY_MAX = 0.8, 3.0
KNOWN_FAILURES.update(
    {
        # the contact zone is refined, the elements around it are not: the force's error there does not change
        # between passes (a mesh refined to 0.8 mm outside the reference's 0.4 mm zone moves the reference by
        # 0.05 %, the adaptive pass 2 is 0.41 % above both)
        "cylinder: adaptive mesh: force estimate at 1 mm: estimate / true error": (
            "under-estimate: the force's estimate extrapolates the change that refining the contact zone "
            "makes; at 1 mm the error left (0.4 %) lies in the unrefined elements around the zone and does "
            "not change between passes (within the 2 % goal)"
        ),
        # a true error of 0.11 % is within 0.06 % of what the reference resolves: the effectivity is 3 to 9
        "cylinder: adaptive mesh: force estimate at 2.5 mm: estimate / true error": (
            "over-estimate near the reference's resolution: a true error of 0.11 % against a reference that "
            "a finer bulk moves by 0.05 %"
        ),
    }
)
_EFFECTIVITY_FLOORS = {
    "force": ("est_force_percent", "true_force_percent", 0.1, "%"),
    "VOI": ("est_voi_percent", "true_voi_percent", 0.5, "%"),
    "bins": ("est_bins_pp", "true_bins_pp", 0.25, "pp"),
}
_HOMOGENEOUS_CASES = ("uniaxial", "equibiaxial", "simple_shear")


def _check(check, value, limit, ok, note=""):
    return dict(check=check, value=float(value), limit=float(limit), ok=bool(ok), note=note)


def _material_checks(points: pd.DataFrame) -> list[dict]:
    """Rows of material_point.csv (case, quantity, max_error, tolerance): error <= tolerance. The rows
    of the uniaxial, equibiaxial and simple-shear cases are the homogeneous responses of
    homogeneous.csv, reduced to the largest error relative to the response's scale."""
    rows = []
    for r in points.itertuples(index=False):
        group = "homogeneous" if r.case in _HOMOGENEOUS_CASES else "material point"
        rows.append(
            _check(
                f"{group}: {r.case}: {r.quantity}",
                r.max_error,
                r.tolerance,
                r.max_error <= r.tolerance,
                "relative error <= limit",
            )
        )
    return rows


def _hertz_checks(hertz: pd.DataFrame, radius_mm: float) -> list[dict]:
    """hertz.csv: the solve reaches 0.1 R, and |F / F_Hertz - 1| <= HERTZ_REL_LIMIT at every increment."""
    depth = float(hertz["depth_mm"].max()) if len(hertz) else 0.0
    target = 0.1 * radius_mm
    err = float(hertz["rel_error"].abs().max()) if len(hertz) else np.nan
    return [
        _check(
            "Hertz: depth reached [mm]",
            depth,
            target,
            depth >= target * (1 - 1e-9),
            "depth >= limit (0.1 R)",
        ),
        _check(
            "Hertz: max |F / F_Hertz - 1| to 0.1 R",
            err,
            HERTZ_REL_LIMIT,
            err <= HERTZ_REL_LIMIT,
            f"{len(hertz)} increments; value <= limit",
        ),
    ]


def _hertz_curve_checks(curve: pd.DataFrame, radius_mm: float) -> list[dict]:
    """hertz_curve.csv: the force-depth curve reaches 2 R (no 'not converged' row). Its force falls
    below small-strain Hertz as the depth grows (finite strain), so only convergence is checked."""
    done = curve["status"] == "converged"
    depth = float(curve.loc[done, "depth_mm"].max()) if done.any() else 0.0
    stopped = curve.loc[~done, "status"]
    note = str(stopped.iloc[-1]) if len(stopped) else "converged to depth 2 R"
    return [
        _check("Hertz curve: depth reached [mm]", depth, 2 * radius_mm, not len(stopped), note)
    ]


def _locking_checks(locking: pd.DataFrame) -> list[dict]:
    """locking.csv: the Hertz force error at 0.1 R stays within HERTZ_REL_LIMIT for every D."""
    rows = []
    for r in locking.itertuples(index=False):
        err = abs(r.rel_error)
        note = f"nu = {r.nu:.4f}; value <= limit" + ("" if r.converged else "; not converged")
        rows.append(
            _check(
                f"locking: D = {r.d_mm2_per_n:g} mm^2/N: |F / F_Hertz - 1|",
                err,
                HERTZ_REL_LIMIT,
                bool(r.converged) and err <= HERTZ_REL_LIMIT,
                note,
            )
        )
    return rows


def _fem_case_checks(checks: pd.DataFrame) -> list[dict]:
    """fem_checks.csv: patch tests exact to rounding, rigid bone motion strain free; each solve converged."""
    limits = dict(
        max_displacement_error_mm=PATCH_LIMIT,
        max_F_error=PATCH_LIMIT,
        max_abs_green_strain=RIGID_LIMIT,
        max_position_error_mm=RIGID_LIMIT,
    )
    rows = []
    for r in checks.to_dict("records"):
        for column, limit in limits.items():
            value = r.get(column, np.nan)
            if pd.isna(value):
                continue
            note = "value <= limit" + ("" if r["converged"] else "; not converged")
            rows.append(
                _check(
                    f"fem check: {r['case']}: {column}",
                    value,
                    limit,
                    bool(r["converged"]) and value <= limit,
                    note,
                )
            )
    return rows


def _solve_checks(df: pd.DataFrame, prefix: str) -> list[dict]:
    """hard_cases.csv or benchmark.csv: each solve converges with the default settings (load parameter 4)."""
    rows = []
    for r in df.to_dict("records"):
        reason = r.get("reason", "")
        note = (
            f"{r['increments']} increments, {r['newton_iterations']} Newton iterations, {r['wall_s']:.0f} s; "
            "value = load parameter reached"
            + ("" if r["converged"] or pd.isna(reason) else f"; {reason}")
        )
        rows.append(
            _check(
                f"{prefix}: {r['case']}",
                r.get("load_reached", np.nan),
                LOAD_DONE,
                r["converged"],
                note,
            )
        )
    return rows


def _cylinder_checks(curve: pd.DataFrame, voi: pd.DataFrame) -> list[dict]:
    """cylinder_curve.csv and cylinder_voi.csv: every mesh but the finest (most DOFs) against the
    finest: |F / F_ref - 1| per curve depth, |VOI / VOI_ref - 1| and the largest bin difference [pp]
    per VOI depth, and the true VOI and largest bin errors over their estimates (voi_err_mm3, the
    largest bins_err_pp)."""
    rows = []
    ref_mesh = curve.loc[curve["n_dofs"].idxmax(), "mesh"]
    ref_c = curve[curve["mesh"] == ref_mesh].set_index("depth_mm")
    ref_v = voi[voi["mesh"] == ref_mesh].set_index("depth_mm")
    bins = [c for c in voi.columns if c.startswith("bins_percent.")]
    for mesh in [m for m in dict.fromkeys(curve["mesh"]) if m != ref_mesh]:
        c = curve[curve["mesh"] == mesh].set_index("depth_mm")
        for d, r in c.iterrows():
            err = abs(r.force_N / ref_c.loc[d, "force_N"] - 1) if d in ref_c.index else np.nan
            ok = bool(r.converged) and np.isfinite(err) and err <= CYLINDER_FORCE_LIMIT
            rows.append(
                _check(
                    f"cylinder: {mesh} mesh: force at {d:g} mm: |F / F_finest - 1|",
                    err,
                    CYLINDER_FORCE_LIMIT,
                    ok,
                    f"finest {ref_mesh}; {r.force_N:.5g} N against {ref_c.loc[d, 'force_N']:.5g} N"
                    if d in ref_c.index
                    else "finest mesh has no solve at this depth",
                )
            )
        v = voi[voi["mesh"] == mesh].set_index("depth_mm")
        for d in ref_v.index:
            if d not in v.index:
                rows.append(
                    _check(
                        f"cylinder: {mesh} mesh: VOI at {d:g} mm: |VOI / VOI_finest - 1|",
                        np.nan,
                        CYLINDER_VOI_LIMIT,
                        False,
                        "not converged",
                    )
                )
                continue
            r, ref = v.loc[d], ref_v.loc[d]
            true = r.voi_mm3 - ref.voi_mm3
            rel = abs(true) / ref.voi_mm3
            note = f"{r.voi_mm3:.3f} mm^3 against {ref.voi_mm3:.3f} mm^3; estimate {r.voi_err_mm3:.3f} mm^3"
            rows.append(
                _check(
                    f"cylinder: {mesh} mesh: VOI at {d:g} mm: |VOI / VOI_finest - 1|",
                    rel,
                    CYLINDER_VOI_LIMIT,
                    rel <= CYLINDER_VOI_LIMIT,
                    note,
                )
            )
            diff = (r[bins] - ref[bins]).abs()
            worst = diff.astype(float).idxmax()
            est = r.get(worst.replace("bins_percent.", "bins_err_pp."), np.nan)
            rows.append(
                _check(
                    f"cylinder: {mesh} mesh: bins at {d:g} mm: max |p - p_finest| [pp]",
                    diff.max(),
                    CYLINDER_BINS_LIMIT_PP,
                    diff.max() <= CYLINDER_BINS_LIMIT_PP,
                    f"largest in bin {worst.split('.', 1)[1]}; estimate {est:.2f} pp",
                )
            )
            ratio = (
                abs(true) / r.voi_err_mm3 if r.voi_err_mm3 > 0 else (0.0 if true == 0 else np.inf)
            )
            rows.append(
                _check(
                    f"cylinder: {mesh} mesh: VOI at {d:g} mm: true error / estimate",
                    ratio,
                    ESTIMATE_FACTOR,
                    ratio <= ESTIMATE_FACTOR,
                    f"true {true:+.3f} mm^3, estimate {r.voi_err_mm3:.3f} mm^3",
                )
            )
            est_b = float(r[[c for c in voi.columns if c.startswith("bins_err_pp.")]].max())
            ratio = diff.max() / est_b if est_b > 0 else (0.0 if diff.max() == 0 else np.inf)
            rows.append(
                _check(
                    f"cylinder: {mesh} mesh: bins at {d:g} mm: largest true error / largest estimate",
                    ratio,
                    ESTIMATE_FACTOR,
                    ratio <= ESTIMATE_FACTOR,
                    f"true {diff.max():.2f} pp, estimate {est_b:.2f} pp",
                )
            )
    return rows


def _cylinder_adaptive_checks(table: pd.DataFrame) -> list[dict]:
    """cylinder_adaptive.csv (:func:`deeptissue.verification.cylinder.adaptive_comparison`): at every depth the
    adaptive run's last pass meets the study's goal by its own estimate, and against the finest fixed
    mesh its force is within ADAPTIVE_FORCE_LIMIT, its VOI within CYLINDER_VOI_LIMIT and its bins within
    CYLINDER_BINS_LIMIT_PP (the VOI and bins at the depths the reference has them)."""
    rows = []
    runs = table[table["kind"] == "adaptive"]
    for d, run in runs.groupby("depth_mm", sort=True):
        last = run.loc[run["pass_index"].idxmax()]
        where = f"pass {int(last['pass_index'])}, {int(last['n_dofs'])} DOFs, {last['wall_s']:.0f} s for all passes"
        met = bool(last["goal_met"])
        rows.append(
            _check(
                f"cylinder: adaptive mesh at {d:g} mm: goal met by its own estimate",
                float(met),
                1.0,
                met,
                f"{where}; stopped on: {last.get('stop_reason', '')}",
            )
        )
        err = abs(last["true_force_percent"]) / 100
        rows.append(
            _check(
                f"cylinder: adaptive mesh: force at {d:g} mm: |F / F_finest - 1|",
                err,
                ADAPTIVE_FORCE_LIMIT,
                err <= ADAPTIVE_FORCE_LIMIT,
                f"{where}; estimate {last['est_force_percent']:.2f} %",
            )
        )
        if np.isfinite(last["true_voi_percent"]):
            rel = abs(last["true_voi_percent"]) / 100
            rows.append(
                _check(
                    f"cylinder: adaptive mesh: VOI at {d:g} mm: |VOI / VOI_finest - 1|",
                    rel,
                    CYLINDER_VOI_LIMIT,
                    rel <= CYLINDER_VOI_LIMIT,
                    f"{where}; estimate {last['est_voi_percent']:.2f} %",
                )
            )
            rows.append(
                _check(
                    f"cylinder: adaptive mesh: bins at {d:g} mm: max |p - p_finest| [pp]",
                    last["true_bins_pp"],
                    CYLINDER_BINS_LIMIT_PP,
                    last["true_bins_pp"] <= CYLINDER_BINS_LIMIT_PP,
                    f"{where}; estimate {last['est_bins_pp']:.2f} pp",
                )
            )
    return rows


def _cylinder_effectivity_checks(table: pd.DataFrame) -> list[dict]:
    """cylinder_adaptive.csv: at every depth and for the force, the VOI and the bins, the effectivity of
    the adaptive run's own estimate (estimate / |true error|) at its most refined pass whose estimate is
    known and whose true error is above the reference's resolution (:data:`_EFFECTIVITY_FLOORS`): within
    [EFFECTIVITY_MIN, EFFECTIVITY_MAX]. A depth where no pass qualifies has no row."""
    rows = []
    runs = table[table["kind"] == "adaptive"]
    for d, run in runs.groupby("depth_mm", sort=True):
        for q, (est_col, true_col, floor, unit) in _EFFECTIVITY_FLOORS.items():
            est, true = run[est_col].astype(float), run[true_col].astype(float).abs()
            ok = run[np.isfinite(est) & (true >= floor)]
            if ok.empty:
                continue
            last = ok.loc[ok["pass_index"].idxmax()]
            eff = float(last[est_col]) / abs(float(last[true_col]))
            rows.append(
                _check(
                    f"cylinder: adaptive mesh: {q} estimate at {d:g} mm: estimate / true error",
                    eff,
                    EFFECTIVITY_MAX,
                    EFFECTIVITY_MIN <= eff <= EFFECTIVITY_MAX,
                    f"goal {EFFECTIVITY_MIN:g} to {EFFECTIVITY_MAX:g}; pass {int(last['pass_index'])}: "
                    f"estimate {float(last[est_col]):.3g} {unit}, true {float(last[true_col]):+.3g} {unit}",
                )
            )
    return rows


@dataclass(frozen=True)
class VerificationTables:
    """The tables the ``verify`` rules write, as :func:`verification_summary` reads them (the fields are
    described there); the cylinder tables are optional."""

    points: pd.DataFrame
    hertz: pd.DataFrame
    curve: pd.DataFrame
    locking: pd.DataFrame
    checks: pd.DataFrame
    hard: pd.DataFrame
    benchmark: pd.DataFrame
    cylinder_curve: pd.DataFrame | None = None
    cylinder_voi: pd.DataFrame | None = None
    cylinder_adaptive: pd.DataFrame | None = None


def verification_summary(
    tables: VerificationTables,
    *,
    radius_mm: float = HERTZ_RADIUS_MM,
    known_failures: dict[str, str] | None = None,
) -> pd.DataFrame:
    """One row per check of the ``verify`` target, from the tables its rules write.

    Parameters
    ----------
    tables : VerificationTables
        The fields below.
    points : DataFrame
        material_point.csv (case, quantity, max_error, tolerance, pass); its uniaxial, equibiaxial
        and simple-shear rows summarise homogeneous.csv.
    hertz, curve : DataFrame
        hertz.csv (depth_mm, force_N, hertz_N, rel_error) and hertz_curve.csv (the same and status).
    locking : DataFrame
        locking.csv (d_mm2_per_n, nu, rel_error, converged, ...).
    checks, hard, benchmark : DataFrame
        fem_checks.csv, hard_cases.csv and benchmark.csv (case, converged, load_reached, ...); the
        benchmark's wall time depends on the machine and is reported in the note, not checked.
    cylinder_curve, cylinder_voi : DataFrame, optional
        cylinder_curve.csv and cylinder_voi.csv (:func:`write_cylinder_verification`): each mesh
        against the finest (:func:`_cylinder_checks`); None: no cylinder rows.
    cylinder_adaptive : DataFrame, optional
        cylinder_adaptive.csv (:func:`deeptissue.verification.cylinder.write_adaptive_cylinder`): the adaptive
        meshes against the finest fixed mesh (:func:`_cylinder_adaptive_checks`) and the effectivity of
        their estimates (:func:`_cylinder_effectivity_checks`); None: no such rows.
    radius_mm : float
        Radius of the Hertz sphere [mm].
    known_failures : dict, optional
        Check name -> reason for checks that fail for a known reason (default :data:`KNOWN_FAILURES`).

    Returns
    -------
    DataFrame
        Columns check, value, limit, status, note; status is ``pass``, ``fail`` or ``known-failure``
        (a failing check named in ``known_failures``, its reason prefixed to the note).
    """
    known = KNOWN_FAILURES if known_failures is None else known_failures
    points, hertz, curve, locking, checks, hard, benchmark = (
        tables.points,
        tables.hertz,
        tables.curve,
        tables.locking,
        tables.checks,
        tables.hard,
        tables.benchmark,
    )
    cylinder_curve, cylinder_voi = tables.cylinder_curve, tables.cylinder_voi
    cylinder_adaptive = tables.cylinder_adaptive
    rows = (
        _material_checks(points)
        + _hertz_checks(hertz, radius_mm)
        + _hertz_curve_checks(curve, radius_mm)
        + _locking_checks(locking)
        + _fem_case_checks(checks)
        + _solve_checks(hard, "hard case")
        + _solve_checks(benchmark, "benchmark")
        + (
            []
            if cylinder_curve is None or cylinder_voi is None
            else _cylinder_checks(cylinder_curve, cylinder_voi)
        )
        + (
            []
            if cylinder_adaptive is None
            else _cylinder_adaptive_checks(cylinder_adaptive)
            + _cylinder_effectivity_checks(cylinder_adaptive)
        )
    )
    for row in rows:
        if row.pop("ok"):
            row["status"] = "pass"
        elif row["check"] in known:
            row["status"] = "known-failure"
            row["note"] = f"{known[row['check']]}; {row['note']}"
        else:
            row["status"] = "fail"
    return pd.DataFrame(rows, columns=SUMMARY_COLUMNS)


def failed_checks(summary: pd.DataFrame) -> list[str]:
    """Names of the checks whose status is ``fail`` (known failures excluded)."""
    return summary.loc[summary["status"] == "fail", "check"].tolist()


@dataclass(frozen=True)
class VerificationCsvs:
    """Paths of the CSVs the ``verify`` rules write, one per field of :class:`VerificationTables`; the
    cylinder rows need both ``cylinder_curve`` and ``cylinder_voi``, the adaptive ones ``cylinder_adaptive``."""

    points: str | Path
    hertz: str | Path
    curve: str | Path
    locking: str | Path
    checks: str | Path
    hard: str | Path
    benchmark: str | Path
    cylinder_curve: str | Path | None = None
    cylinder_voi: str | Path | None = None
    cylinder_adaptive: str | Path | None = None

    def read(self) -> VerificationTables:
        """The tables of these CSVs (no cylinder tables unless both cylinder CSVs are given)."""
        cyl = self.cylinder_curve is not None and self.cylinder_voi is not None
        return VerificationTables(
            points=pd.read_csv(self.points),
            hertz=pd.read_csv(self.hertz),
            curve=pd.read_csv(self.curve),
            locking=pd.read_csv(self.locking),
            checks=pd.read_csv(self.checks),
            hard=pd.read_csv(self.hard),
            benchmark=pd.read_csv(self.benchmark),
            cylinder_curve=pd.read_csv(self.cylinder_curve) if cyl else None,
            cylinder_voi=pd.read_csv(self.cylinder_voi) if cyl else None,
            cylinder_adaptive=None
            if self.cylinder_adaptive is None
            else pd.read_csv(self.cylinder_adaptive),
        )


def write_verification_summary(csvs: VerificationCsvs, summary_csv) -> pd.DataFrame:
    """Read the verification CSVs, write :func:`verification_summary` to summary_csv and return it."""
    summary = verification_summary(csvs.read())
    _write_csv(summary, summary_csv)
    return summary
