"""FE core solver: patch test, rigid bone motion, contact derivatives, indentation and cast contact."""

from dataclasses import replace

import numpy as np
import pytest
from deeptissue.fem.assembly import as_material_law
from deeptissue.fem.cast import Cast
from deeptissue.fem.contact import ContactSurface
from deeptissue.fem.indenters import Indenter
from deeptissue.fem.shapes import block_mesh, cored_cylinder_mesh, distort_interior
from deeptissue.fem.solver import SolverSettings, solve_indentation, solve_prescribed
from deeptissue.mesh import TetMesh
from deeptissue.rigid import BoneMotion, apply_rigid

from deeptissue.fem.material import Ogden

LAW = as_material_law(Ogden())  # mu = 3.65 kPa, alpha = 5, D = 57 mm^2/N


def green_lagrange(F):
    return 0.5 * (np.swapaxes(F, -1, -2) @ F - np.eye(3))


@pytest.mark.parametrize("curved", [False, True])
def test_patch_test_on_distorted_mesh(curved):
    # straight-sided distorted tets are exact with the default 4-point rule; curved P2 tets need
    # degree-3 exactness (cofactor(J) grad N is cubic)
    m = distort_interior(block_mesh((3.0, 2.0, 2.0), h_mm=0.8), amount=0.1 if curved else 0.3, seed=1, curved=curved)
    F0 = np.array([[1.12, 0.05, 0.0], [0.02, 0.93, 0.04], [0.03, 0.0, 1.06]])
    settings = SolverSettings(quadrature_order=3 if curved else 2)
    r = solve_prescribed(m, material=LAW, bc_sets=list(m.facets), displacement_mm=lambda X, s: s * X @ (F0 - np.eye(3)).T,
                         settings=settings)
    assert r.converged, r.reason
    np.testing.assert_allclose(r.displacement_mm, m.nodes_mm @ (F0 - np.eye(3)).T, atol=1e-9)
    np.testing.assert_allclose(r.deformation_gradient, np.broadcast_to(F0, r.deformation_gradient.shape), atol=1e-9)


@pytest.mark.slow
def test_newton_out_of_iterations_within_the_stall_tolerance_keeps_its_best_iterate():
    # a Newton matrix 2.5 x too stiff converges only linearly (error x 0.6 per iteration), like Newton with the
    # contact curvature term dropped: 14 iterations reach the stall tolerance but not rtol
    from deeptissue.fem.assembly import MaterialLaw

    o = Ogden()
    stiff = MaterialLaw(params=o, energy=LAW.energy, stress=LAW.stress,
                        stress_tangent=lambda F, p: (lambda W, P, A: (W, P, 2.5 * A))(*LAW.stress_tangent(F, p)))
    m = block_mesh((2.0, 2.0, 2.0), h_mm=1.0)
    shear = lambda X, t: t * np.stack([0.1 * X[:, 2], 0.0 * X[:, 2], -0.05 * X[:, 2]], axis=1)
    kw = dict(rtol=1e-9, energy_rtol=1e-30, atol_mu_rel=0.0, stall_rtol=1e-2, max_iterations=14,
              initial_increment=1.0, max_increment=1.0, min_increment=0.2, loose_rotation_steps=False)
    exact = solve_prescribed(m, material=LAW, bc_sets=["bottom", "top"], displacement_mm=shear,
                             settings=SolverSettings(**kw))
    assert exact.converged and exact.newton_iterations <= 6  # quadratic
    r = solve_prescribed(m, material=stiff, bc_sets=["bottom", "top"], displacement_mm=shear,
                         settings=SolverSettings(**kw))
    assert r.converged, r.reason
    assert r.increments == 1 and r.newton_iterations == 14
    res = r.history[-1].residuals
    assert res[-1] < 1e-3 * res[0] and all(0.5 * a < b < 0.7 * a for a, b in zip(res[:-1], res[1:]))  # linear, never stalled
    np.testing.assert_allclose(r.displacement_mm, exact.displacement_mm, atol=1e-3 * np.abs(exact.displacement_mm).max())  # stall_rtol 1e-2
    # with a stall tolerance it does not reach, running out of iterations is still a failure
    r = solve_prescribed(m, material=stiff, bc_sets=["bottom", "top"], displacement_mm=shear,
                         settings=SolverSettings(**{**kw, "stall_rtol": 1e-9}))
    assert not r.converged and "too many iterations" in r.reason


@pytest.fixture(scope="module")
def limb():
    return cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.2)


