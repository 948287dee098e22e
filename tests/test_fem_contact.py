"""Frictionless contact (weighted gaps, semi-smooth Newton): derivatives, convergence rate, gaps, forces, release."""

import numpy as np
import pytest

from deeptissue.fem.contact import WeightedContact
from deeptissue.fem.indenters import Indenter
from deeptissue.fem.material import Ogden
from deeptissue.fem.solver import (
    BoneMotion,
    FacetSets,
    IncrementSettings,
    SolverSettings,
    solve_indentation,
)
from deeptissue.mesh import TetMesh
from deeptissue.verification.shapes import block_mesh, cored_cylinder_mesh

LAW = Ogden()
R_MM = 1.5


def _block(size=(6.0, 6.0, 3.0), h_mm=1.5, fine_mm=0.45, fine_radius_mm=1.0):
    m = block_mesh(
        size,
        h_mm=h_mm,
        refine_point_mm=(size[0] / 2, size[1] / 2, size[2]),
        refine_h_mm=fine_mm,
        refine_radius_mm=fine_radius_mm,
        refine_growth=0.5,
    )
    return TetMesh(m.nodes_mm, m.tets, {"bone": m.facets["bottom"], "patch": m.facets["top"]})


def _hertz_N(law, radius_mm, depth_mm):
    # independent of the code under test: small-strain moduli from mu and K = 2 / D of the Ogden law
    K, mu = 2.0 / law.d_mm2_per_n, law.mu_kpa * 1e-3
    E = 9 * K * mu / (3 * K + mu)
    nu = (3 * K - 2 * mu) / (2 * (3 * K + mu))
    return 4.0 / 3.0 * E / (1 - nu**2) * np.sqrt(radius_mm) * depth_mm**1.5


@pytest.fixture(scope="module")
def pressed():
    m = _block()
    ind = Indenter(
        "sphere",
        axis=(0, 0, -1),
        start_mm=(3.0, 3.0, 3.2),
        end_mm=(3.0, 3.0, 2.75),
        radius_mm=R_MM,
    )
    r = solve_indentation(m, material=LAW, indenter=ind, bone_motion=BoneMotion())
    return m, ind, r


def test_converges_superlinearly_near_the_solution(pressed):
    _, _, r = pressed
    assert r.converged, r.reason
    last = [h for h in r.history if h.converged][-1]
    res = np.asarray(last.residuals)
    assert len(res) >= 3
    rates = res[1:] / res[:-1]
    # the last contraction is far stronger than the one before it: the rate goes to zero (superlinear),
    # a linear method keeps a constant rate
    assert rates[-1] < 1e-2
    assert rates[-1] < 0.1 * rates[-2]


def test_few_newton_iterations_per_increment(pressed):
    _, _, r = pressed
    its = [h.iterations for h in r.history if h.converged and h.step == 4]
    assert np.median(its) <= 5


def test_weighted_gaps_closed_and_no_tensile_force(pressed):
    m, ind, r = pressed
    ce = r.extra["contact_entries"]
    gw, lam, h = ce["weighted_gap_mm"], ce["lam_N"], ce["h_mm"]
    tested = np.isfinite(gw)
    assert np.count_nonzero(lam > 0) >= 10
    assert lam.min() >= 0.0
    # no weighted gap closed beyond 0.1 % of the node's facet size; a node carrying force touches the sphere
    # in the weighted sense, a node clear of it carries none
    assert np.all(gw[tested] >= -1e-3 * h[tested])
    assert np.all(np.abs(gw[lam > 0]) <= 1e-3 * h[lam > 0])
    assert np.all(lam[tested & (gw > 1e-3 * h)] == 0.0)
    # between the nodes the quadratic facets follow the sphere to a few per cent of a facet
    assert r.max_penetration_rel < 0.03
    # the force is the sum of the nodal forces, along the axis (frictionless, symmetric)
    f = r.force_on_tissue_N
    assert r.indenter_force_N > 0
    assert np.hypot(f[0], f[1]) < 0.02 * abs(f[2])


def test_a_node_the_indenter_leaves_is_released():
    # the sphere presses in while sliding 2 mm along x: the nodes it touched first are behind it at the end
    m = _block((8.0, 6.0, 3.0), fine_mm=0.6, fine_radius_mm=1.5)
    ind = Indenter(
        "sphere",
        axis=(0, 0, -1),
        start_mm=(3.0, 3.0, 2.95),
        end_mm=(5.0, 3.0, 2.8),
        radius_mm=R_MM,
    )
    r = solve_indentation(
        m,
        material=LAW,
        indenter=ind,
        bone_motion=BoneMotion(),
        settings=SolverSettings(increments=IncrementSettings(max_increment=0.25)),
    )
    assert r.converged, r.reason
    seen = r.extra["active_nodes_per_increment"]
    ever = np.unique(np.concatenate(seen))
    final = seen[-1]
    released = np.setdiff1d(ever, final)
    assert len(released) > 0
    ce = r.extra["contact_entries"]
    gw = dict(zip(ce["nodes"], ce["weighted_gap_mm"]))
    h = dict(zip(ce["nodes"], ce["h_mm"]))
    # released and clear of the sphere (in the weighted sense: no facet around it presses on the sphere)
    assert all(gw[n] > 1e-3 * h[n] for n in released if np.isfinite(gw[n]))
    assert any(np.isfinite(gw[n]) for n in released)


