"""Verification of the Ogden material point (used by tests/test_material.py and rule verify_material).

Every check compares :mod:`deeptissue.fem.material` with a truth it does not compute itself:
finite differences of its energy (whose values are checked against the independent principal-stretch
energy of :mod:`deeptissue.verification.analytic`), small-strain elasticity, rotated evaluations, and the
analytical homogeneous responses of :mod:`deeptissue.verification.analytic`.

Finite differences: fourth-order central stencils, f'(x) ~ [f(x-2h) - 8 f(x-h) + 8 f(x+h) - f(x+2h)] / (12 h),
truncation error ~ h^4 f^(5) / 30, rounding error ~ 1.5 eps |f| / h. With entries of F of order 1,

* P vs dW/dF and A vs dP/dF use h = 1e-3: truncation ~ 1e-12 relative (f^(5) of lam^5 is 120 lam^0,
  times the 1/30), rounding ~ 1e-13; the errors come out ~ 1e-12. Tolerance 1e-9: three orders above
  the expected error, and far below what a wrong or perturbation-based tangent gives (a naive
  divided difference (tau_a - tau_b)/(lam_a^2 - lam_b^2) at stretches 1e-9 apart is off by
  ~ eps / 1e-9 ~ 1e-7 relative; a stretch perturbation of 1e-6 by ~ 1e-6).
* A vs the mixed second differences of W (the stencil above in both directions) uses h = 2e-3:
  rounding ~ 2 eps |W| / h^2 ~ 1e-10 |W| and truncation ~ 1e-10; tolerance 1e-7.

Derivatives of lam^alpha grow like |alpha|^k, so for |alpha| > 5 both steps shrink by 5/|alpha|
(:func:`fd_steps`), which keeps the truncation error at the alpha = 5 level.

Errors are reported relative to a scale: max |P| (at least mu) for stresses, max |A| for tangents.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd

from ..fem.material import Ogden, ogden_energy, ogden_stress, ogden_stress_tangent
from ..io import atomic_path
from . import analytic

__all__ = [
    "FD_STEP_SECOND",
    "FD_STEP_STRESS",
    "TOL_CONTINUITY",
    "TOL_EXACT",
    "TOL_FD",
    "TOL_FD_SECOND",
    "TOL_HOMOGENEOUS",
    "deformation_cases",
    "fd_gradient",
    "fd_hessian",
    "fd_steps",
    "homogeneous_responses",
    "material_point_checks",
    "plot_homogeneous",
    "random_rotations",
    "run_material_verification",
    "small_strain_tangent",
    "time_material",
]

log = logging.getLogger(__name__)

FD_STEP_STRESS = 1e-3
FD_STEP_SECOND = 2e-3
TOL_FD = 1e-9
TOL_FD_SECOND = 1e-7
TOL_EXACT = 1e-12  # identities that hold to rounding (objectivity, symmetry, closed forms)
TOL_HOMOGENEOUS = 1e-10
TOL_CONTINUITY = 2e-8

_OFFSETS = np.array([-2.0, -1.0, 1.0, 2.0])
_WEIGHTS = np.array([1.0, -8.0, 8.0, -1.0]) / 12.0


def fd_steps(material: Ogden) -> tuple[float, float]:
    """(step for first differences, step for second differences) of F entries for this material."""
    shrink = min(1.0, 5.0 / abs(material.alpha))
    return FD_STEP_STRESS * shrink, FD_STEP_SECOND * shrink


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3, 3) proper rotations, uniformly distributed (QR of Gaussian matrices)."""
    q, r = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1.0
    return q


def deformation_cases(
    rng: np.random.Generator | None = None, *, n_random: int = 8
) -> dict[str, np.ndarray]:
    """Named sets of deformation gradients (k, 3, 3): general, equal and nearly equal stretches."""
    rng = np.random.default_rng(20261122) if rng is None else rng

    def spectral(stretches):
        """F = R1 diag(stretches) R2^T with random rotations R1, R2: (k, 3, 3) for stretches (k, 3)."""
        stretches = np.asarray(stretches, float)
        k = len(stretches)
        R1, R2 = random_rotations(k, rng), random_rotations(k, rng)
        return np.einsum("nia,na,nja->nij", R1, stretches, R2)

    a = rng.uniform(0.7, 1.4, size=n_random)
    b = rng.uniform(0.7, 1.4, size=n_random)
    general = np.eye(3) + 0.25 * rng.standard_normal((n_random, 3, 3))
    general = general[np.linalg.det(general) > 0.3]
    return {
        "reference F=I": np.eye(3)[None],
        "rigid rotation": random_rotations(3, rng),
        "random F": np.concatenate([general, spectral(rng.uniform(0.6, 1.6, size=(n_random, 3)))]),
        "two equal stretches": spectral(np.stack([a, a, b], axis=1)),
        "three equal stretches": spectral(np.stack([a, a, a], axis=1)),
        "two stretches 1e-9 apart": spectral(np.stack([a, a + 1e-9, b], axis=1)),
        "three stretches 1e-9 apart": spectral(np.stack([a, a + 1e-9, a - 1e-9], axis=1)),
    }