@pytest.mark.parametrize("angle", [15.0, 90.0])
def test_rigid_bone_motion_alone_gives_zero_strain(limb, angle):
    motion = BoneMotion(rotation_deg=tuple(angle * np.array([0.6, -0.48, 0.64])), centre_mm=(0.5, -0.2, 3.0),
                        translation_mm=(0.3, -0.4, 0.2))
    r = solve_indentation(limb, material=LAW, indenter=None, bone_motion=motion)
    assert r.converged, r.reason
    moved = apply_rigid(limb.nodes_mm, rotation_deg=motion.rotation_deg, centre_mm=motion.centre_mm,
                        translation_mm=motion.translation_mm)
    np.testing.assert_allclose(limb.nodes_mm + r.displacement_mm, moved, atol=1e-7)
    assert np.abs(green_lagrange(r.deformation_gradient)).max() < 1e-7


@pytest.mark.parametrize("barrier", [False, True])
def test_contact_force_and_tangent_are_derivatives_of_the_contact_potential(limb, barrier):
    surf = ContactSurface(limb.nodes_mm, limb.facets["skin"], order=4)
    ind = Indenter("sphere", axis=(-1, 0, 0), radius_mm=1.5)
    tip = np.array([2.7, 0.0, 3.0])
    gap = lambda x: ind.gap(x, tip)
    rng = np.random.default_rng(5)
    surf.lam[:] = 0.002 * rng.random(surf.lam.shape)
    eps = np.full(surf.n_facets, 0.3)
    u = 0.01 * rng.standard_normal(3 * len(limb.nodes_mm))
    idx = np.arange(surf.n_facets)
    # barrier from 0.05 mm of penetration, limit 0.2 mm: points below its onset, on it, and beyond
    # 0.1985 mm (s < 0.01 s_hat = 0.0015 mm) where it continues as a quadratic
    bar = (np.full((len(idx), 1), 0.05), np.full((len(idx), 1), 0.2), eps[:, None]) if barrier else None
    r = surf.evaluate(u, gap, eps, idx, barrier=bar)
    assert np.count_nonzero(r["pressure"] > 0) > 10
    if barrier:
        pen = -r["gap"]
        assert np.count_nonzero((pen > 0) & (pen < 0.05)) > 5
        assert np.count_nonzero((pen > 0.05) & (pen < 0.1985)) > 5
        assert np.count_nonzero(pen > 0.1985) > 5
        plain = surf.evaluate(u, gap, eps, idx)
        assert r["energy"] > plain["energy"]
        assert np.all(r["pressure"] >= plain["pressure"])
        np.testing.assert_array_equal(r["pressure"][pen < 0.05], plain["pressure"][pen < 0.05])
    du = 1e-7 * rng.standard_normal(u.size)
    ep = surf.evaluate(u + du, gap, eps, idx, barrier=bar)
    em = surf.evaluate(u - du, gap, eps, idx, barrier=bar)
    assert (ep["energy"] - em["energy"]) / 2 == pytest.approx(r["force"] @ du, rel=1e-5)
    df = (ep["force"] - em["force"]) / 2
    dofs = r["dofs"]
    K = r["Kf"] + r["Kf_geo"]
    Kdu = np.bincount(dofs.ravel(), weights=np.einsum("kab,kb->ka", K, du[dofs]).ravel(), minlength=u.size)
    assert np.linalg.norm(df - Kdu) < 1e-4 * np.linalg.norm(Kdu)


def _hertz_force(law, R, d):
    E, K, mu = law.young_mpa, law.bulk_mpa, law.mu_mpa
    nu = (3 * K - 2 * mu) / (2 * (3 * K + mu))
    return 4.0 / 3.0 * E / (1 - nu**2) * np.sqrt(R) * d**1.5