def test_missing_facet_set_raises():
    m = _block()
    ind = Indenter("sphere", axis=(0, 0, -1), start_mm=(3.0, 3.0, 3.2), end_mm=(3.0, 3.0, 2.9))
    with pytest.raises(ValueError, match="no facet set 'nope'"):
        solve_indentation(
            m,
            material=LAW,
            indenter=ind,
            bone_motion=BoneMotion(),
            sets=FacetSets(indenter="nope"),
        )


@pytest.mark.slow
def test_sphere_force_within_3_percent_of_hertz_at_small_depth():
    from deeptissue.verification.scenes import _block_with_top_patch

    d = 0.06  # 0.04 R, the block and mesh of verification.hertz_curve
    m = _block_with_top_patch((40.0, 40.0, 20.0), 6.0, 0.1, 0.4, (20.0, 20.0, 20.0), 0.5)
    ind = Indenter(
        "sphere",
        axis=(0, 0, -1),
        start_mm=(20.0, 20.0, 20.001),
        end_mm=(20.0, 20.0, 20.0 - d),
        radius_mm=R_MM,
    )
    r = solve_indentation(m, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert r.converged, r.reason
    assert r.indenter_force_N == pytest.approx(_hertz_N(LAW, R_MM, d), rel=0.03)


@pytest.mark.parametrize("nodes", [6, 3])
def test_weighted_gap_rows_and_curvature_are_derivatives_of_the_gaps_and_forces(nodes):
    # G = d gw / d u, and the curvature blocks are the derivative of G^T lam at fixed multipliers minus the part
    # that changes G's normals' weights (tested with the gap's own linearisation: G(u + du) - G(u) ~ the blocks)
    limb = cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.2)
    facets = limb.facets["skin"] if nodes == 6 else limb.facets["skin"][:, :3]
    wc = WeightedContact(
        limb.nodes_mm, [("indenter", facets)], np.unique(limb.facets["bone"]), young_mpa=0.01
    )
    ind = Indenter("sphere", axis=(-1, 0, 0), radius_mm=1.5)
    tip = np.array([2.7, 0.0, 3.0])
    wc.gapfns[0] = lambda x, hessian=True: ind.gap(x, tip, hessian=hessian)
    rng = np.random.default_rng(5)
    u = 0.01 * rng.standard_normal(3 * len(limb.nodes_mm))
    which = np.ones(len(wc.node), bool)
    gw0 = wc.weighted(u, which)[0]
    near = np.isfinite(gw0) & (gw0 < 1.0)
    assert np.count_nonzero(near) >= 6 and np.any(gw0[near] < 0)
    lam = np.where(near, 1e-3 * rng.random(len(wc.node)), 0.0)
    gw, G, geo, force = wc.weighted(u, which, lam)
    rows, cols, vals = G
    du = 1e-7 * rng.standard_normal(u.size)
    gp, gm = wc.weighted(u + du, which)[0], wc.weighted(u - du, which)[0]
    ok = np.isfinite(gp) & np.isfinite(gm) & np.isfinite(gw)
    Gdu = np.bincount(rows, weights=vals * du[cols], minlength=len(wc.node))
    np.testing.assert_allclose(((gp - gm) / 2)[ok], Gdu[ok], rtol=1e-5, atol=1e-12)
    # the force is G^T lam
    np.testing.assert_allclose(
        force, np.bincount(cols, weights=vals * lam[rows], minlength=u.size), atol=1e-15
    )
    # d(G^T lam)/du = the curvature blocks + the change of the weights 1/m_j (zero: m_j uses reference areas)
    fp = wc.weighted(u + du, which, lam)[3]
    fm = wc.weighted(u - du, which, lam)[3]
    Kdu = np.zeros(u.size)
    for dofs, blk in geo:
        np.add.at(Kdu, dofs.ravel(), np.einsum("kab,kb->ka", blk, du[dofs]).ravel())
    # the contact force's derivative is -curvature (the blocks carry the sign of the Newton matrix K - ...)
    np.testing.assert_allclose((fp - fm) / 2, -Kdu, atol=1e-4 * np.abs(Kdu).max())