def fd_gradient(fun, F: np.ndarray, h: float) -> np.ndarray:
    """d fun / dF by fourth-order central differences. F (n, 3, 3); fun values (n, *s) -> (n, *s, 3, 3)."""
    n = F.shape[0]
    E = np.eye(9).reshape(9, 3, 3)
    Fp = (
        F[:, None, None] + h * _OFFSETS[None, None, :, None, None] * E[None, :, None]
    )  # (n, 9, 4, 3, 3)
    vals = np.asarray(fun(Fp.reshape(-1, 3, 3)))
    vals = vals.reshape((n, 9, 4) + vals.shape[1:])
    d = np.einsum("nkm...,m->n...k", vals, _WEIGHTS) / h  # (n, *s, 9)
    return d.reshape(d.shape[:-1] + (3, 3))


def fd_hessian(energy, F: np.ndarray, h: float) -> np.ndarray:
    """d^2 energy / dF dF by the tensor product of two fourth-order central stencils -> (n, 3, 3, 3, 3)."""
    n = F.shape[0]
    E = np.eye(9).reshape(9, 3, 3)
    shift = h * _OFFSETS[:, None, None, None] * E[None]  # (4, 9, 3, 3): offset m along direction p
    Fp = (
        F[:, None, None, None, None]
        + shift[None, :, :, None, None]
        + shift[None, None, None, :, :]
    )
    W = energy(Fp.reshape(-1, 3, 3)).reshape(n, 4, 9, 4, 9)
    H = np.einsum("napbq,a,b->npq", W, _WEIGHTS, _WEIGHTS) / h**2
    return H.reshape(n, 3, 3, 3, 3)


def _row(case, quantity, err, tol):
    return {
        "case": case,
        "quantity": quantity,
        "max_error": float(err),
        "tolerance": float(tol),
        "pass": bool(err <= tol),
    }


def _rel(a, b, scale):
    return float(np.max(np.abs(a - b)) / scale)


def small_strain_tangent(material: Ogden) -> np.ndarray:
    """Isotropic small-strain elasticity (3, 3, 3, 3) [MPa] with shear modulus mu and bulk modulus 2/D."""
    d = np.eye(3)
    K, mu = material.bulk_mpa, material.mu_mpa
    dd = np.einsum("ij,kl->ijkl", d, d)
    return K * dd + mu * (
        np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d) - 2.0 / 3.0 * dd
    )


def _reference_rows(material: Ogden, sets: dict) -> list:
    """The reference state F = I and a rigid rotation: no energy, no stress, the small-strain tangent."""
    mu = material.mu_mpa
    W0, P0, A0 = ogden_stress_tangent(np.eye(3), material)
    C0 = small_strain_tangent(material)
    Wr, Pr, _ = ogden_stress_tangent(sets["rigid rotation"], material)
    return [
        _row("reference F=I", "|W| / mu", abs(W0) / mu, TOL_EXACT),
        _row("reference F=I", "|P| / mu", np.max(np.abs(P0)) / mu, TOL_EXACT),
        _row(
            "reference F=I",
            "A vs small-strain elasticity (mu, K=2/D)",
            _rel(A0, C0, np.max(np.abs(C0))),
            TOL_EXACT,
        ),
        _row(
            "rigid rotation",
            "|W|, |P| / mu",
            max(np.max(np.abs(Wr)), np.max(np.abs(Pr))) / mu,
            TOL_EXACT,
        ),
    ]


def _energy_rows(material: Ogden, sets: dict) -> list:
    """W against the independent principal-stretch form (singular values by SVD)."""
    allF = np.concatenate(list(sets.values()))
    sv = np.linalg.svd(allF, compute_uv=False)
    W_ref = np.array([analytic.principal_energy(*s, material) for s in sv])
    return [
        _row(
            "all",
            "W vs principal-stretch energy (analytic)",
            _rel(ogden_energy(allF, material), W_ref, material.mu_mpa),
            TOL_EXACT,
        )
    ]