@pytest.mark.slow
def test_sphere_indentation_is_near_hertz_and_penetration_small():
    L, H = 12.0, 6.0
    m = block_mesh((L, L, H), h_mm=2.0, refine_point_mm=(L / 2, L / 2, H), refine_h_mm=0.25, refine_radius_mm=1.0)
    m = TetMesh(m.nodes_mm, m.tets, {"bone": m.facets["bottom"], "patch": m.facets["top"]})
    d = 0.15
    ind = Indenter("sphere", axis=(0, 0, -1), start_mm=(L / 2, L / 2, H + 0.3), end_mm=(L / 2, L / 2, H - d))
    r = solve_indentation(m, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert r.converged, r.reason
    assert r.max_penetration_rel <= 0.01 + 1e-12
    # coarse mesh and finite block: Hertz within 15 % (the verify target checks 3-5 % on a fine mesh)
    assert r.indenter_force_N == pytest.approx(_hertz_force(LAW, 1.5, d), rel=0.15)
    np.testing.assert_allclose(r.force_on_tissue_N[:2], 0.0, atol=0.02 * r.indenter_force_N)


def _cylinder_cast(radius, length, n=64, m=16, hole_centre=None, hole_radius=0.0):
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    z = np.linspace(-1.0, length + 1.0, m)
    v = np.array([[radius * np.cos(a), radius * np.sin(a), zz] for zz in z for a in th])
    tris = []
    for j in range(m - 1):
        for i in range(n):
            a, b = j * n + i, j * n + (i + 1) % n
            tris += [[a, a + n, b], [b, a + n, b + n]]
    tris = np.array(tris)
    if hole_centre is not None:
        c = v[tris].mean(axis=1)
        tris = tris[np.linalg.norm(c - hole_centre, axis=1) > hole_radius]
    return Cast(v, tris)


@pytest.mark.slow
def test_cast_holds_the_skin_when_the_bone_pushes_outward(limb):
    # the bone moves 0.45 mm toward +x; a cast of radius 3.2 mm stops the skin on that side
    cast = _cylinder_cast(3.2, 6.0)
    motion = BoneMotion(translation_mm=(0.45, 0.0, 0.0))
    r = solve_indentation(limb, material=LAW, indenter=None, bone_motion=motion, cast=cast)
    assert r.converged, r.reason
    x = limb.nodes_mm + r.displacement_mm
    skin = np.unique(limb.facets["skin"])
    radial = np.linalg.norm(x[skin, :2], axis=1)
    assert radial.max() < 3.2 + 0.01 * 1.2 * 2  # penetration below ~1 % of the facet size (+ facet chord)
    assert r.cast_force_N[0] < 0  # the cast pushes the tissue back toward -x
    free = solve_indentation(limb, material=LAW, indenter=None, bone_motion=motion)
    assert np.linalg.norm(free.displacement_mm[skin, :2] + limb.nodes_mm[skin, :2], axis=1).max() > 3.3


def test_vtu_output_round_trip(limb, tmp_path):
    import meshio

    from deeptissue.fem.output import write_result_vtu

    motion = BoneMotion(rotation_deg=(0.0, 0.0, 20.0))
    r = solve_indentation(limb, material=LAW, indenter=None, bone_motion=motion)
    write_result_vtu(tmp_path / "r.vtu", limb, r, cell_data={"tag": np.arange(len(limb.tets))})
    back = meshio.read(tmp_path / "r.vtu")
    np.testing.assert_allclose(back.point_data["displacement_mm"], r.displacement_mm)
    np.testing.assert_allclose(back.cell_data["J"][0], 1.0, atol=1e-8)
    # VTK quadratic tet: mid-node 8 is on edge (1, 3), node 9 on edge (2, 3) (curved edges: nearest)
    p, t = back.points, back.cells_dict["tetra10"]
    d = lambda k, a, b: np.linalg.norm(p[t[:, k]] - 0.5 * (p[t[:, a]] + p[t[:, b]]), axis=1)
    assert np.all(d(8, 1, 3) < d(8, 2, 3)) and np.all(d(9, 2, 3) < d(9, 1, 3))


def test_rigid_predictor_is_not_mistaken_for_a_prescribed_increment(limb):
    # the rigid predictor and the Dirichlet target of the bone are computed by different formulas and
    # differ by round-off (~1e-16 mm); taken for a prescribed increment, that difference would switch
    # off the Armijo line search, the descent check and the convergence test of the first Newton
    # iteration of every increment (one wasted, unguarded iteration per increment, in which an
    # indefinite contact tangent could take a full step).
    # A rigid motion of the whole limb is an exact equilibrium: the predictor solves it, so no
    # Newton iteration is needed.
    motion = BoneMotion(rotation_deg=(1.0, -0.5, 0.5), centre_mm=(0.1, -0.2, 3.0), translation_mm=(0.05, -0.1, 0.0))
    r = solve_indentation(limb, material=LAW, indenter=None, bone_motion=motion)
    assert r.converged, r.reason
    assert r.increments >= 4
    assert r.newton_iterations == 0


@pytest.mark.slow
def test_sphere_with_bone_motion_reaches_full_depth_without_cutbacks(limb):
    # bone rotation + translation with 1 mm of sphere indentation: no increment after first touch is
    # cut. This needs the line search in the first iteration of each increment (also when its
    # Dirichlet increment is only round-off) and a contact tangent that is the derivative of the
    # residual: a tangent that is not converges only linearly while the contact set settles, and the
    # increments are cut ("too many iterations", "line search failed").
    motion = BoneMotion(rotation_deg=(1.0, -0.5, 0.5), centre_mm=(0.1, -0.2, 3.0), translation_mm=(0.05, -0.1, 0.0))
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 3.0), end_mm=(1.5, 0.0, 3.0))
    r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=motion)
    assert r.converged, r.reason
    assert r.load_reached == pytest.approx(4.0)
    cut = [(h.t_start, h.t_end, h.reason) for h in r.history if not h.converged]
    assert not cut, cut
    assert r.newton_iterations <= 80
    assert r.indenter_force_N > 0.0