def test_the_augmented_lagrangian_slope_is_its_derivative():
    # the line search's second merit (solver._Problem.lagrangian) and the slope its Armijo test uses: entries on both
    # branches of psi (lam - rho g > 0 and not), a step in u and in the multipliers
    from deeptissue.fem.assembly import Assembler, as_material_law
    from deeptissue.fem.solver import SolverSettings, _Problem

    limb = cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.2)
    bone = np.unique(limb.facets["bone"])
    law = as_material_law(LAW)
    constrained = np.zeros(limb.nodes_mm.size, bool)
    constrained[(3 * bone[:, None] + np.arange(3)).ravel()] = True
    asm = Assembler(limb, law, constrained=constrained)
    wc = WeightedContact(
        limb.nodes_mm, [("indenter", limb.facets["skin"])], bone, young_mpa=law.young_mpa
    )
    ind = Indenter("sphere", axis=(-1, 0, 0), radius_mm=1.5)
    tip = np.array([2.7, 0.0, 3.0])
    wc.gapfns[0] = lambda x, hessian=True: ind.gap(x, tip, hessian=hessian)
    p = _Problem(SolverSettings(), asm, wc, constrained, 1.0)
    rng = np.random.default_rng(7)
    u = np.where(constrained, 0.0, 0.01 * rng.standard_normal(limb.nodes_mm.size))
    gw, G, _, _ = p.weighted(u, np.zeros(len(wc.node)))
    near = np.isfinite(gw) & (gw < 0.5)
    lam = np.where(near, 1e-4 * rng.random(len(wc.node)), 0.0)
    _, f = asm.force(u)
    on = near & (lam - 10.0 * wc.c * gw > 0)
    assert np.count_nonzero(on) >= 3 and np.count_nonzero(near & ~on) >= 3
    du = np.where(constrained, 0.0, 1e-3 * rng.standard_normal(u.size))
    dlam = np.where(near, 1e-5 * rng.standard_normal(len(wc.node)), 0.0)
    eps = 1e-4
    for a, b in (
        (du, 0 * dlam),
        (0 * du, np.where(on, dlam, 0.0)),
        (0 * du, np.where(on, 0.0, dlam)),
        (du, dlam),
    ):
        fd = (
            p.lagrangian(u + eps * a, lam + eps * b) - p.lagrangian(u - eps * a, lam - eps * b)
        ) / (2 * eps)
        assert p.lagrangian_slope(f, gw, G, lam, a, b) == pytest.approx(fd, rel=1e-5)


def _limb_beside_a_sphere():
    """A small cored limb with free nodes, its weighted contact with a sphere clear of the skin, and a solver
    problem on it: (limb, contact, problem)."""
    from deeptissue.fem.assembly import Assembler, as_material_law
    from deeptissue.fem.solver import SolverSettings, _Problem

    limb = cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.2)
    law = as_material_law(LAW)
    constrained = np.zeros(limb.nodes_mm.size, bool)
    asm = Assembler(limb, law, constrained=constrained)
    wc = WeightedContact(
        limb.nodes_mm,
        [("indenter", limb.facets["skin"])],
        np.array([], int),
        young_mpa=law.young_mpa,
    )
    ind = Indenter("sphere", axis=(-1, 0, 0), radius_mm=1.5)
    wc.gapfns[0] = lambda x, hessian=True: ind.gap(x, np.array([9.0, 0.0, 3.0]), hessian=hessian)
    return limb, wc, _Problem(SolverSettings(), asm, wc, constrained, 1.0)


def test_a_newton_step_may_not_crush_an_element_past_a_fraction_of_its_volume():
    # the line search's merits refuse a point whose det F falls below _STEP_DET_FRACTION (0.1) of its value at the
    # step's start: a homogeneous compression to 0.4 of the length (det F 0.064) is refused, to 0.7 (det F 0.34)
    # taken; outside a line search only an inverted point is refused
    from deeptissue.fem.solver import _line_search

    limb, wc, p = _limb_beside_a_sphere()
    u, lam = np.zeros(limb.nodes_mm.size), np.zeros(len(wc.node))
    du = -0.6 * limb.nodes_mm.ravel()  # every length to 0.4: det F = 0.064
    assert np.isfinite(p.merit(u + du, lam))
    with p.step_bound(u) as min_det:
        assert min_det == pytest.approx(1.0)
        assert p.merit(u + du, lam) == np.inf and p.lagrangian(u + du, lam) == np.inf
        assert np.isfinite(p.merit(u + 0.5 * du, lam))
        assert _line_search(p.merit, u, lam, du, 0 * lam, np.inf, -1.0, whole=True) == 0.5
    assert np.isfinite(p.merit(u + du, lam))


def test_an_increment_whose_merit_does_not_fall_is_cut_after_a_few_iterations(monkeypatch):
    # Newton steps that never bring the merit below the increment's start (here each one stretches the limb
    # further) give up after _PROGRESS_ITERATIONS iterations with the reason, not at the iteration limit
    import deeptissue.fem.solver as solver

    limb, wc, p = _limb_beside_a_sphere()
    u, lam = 0.02 * limb.nodes_mm.ravel(), np.zeros(len(wc.node))

    def away(p, lin, du_d, act, curvature=1.0):
        return 0.05 * u, lam.copy()

    def whole(merit, u, lam, du, dlam, ref, slope, whole=False):
        merit(u + du, lam + dlam)
        return 1.0

    monkeypatch.setattr(solver, "_direction", away)
    monkeypatch.setattr(solver, "_line_search", whole)
    ok, why, it, residuals, _ = solver._solve_increment(p, u, lam, np.zeros(0), 1e-6, 1e-9, 1e-3)
    assert not ok and it == solver._PROGRESS_ITERATIONS < p.s.newton.max_iterations
    assert why == f"no progress in {solver._PROGRESS_ITERATIONS} iterations"
    assert residuals[-1] > residuals[0]