def _finite_difference_rows(material: Ogden, sets: dict) -> list:
    """P and A against finite differences of W and P, per case; A's major symmetry."""
    mu = material.mu_mpa
    h1, h2 = fd_steps(material)

    def energy(F):
        return ogden_energy(F, material)

    def stress(F):
        return ogden_stress(F, material)

    rows = []
    for case, F in sets.items():
        W, P, A = ogden_stress_tangent(F, material)
        p_scale = max(np.max(np.abs(P)), mu)
        a_scale = np.max(np.abs(A))
        rows += [
            _row(case, "P vs FD of W", _rel(P, fd_gradient(energy, F, h1), p_scale), TOL_FD),
            _row(case, "A vs FD of P", _rel(A, fd_gradient(stress, F, h1), a_scale), TOL_FD),
            _row(
                case,
                "A vs second FD of W",
                _rel(A, fd_hessian(energy, F, h2), a_scale),
                TOL_FD_SECOND,
            ),
            _row(
                case,
                "A major symmetry A[iJkL] - A[kLiJ]",
                _rel(A, A.transpose(0, 3, 4, 1, 2), a_scale),
                TOL_EXACT,
            ),
            # W and P(F) agree with the combined call
            _row(
                case,
                "ogden_energy/ogden_stress vs ogden_stress_tangent",
                max(_rel(energy(F), W, mu), _rel(stress(F), P, p_scale)),
                TOL_EXACT,
            ),
        ]
    return rows


def _coalescence_rows(material: Ogden, sets: dict) -> list:
    """Continuity across coalescence: nearly equal principal stretches against exactly equal ones."""
    F_eq = sets["two equal stretches"]
    U, s, Vt = np.linalg.svd(F_eq)
    s_near = s.copy()
    # the two equal singular values are adjacent after sorting; split the pair by 1e-9
    pair = np.argmin(np.abs(np.diff(s, axis=1)), axis=1)
    s_near[np.arange(len(s)), pair] += 1e-9
    F_near = np.einsum("nia,na,naj->nij", U, s_near, Vt)
    _, P_eq, A_eq = ogden_stress_tangent(F_eq, material)
    _, P_ne, A_ne = ogden_stress_tangent(F_near, material)
    # A changes to first order by ~ (|alpha| + 2) 1e-9 / lam relative: tolerance 2e-8 at alpha = 5
    # (a naive divided difference is off by ~1e-7)
    return [
        _row(
            "two equal vs 1e-9 apart",
            "A continuity",
            _rel(A_eq, A_ne, np.max(np.abs(A_eq))),
            TOL_CONTINUITY * (abs(material.alpha) + 2.0) / 7.0,
        )
    ]


def _frame_rows(material: Ogden, sets: dict, rng: np.random.Generator) -> list:
    """Objectivity (F -> QF) and isotropy (F -> FQ) of W, P and A for random rotations Q."""
    mu = material.mu_mpa
    F = sets["random F"]
    Q = random_rotations(len(F), rng)
    W, P, A = ogden_stress_tangent(F, material)
    a_scale, p_scale = np.max(np.abs(A)), max(np.max(np.abs(P)), mu)
    Wq, Pq, Aq = ogden_stress_tangent(np.einsum("nij,njk->nik", Q, F), material)
    Wm, Pm, Am = ogden_stress_tangent(np.einsum("nij,njk->nik", F, Q), material)
    return [
        _row("objectivity F -> QF", "W(QF) - W(F)", _rel(Wq, W, mu), TOL_EXACT),
        _row(
            "objectivity F -> QF",
            "P(QF) - Q P(F)",
            _rel(Pq, np.einsum("nia,naJ->niJ", Q, P), p_scale),
            TOL_EXACT,
        ),
        _row(
            "objectivity F -> QF",
            "A(QF) - Q A(F) Q",
            _rel(Aq, np.einsum("nia,nkb,naJbL->niJkL", Q, Q, A), a_scale),
            TOL_EXACT,
        ),
        _row("isotropy F -> FQ", "W(FQ) - W(F)", _rel(Wm, W, mu), TOL_EXACT),
        _row(
            "isotropy F -> FQ",
            "P(FQ) - P(F) Q",
            _rel(Pm, np.einsum("niM,nMJ->niJ", P, Q), p_scale),
            TOL_EXACT,
        ),
        _row(
            "isotropy F -> FQ",
            "A(FQ) - A(F) Q Q",
            _rel(Am, np.einsum("niMkN,nMJ,nNL->niJkL", A, Q, Q), a_scale),
            TOL_EXACT,
        ),
    ]