@pytest.mark.slow
def test_state_violating_contact_is_never_accepted(limb):
    # the AL / final-solve fallbacks keep penalty or loosely converged states; one that still
    # penetrates more than penetration_accept x facet size must be cut back, not reported converged
    # (else a state with, e.g., 0.37 mm penetration could be reported converged). A bound below what AL can reach
    # on this coarse limb makes every contact increment fail.
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 3.0), end_mm=(2.6, 0.0, 3.0))
    strict = SolverSettings(penetration_accept=1e-9, min_increment=0.02, max_al_updates=0)
    r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=strict)
    assert not r.converged
    assert "penetration" in r.reason
    assert any("penetration" in h.reason for h in r.history if not h.converged)
    ok = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert ok.converged, ok.reason
    assert ok.max_penetration_rel <= SolverSettings().penetration_accept


def test_penalty_growth_stiffens_only_facets_still_penetrating_and_is_capped():
    from deeptissue.fem.assembly import Assembler
    from deeptissue.fem.solver import _Pair

    m = cored_cylinder_mesh(length_mm=3.0, radius_mm=2.0, core_radius_mm=0.8, h_mm=1.0)
    asm = Assembler(m, Ogden(), constrained=np.zeros(3 * len(m.nodes_mm), bool))
    surf = ContactSurface(m.nodes_mm, m.facets["skin"])
    pair = _Pair("indenter", surf, lambda t: None, 2.0 / surf.h_mm, asm)
    K = surf.n_facets
    cand = np.arange(K)
    gap = np.zeros((K, surf.n_qp))
    gap[0, 2] = -0.05 * surf.h_mm[0]  # 5 % of its size: beyond a 1 % tolerance
    gap[1, 0] = -0.005 * surf.h_mm[1]  # 0.5 %: within it
    out = {"cand": cand, "gap": gap, "h_mm": surf.h_mm}
    assert pair.stiffen(out, 0.01, 3.0, 10.0) == 1
    assert pair.eps[0] == pytest.approx(3 * pair.eps0[0]) and np.array_equal(pair.eps[1:], pair.eps0[1:])
    for _ in range(4):
        pair.stiffen(out, 0.01, 3.0, 10.0)
    assert pair.eps[0] == pytest.approx(10 * pair.eps0[0])  # capped at max_penalty_growth
    assert pair.stiffen(out, 0.01, 3.0, 10.0) == 0  # nothing left to raise


def test_penetration_barrier_is_smooth_convex_and_stiffens_toward_its_limit():
    from deeptissue.fem.contact import _barrier

    s_hat, kappa = 0.07, 0.4
    s = np.linspace(-0.05, 0.1, 3001)  # beyond the limit (s < 0), on the barrier, and past its onset
    b, b1, b2 = _barrier(s, s_hat, kappa)
    assert np.all(np.isfinite(b)) and np.all(b[s >= s_hat] == 0) and np.all(b2 >= 0)
    d = 1e-8
    (bp, b1p, _), (bm, b1m, _) = _barrier(s + d, s_hat, kappa), _barrier(s - d, s_hat, kappa)
    np.testing.assert_allclose((bp - bm) / (2 * d), b1, rtol=1e-5, atol=1e-6 * np.abs(b1).max())
    np.testing.assert_allclose((b1p - b1m) / (2 * d), b2, rtol=1e-5, atol=1e-6 * b2.max())
    on = (s > 0.01 * s_hat) & (s < s_hat)
    assert np.all(np.diff(b[on]) < 0) and np.all(np.diff(b2[on]) < 0)  # stiffer the nearer the limit
    assert b2[np.searchsorted(s, 0.02 * s_hat)] > 500 * kappa  # ~ kappa s_hat^2 / s^2 near it
    with pytest.raises(ValueError, match="barrier_onset_rel"):
        SolverSettings(barrier_onset_rel=0.2, barrier_limit_rel=0.1)


def test_penetration_barrier_bounds_what_a_soft_penalty_lets_through(limb):
    # a penalty 60 x softer than the default, without multiplier updates or growth, lets the sphere sink
    # into the skin by most of a facet; the barrier keeps every point short of its limit
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 3.0), end_mm=(2.0, 0.0, 3.0))
    soft = SolverSettings(penalty_factor=0.5, max_al_updates=0, end_penalty_passes=0, penalty_growth=1.0,
                          penetration_accept=10.0, retry_shift_scales=())
    plain = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=soft)
    walled = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(),
                               settings=replace(soft, barrier_onset_rel=0.03))
    assert plain.converged and walled.converged, (plain.reason, walled.reason)
    assert plain.max_penetration_rel > 0.3
    assert soft.barrier_onset_rel is None and 0.03 < walled.max_penetration_rel < soft.barrier_limit_rel
    assert walled.indenter_force_N > 2 * plain.indenter_force_N  # the skin is pushed, not passed through


@pytest.mark.slow
def test_energy_criterion_is_not_fooled_by_a_predictor_far_beyond_the_barrier(limb):
    # an increment's predictor can leave skin beyond the barrier's limit (a pinched solve, solved first
    # with the barrier), where the barrier's stiff continuation makes the first Newton decrement huge;
    # the energy criterion (decrement below energy_rtol x the first one) then accepts a crushed state
    # far from equilibrium, and the solve spends many iterations getting out of it. decrement_cap
    # bounds that first decrement by the strain energy (off by default: with it the hard case of the
    # bar tilted 30 deg does not converge).
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 3.0), end_mm=(2.0, 0.0, 3.0))
    st = SolverSettings(barrier_onset_rel=0.03, first_touch_mm=0.5, max_increment=0.5, retry_shift_scales=())
    forces = {}
    assert st.decrement_cap is None
    for cap in (None, 10.0):
        r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=replace(st, decrement_cap=cap))
        assert r.converged, (cap, r.reason)
        forces[cap] = [h.indenter_force_N for h in r.history if h.converged and h.step == 4 and h.t_end > h.t_start]
    assert max(forces[None]) > 5 * forces[None][-1]  # without the cap: an intermediate state far from equilibrium
    capped = forces[10.0]
    assert all(a <= b for a, b in zip(capped[:-1], capped[1:]))  # with it: the force grows with the indentation
    assert capped[-1] == pytest.approx(forces[None][-1], rel=0.05)


@pytest.mark.slow
def test_indenter_starting_inside_the_skin_is_backed_off_and_reaches_the_same_end_state(limb):
    # a bar tilted 30 deg whose axis starts 0.8 mm clear still dips its lower end 0.3 mm into the skin
    # (the hard case "bar tilted 30 deg" starts 1.3 mm deep): the solver moves the start back along
    # the axis until the skin is start_clearance_mm clear; the end state does not depend on the path
    a = np.radians(30.0)
    axis = np.array([-np.cos(a), 0.0, np.sin(a)])
    end = np.array([2.7, 0.0, 3.0])
    ind = Indenter("bar", axis=tuple(axis), start_mm=tuple(end - 0.8 * axis), end_mm=tuple(end), bar_length_mm=5.0)
    skin = limb.nodes_mm[np.unique(limb.facets["skin"].ravel())]
    assert ind.gap(skin, ind.tip_at(0.0))[0].min() < -0.2
    r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert r.converged, r.reason
    back = r.extra["start_backoff_mm"]
    assert back > 0.3
    clear = ind.gap(skin, ind.tip_at(0.0) - back * axis)[0].min()
    assert clear > 0.5 * SolverSettings().start_clearance_mm
    # the same end state as the solve that starts inside (it converges on this small limb)
    inside = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(),
                               settings=SolverSettings(start_clearance_mm=-10.0))
    assert inside.extra["start_backoff_mm"] == 0.0
    assert r.indenter_force_N == pytest.approx(inside.indenter_force_N, rel=1e-3)
    # a start that is clear is left alone
    clear_ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 3.0), end_mm=(2.9, 0.0, 3.0))
    assert solve_indentation(limb, material=LAW, indenter=clear_ind, bone_motion=BoneMotion()).extra["start_backoff_mm"] == 0.0


def test_wall_time_budget_ends_the_solve_unconverged_with_its_reason(limb):
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(2.5, 0.0, 3.0))
    r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(),
                          settings=SolverSettings(max_wall_s=1e-6))
    assert not r.converged
    assert "wall-time budget" in r.reason
    assert r.load_reached < 4.0