def _inverted_and_homogeneous_rows(material: Ogden) -> list:
    """W = +inf for det F <= 0; the homogeneous responses against their closed forms, summarised."""
    F_inv = np.array([np.diag([1.0, 1.0, -1.0]), np.zeros((3, 3))])
    W_inv = ogden_energy(F_inv, material)
    rows = [
        _row(
            "det F <= 0", "W = +inf (count of violations)", float(np.sum(~np.isposinf(W_inv))), 0.0
        )
    ]
    hom = homogeneous_responses(material)
    for (case, quantity), g in hom.groupby(["case", "quantity"], sort=False):
        scale = max(
            np.max(np.abs(g["analytic"])), 1.0 if "stretch" in quantity else 1e3 * material.mu_mpa
        )
        rows.append(
            _row(
                case,
                f"{quantity} vs analytic",
                np.max(np.abs(g["model"] - g["analytic"])) / scale,
                TOL_HOMOGENEOUS,
            )
        )
    return rows


def material_point_checks(
    material: Ogden, *, rng: np.random.Generator | None = None
) -> pd.DataFrame:
    """All material-point checks as rows: case, quantity, max_error, tolerance, pass."""
    rng = np.random.default_rng(7) if rng is None else rng
    sets = deformation_cases(rng)
    rows = (
        _reference_rows(material, sets)
        + _energy_rows(material, sets)
        + _finite_difference_rows(material, sets)
        + _coalescence_rows(material, sets)
        + _frame_rows(material, sets, rng)
        + _inverted_and_homogeneous_rows(material)
    )
    return pd.DataFrame(rows, columns=["case", "quantity", "max_error", "tolerance", "pass"])


def _traction_free(
    material: Ogden, F: np.ndarray, free: list[int], *, tol: float = 1e-13, max_iter: int = 30
) -> np.ndarray:
    """Solve P[a, a] = 0 for the diagonal entries F[a, a], a in ``free`` (kept equal), by Newton with the model tangent."""
    F = F.copy()
    for _ in range(max_iter):
        _, P, A = ogden_stress_tangent(F, material)
        r = P[free[0], free[0]]
        if abs(r) <= tol * material.mu_mpa:
            return F
        slope = sum(A[free[0], free[0], b, b] for b in free)
        for b in free:
            F[b, b] -= r / slope
    raise RuntimeError(f"traction-free Newton did not converge (residual {r:.3e} MPa)")


def homogeneous_responses(
    material: Ogden,
    *,
    uniaxial_stretches=np.linspace(0.6, 1.6, 21),
    equibiaxial_stretches=np.linspace(0.7, 1.5, 17),
    shears=np.linspace(0.0, 1.0, 21),
) -> pd.DataFrame:
    """Model vs analytic homogeneous responses (long table).

    Columns: case (uniaxial, equibiaxial, simple_shear), x (stretch or amount of shear [-]),
    quantity, model, analytic, abs_error. Stresses in kPa. For uniaxial and equibiaxial loading the
    model's traction-free stretch is found by Newton's method with the model's own tangent.
    """
    rows = []
    for case, xs, free in (
        ("uniaxial", uniaxial_stretches, [1, 2]),
        ("equibiaxial", equibiaxial_stretches, [2]),
    ):
        for x in xs:
            F = np.diag([x, x, 1.0]) if case == "equibiaxial" else np.diag([x, 1.0, 1.0])
            F = _traction_free(material, F, free)
            P = ogden_stress(F, material)
            t_ref, p_ref = (analytic.uniaxial if case == "uniaxial" else analytic.equibiaxial)(
                x, material
            )
            rows.append((case, x, "nominal_stress_kpa", 1e3 * P[0, 0], 1e3 * p_ref))
            rows.append((case, x, "lateral_stretch", F[free[0], free[0]], t_ref))
    for g in shears:
        F = np.eye(3)
        F[0, 1] = g
        P = ogden_stress(F, material)
        sigma = P @ F.T / np.linalg.det(F)
        ref = analytic.simple_shear_cauchy(g, material)
        rows.append(("simple_shear", g, "shear_stress_kpa", 1e3 * sigma[0, 1], 1e3 * ref[0, 1]))
        rows.append(
            (
                "simple_shear",
                g,
                "normal_stress_difference_11_22_kpa",
                1e3 * (sigma[0, 0] - sigma[1, 1]),
                1e3 * (ref[0, 0] - ref[1, 1]),
            )
        )
        rows.append(
            ("simple_shear", g, "normal_stress_33_kpa", 1e3 * sigma[2, 2], 1e3 * ref[2, 2])
        )
    df = pd.DataFrame(rows, columns=["case", "x", "quantity", "model", "analytic"])
    df["abs_error"] = (df["model"] - df["analytic"]).abs()
    return df