def test_unconverged_solve_is_retried_once_with_shifts_and_reports_both_tries(limb, caplog):
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(2.5, 0.0, 3.0))
    few = SolverSettings(max_increments=2)
    with caplog.at_level("WARNING", logger="deeptissue.fem.solver"):
        r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=few)
    assert "diagonal shifts (0.1,), up to 30 iterations per increment and the penetration barrier from 0.03" in caplog.text
    assert not r.converged and r.extra["attempts"] == 2
    assert "more than 2 increments" in r.extra["first_attempt_reason"] and "the other try" in r.reason
    # the retry solves with the shifts and the penetration barrier (the best try reports which it had)
    assert r.extra["barrier_onset_rel"] == (few.retry_barrier_onset_rel if r.extra["shifted"] else None)
    assert r.newton_iterations > r.extra["first_attempt_iterations"] > 0
    once = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(),
                             settings=replace(few, retry_shift_scales=()))
    assert not once.converged and once.extra["attempts"] == 1
    assert once.newton_iterations == r.extra["first_attempt_iterations"]  # the first try is the plain solve


def test_indenter_ending_inside_the_bone_is_reported_infeasible_without_solving(limb):
    # the limb's rigid core has radius 0.8 mm about the z axis: a sphere (R 1.5 mm) whose tip ends at
    # x = 0.6 reaches 0.2 mm into it (less at the core's nodes, which are not all on the tip's line)
    deep = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(0.6, 0.0, 3.0))
    r = solve_indentation(limb, material=LAW, indenter=deep, bone_motion=BoneMotion())
    assert not r.converged and r.reason.startswith("infeasible") and r.extra["infeasible"]
    assert -0.2 - 1e-9 <= r.extra["bone_clearance_mm"] < -0.1
    assert r.newton_iterations == 0 and r.extra["attempts"] == 1  # neither solved nor retried
    # a clear end is solved, and its clearance reported
    ok_ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(2.9, 0.0, 3.0))
    ok = solve_indentation(limb, material=LAW, indenter=ok_ind, bone_motion=BoneMotion())
    assert ok.converged and 2.1 - 1e-9 <= ok.extra["bone_clearance_mm"] < 2.2


@pytest.mark.slow
def test_end_state_is_solved_again_with_stiffer_facets_until_within_the_penetration_tolerance(limb):
    # multiplier updates that stall (here: switched off) leave the penalty state of the last increment
    # penetrating; the facets concerned are stiffened, and the end state is solved again with them
    tol = SolverSettings().penetration_tol
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(1.8, 0.0, 3.0))
    no_al = SolverSettings(max_al_updates=0, end_penalty_passes=0)
    plain = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=no_al)
    assert plain.converged, plain.reason
    assert plain.max_penetration_rel > 5 * tol
    passes = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(),
                               settings=replace(no_al, end_penalty_passes=3))
    assert passes.converged, passes.reason
    assert passes.max_penetration_rel <= tol
    assert any(h.t_start == h.t_end == 4.0 and h.converged for h in passes.history)
    assert passes.extra["end_passes"] >= 1 and plain.extra["end_passes"] == 0
    default = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert default.converged and default.max_penetration_rel <= tol
    # the force follows the contact constraint: 12 % low at 8 % penetration, within 1 % once it is met
    assert passes.indenter_force_N == pytest.approx(default.indenter_force_N, rel=1e-2)
    assert plain.indenter_force_N < 0.95 * default.indenter_force_N


def test_end_passes_never_cost_a_converged_solve_its_convergence(limb):
    # the end state is reached and converged; the budget runs out before or during the end passes
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(1.8, 0.0, 3.0))
    no_al = SolverSettings(max_al_updates=0)
    full = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=no_al)
    passes = [h for h in full.history if h.t_start == h.t_end == 4.0]
    assert full.converged and passes
    n_before = len(full.history) - len(passes)
    capped = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(),
                               settings=replace(no_al, max_increments=n_before))
    assert capped.converged, capped.reason
    assert capped.load_reached == pytest.approx(4.0)
    assert capped.max_penetration_rel > full.max_penetration_rel


@pytest.mark.slow
def test_pinched_solve_starts_with_the_retry_settings_and_falls_back_to_plain(limb, caplog):
    # the sphere's tip ends at x = 1.6: 0.8 mm from the rigid core (radius 0.8 mm about z)
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(1.6, 0.0, 3.0))
    pinch = SolverSettings(pinch_clearance_mm=1.0)
    with caplog.at_level("INFO", logger="deeptissue.fem.solver"):
        r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=pinch)
    assert 0.7 < r.extra["bone_clearance_mm"] < 1.0
    assert "solving first with the retry's settings (diagonal shifts (0.1,)" in caplog.text
    assert r.converged and r.extra["attempts"] == 1
    assert r.extra["pinch_first"] and r.extra["shifted"] and r.extra["barrier_onset_rel"] == pinch.retry_barrier_onset_rel
    assert r.extra["linear_precision"] == "double"  # the retry's settings solve in double precision
    # the default threshold (0.6 mm) solves it plainly first; path independent: the same end state, to
    # within what the 1 % penetration tolerance leaves open (the forces differ by about 0.2 %)
    plain = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert plain.converged and not plain.extra["pinch_first"] and not plain.extra["shifted"]
    assert plain.extra["barrier_onset_rel"] is None and plain.extra["linear_precision"] == "mixed"
    assert r.indenter_force_N == pytest.approx(plain.indenter_force_N, rel=5e-3)
    # mixed precision solves some Newton matrices by conjugate gradients on the last factor; the
    # double-precision try factorises every one
    assert plain.extra["reused"] > 0 and plain.extra["factorisations"] < plain.extra["linear_solves"]
    assert r.extra["reused"] == 0 and r.extra["factorisations"] >= r.extra["linear_solves"]
    every = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(),
                              settings=SolverSettings(linear_reuse_iterations=0))
    assert every.converged and every.extra["reused"] == 0
    assert every.extra["factorisations"] > plain.extra["factorisations"]
    assert plain.indenter_force_N == pytest.approx(every.indenter_force_N, rel=1e-3)
    # a pinched first try that fails is followed by the plain one, which is what it then reports
    caplog.clear()
    few = replace(pinch, max_increments=2)
    with caplog.at_level("WARNING", logger="deeptissue.fem.solver"):
        f = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=few)
    assert "solving again from the start without shifts or barrier" in caplog.text
    assert not f.converged and f.extra["attempts"] == 2 and f.extra["pinch_first"]
    assert "the other try, with" in f.reason or "the other try, without shifts or barrier" in f.reason
    assert f.extra["barrier_onset_rel"] == (few.retry_barrier_onset_rel if f.extra["shifted"] else None)


@pytest.mark.slow
def test_variant_started_from_the_shared_bone_state_takes_the_same_path(limb, tmp_path):
    # the bone-rotation steps (t 0 -> 3) do not involve the indenter (1 mm clear until its step): solved
    # once per mesh (solve_bone_rotation) they start every variant, which then reports the same path,
    # iterations and answer as a solve of its own (to the linear solver's 1e-10: the first Newton matrix
    # of the indentation step is factorised instead of solved on step 3's factor)
    from deeptissue.fem.solver import load_bone_state, save_bone_state, solve_bone_rotation

    cast = _cylinder_cast(3.2, 6.0, hole_centre=np.array([3.2, 0.0, 3.0]), hole_radius=1.8)
    motion = BoneMotion(rotation_deg=(6.0, -5.0, 4.0), centre_mm=(0.0, 0.0, 3.0), translation_mm=(0.1, 0.0, 0.0))
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.2, 0.0, 3.0), end_mm=(2.3, 0.0, 3.0))
    whole = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=motion, cast=cast)
    assert whole.converged, whole.reason
    rot, state = solve_bone_rotation(limb, material=LAW, bone_motion=motion, cast=cast)
    assert rot.converged and rot.load_reached == 3.0 and state.newton_iterations > 0
    assert np.linalg.norm(rot.cast_force_N) > 0 and state.cast_lam_mpa.shape == state.cast_eps.shape + (6,)  # the cast holds the skin
    save_bone_state(tmp_path / "bone_state.npz", state)
    back = load_bone_state(tmp_path / "bone_state.npz")
    assert back.settings == state.settings and back.history == state.history
    np.testing.assert_array_equal(back.cast_lam_mpa, state.cast_lam_mpa)
    started = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=motion, cast=cast, start=back)
    assert started.converged and started.extra["started_from_bone_state"] and not whole.extra["started_from_bone_state"]
    assert started.newton_iterations == whole.newton_iterations
    assert [(h.t_start, h.t_end, h.iterations) for h in started.history] == [(h.t_start, h.t_end, h.iterations) for h in whole.history]
    np.testing.assert_allclose(started.displacement_mm, whole.displacement_mm, atol=1e-8)
    assert started.indenter_force_N == pytest.approx(whole.indenter_force_N, rel=1e-8)
    # a try with other settings (the retry's, a pinched variant's) solves the rotation itself
    other = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=motion, cast=cast, start=back,
                              settings=SolverSettings(rtol=1e-7))
    assert not other.extra["started_from_bone_state"]
    # a state of another mesh is refused, naming the mismatch; a file that is not a state names the file
    with pytest.raises(ValueError, match="not this mesh's state"):
        solve_indentation(block_mesh((2.0, 2.0, 2.0), h_mm=1.0), material=LAW, indenter=None, bone_motion=motion, start=back)
    (tmp_path / "junk.npz").write_bytes(b"not a state")
    with pytest.raises(ValueError, match="junk.npz: not a bone-state file"):
        load_bone_state(tmp_path / "junk.npz")