def plot_homogeneous(df: pd.DataFrame, path: str | Path) -> None:
    """Nominal stress vs stretch (uniaxial, equibiaxial) and shear stress vs amount of shear."""

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        (
            "uniaxial",
            "nominal_stress_kpa",
            "stretch $\\lambda$",
            "nominal stress $P_{11}$ [kPa]",
            "uniaxial (traction-free sides)",
        ),
        (
            "equibiaxial",
            "nominal_stress_kpa",
            "stretch $\\lambda$",
            "nominal stress $P_{11}$ [kPa]",
            "equibiaxial",
        ),
        (
            "simple_shear",
            "shear_stress_kpa",
            "amount of shear $\\gamma$",
            "shear stress $\\sigma_{12}$ [kPa]",
            "simple shear",
        ),
    ]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    for ax, (case, q, xl, yl, title) in zip(axes, panels):
        g = df[(df["case"] == case) & (df["quantity"] == q)]
        ax.plot(g["x"], g["analytic"], "-", color="0.3", label="analytical (principal stretches)")
        ax.plot(
            g["x"], g["model"], "o", ms=4, mfc="none", color="C0", label="deeptissue.fem.material"
        )
        ax.axhline(0, color="0.8", lw=0.8)
        ax.set(xlabel=xl, ylabel=yl, title=title)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def time_material(
    material: Ogden, *, n_points: int = 100_000, repeats: int = 5, seed: int = 0
) -> pd.DataFrame:
    """Best-of-``repeats`` wall and CPU time of each material function for ``n_points`` random F.

    One process, one thread (numpy element-wise code); CPU time is less sensitive than wall time
    to other jobs sharing the machine. Columns: function, n_points, best_wall_s, best_cpu_s,
    us_per_point (from the wall time).
    """
    rng = np.random.default_rng(seed)
    F = np.eye(3) + 0.2 * rng.standard_normal((n_points, 3, 3))
    F[np.linalg.det(F) <= 0.2] = np.eye(3)
    rows = []
    for fun in (ogden_energy, ogden_stress, ogden_stress_tangent):
        wall = cpu = np.inf
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fun(F, material)
            wall = min(wall, time.perf_counter() - t0)
            cpu = min(cpu, time.process_time() - c0)
        rows.append(
            {
                "function": fun.__name__,
                "n_points": n_points,
                "best_wall_s": wall,
                "best_cpu_s": cpu,
                "us_per_point": 1e6 * wall / n_points,
            }
        )
    return pd.DataFrame(rows)


def _write_csv(df: pd.DataFrame, path) -> None:
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.10g")


def run_material_verification(
    material: Ogden,
    *,
    point_csv,
    homogeneous_csv,
    figure_png,
    speed_csv,
    raise_on_failure: bool = True,
) -> pd.DataFrame:
    """Write the material-point checks, the homogeneous responses and their plot, and the speed table.

    Raises RuntimeError naming the failed checks (after writing the files) if any check fails and
    ``raise_on_failure``; the rule verify_material passes False and leaves the verdict to the summary.
    """
    hom = homogeneous_responses(material)
    _write_csv(hom, homogeneous_csv)
    plot_homogeneous(hom, figure_png)
    checks = material_point_checks(material)
    _write_csv(checks, point_csv)
    speed = time_material(material)
    _write_csv(speed, speed_csv)
    log.info(
        "material %s\n%s\n%s",
        material,
        checks.to_string(index=False),
        speed.to_string(index=False),
    )
    failed = checks[~checks["pass"]]
    if raise_on_failure and len(failed):
        raise RuntimeError(
            "material verification failed: "
            + "; ".join(
                f"{r.case}: {r.quantity} error {r.max_error:.3g} > {r.tolerance:.3g}"
                for r in failed.itertuples()
            )
        )
    return checks