@pytest.mark.slow
def test_turned_variant_solved_from_the_base_end_state_reaches_the_same_end_state(limb, tmp_path):
    # hyperelastic and frictionless: the end state does not depend on the path, so a variant whose indenter
    # is the base's turned about the same final tip is solved by turning it from the base's end state
    from deeptissue.fem.solver import end_state, load_end_state, save_end_state, solve_turned
    from deeptissue.rigid import rotation_matrix

    cast = _cylinder_cast(3.2, 6.0, hole_centre=np.array([3.2, 0.0, 3.0]), hole_radius=1.8)
    motion = BoneMotion(rotation_deg=(3.0, 0.0, 0.0), centre_mm=(0.0, 0.0, 3.0), translation_mm=(0.05, 0.0, 0.0))
    end = np.array([2.3, 0.0, 3.0])
    base_ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.2, 0.0, 3.0), end_mm=tuple(end))
    axis = rotation_matrix(np.array([0.0, 15.0, 0.0])) @ np.array([-1.0, 0.0, 0.0])
    turned_ind = replace(base_ind, axis=tuple(axis), start_mm=tuple(end - 1.9 * axis))
    base = solve_indentation(limb, material=LAW, indenter=base_ind, bone_motion=motion, cast=cast)
    direct = solve_indentation(limb, material=LAW, indenter=turned_ind, bone_motion=motion, cast=cast)
    assert base.converged and direct.converged, (base.reason, direct.reason)
    state = end_state(base, limb, indenter=base_ind, bone_motion=motion, settings=SolverSettings())
    save_end_state(tmp_path / "end_state.npz", state)
    back = load_end_state(tmp_path / "end_state.npz")
    assert back.indenter == base_ind and back.bone_motion == motion and back.settings == SolverSettings()
    assert set(back.contact) == {"indenter", "cast"}
    np.testing.assert_array_equal(back.contact["indenter"][1], state.contact["indenter"][1])
    assert np.any(back.contact["indenter"][1] > 0)  # the multipliers carried over
    turned = solve_turned(limb, material=LAW, base=back, indenter=turned_ind, cast=cast)
    assert turned.converged and turned.extra["turned"], turned.reason
    # only the turn was solved: one load step, the tip held at the common final tip
    assert all(h.step == 4 for h in turned.history) and all(np.allclose(h.tip_mm, end) for h in turned.history)
    assert turned.newton_iterations < direct.newton_iterations
    assert turned.indenter_force_N == pytest.approx(direct.indenter_force_N, rel=5e-3)
    np.testing.assert_allclose(turned.force_on_tissue_N, direct.force_on_tissue_N, atol=5e-3 * np.linalg.norm(direct.force_on_tissue_N))
    # the two end states differ by what the contact tolerance leaves open: about the penetration it allows
    # (0.0077 mm at most here, with 0.0079 mm penetration in both and 0.74 mm largest displacement)
    pen = max(turned.max_penetration_mm, direct.max_penetration_mm)
    assert np.max(np.abs(turned.displacement_mm - direct.displacement_mm)) < 2.0 * pen
    # a different end tip or shape is no turn; a state of another mesh is refused; junk names the file
    with pytest.raises(ValueError, match="is not a turn of"):
        solve_turned(limb, material=LAW, base=back, indenter=replace(turned_ind, end_mm=(2.2, 0.0, 3.0)), cast=cast)
    with pytest.raises(ValueError, match="is not a turn of"):
        solve_turned(limb, material=LAW, base=back, indenter=replace(turned_ind, kind="bar"), cast=cast)
    with pytest.raises(ValueError, match="not this mesh's state"):
        solve_turned(block_mesh((2.0, 2.0, 2.0), h_mm=1.0), material=LAW, base=back, indenter=turned_ind)
    (tmp_path / "junk.npz").write_bytes(b"not a state")
    with pytest.raises(ValueError, match="junk.npz: not an end-state file"):
        load_end_state(tmp_path / "junk.npz")
