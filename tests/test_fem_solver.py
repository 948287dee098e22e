"""FE core solver: patch test, rigid bone motion, indentation, cast contact, bone and end states."""

import logging
import time
from dataclasses import replace

import numpy as np
import pytest

from deeptissue.fem.assembly import as_material_law
from deeptissue.fem.cast import Cast
from deeptissue.fem.indenters import Indenter
from deeptissue.fem.material import Ogden
from deeptissue.fem.solver import (
    IncrementSettings,
    NewtonSettings,
    SolverSettings,
    solve_indentation,
    solve_prescribed,
)
from deeptissue.mesh import TetMesh
from deeptissue.rigid import BoneMotion, apply_rigid
from deeptissue.verification.shapes import block_mesh, cored_cylinder_mesh, distort_interior

LAW = as_material_law(Ogden())  # mu = 3.65 kPa, alpha = 5, D = 57 mm^2/N


def green_lagrange(F):
    return 0.5 * (np.swapaxes(F, -1, -2) @ F - np.eye(3))


@pytest.mark.parametrize("curved", [False, True])
def test_patch_test_on_distorted_mesh(curved):
    # straight-sided distorted tets are exact with the default 4-point rule; curved P2 tets need
    # degree-3 exactness (cofactor(J) grad N is cubic)
    m = distort_interior(
        block_mesh((3.0, 2.0, 2.0), h_mm=0.8), amount=0.1 if curved else 0.3, seed=1, curved=curved
    )
    F0 = np.array([[1.12, 0.05, 0.0], [0.02, 0.93, 0.04], [0.03, 0.0, 1.06]])
    settings = SolverSettings(quadrature_order=3 if curved else 2)
    r = solve_prescribed(
        m,
        material=LAW,
        bc_sets=list(m.facets),
        displacement_mm=lambda X, s: s * X @ (F0 - np.eye(3)).T,
        settings=settings,
    )
    assert r.converged, r.reason
    np.testing.assert_allclose(r.displacement_mm, m.nodes_mm @ (F0 - np.eye(3)).T, atol=1e-9)
    np.testing.assert_allclose(
        r.deformation_gradient, np.broadcast_to(F0, r.deformation_gradient.shape), atol=1e-9
    )


@pytest.fixture(scope="module")
def limb():
    return cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.2)


@pytest.mark.parametrize("angle", [15.0, 90.0])
def test_rigid_bone_motion_alone_gives_zero_strain(limb, angle):
    motion = BoneMotion(
        rotation_deg=tuple(angle * np.array([0.6, -0.48, 0.64])),
        centre_mm=(0.5, -0.2, 3.0),
        translation_mm=(0.3, -0.4, 0.2),
    )
    r = solve_indentation(limb, material=LAW, indenter=None, bone_motion=motion)
    assert r.converged, r.reason
    moved = apply_rigid(
        limb.nodes_mm,
        rotation_deg=motion.rotation_deg,
        centre_mm=motion.centre_mm,
        translation_mm=motion.translation_mm,
    )
    np.testing.assert_allclose(limb.nodes_mm + r.displacement_mm, moved, atol=1e-7)
    assert np.abs(green_lagrange(r.deformation_gradient)).max() < 1e-7


def _hertz_force(law, R, d):
    E, K, mu = law.young_mpa, law.bulk_mpa, law.mu_mpa
    nu = (3 * K - 2 * mu) / (2 * (3 * K + mu))
    return 4.0 / 3.0 * E / (1 - nu**2) * np.sqrt(R) * d**1.5


@pytest.mark.slow
def test_sphere_indentation_is_near_hertz_and_penetration_small():
    L, H = 12.0, 6.0
    m = block_mesh(
        (L, L, H),
        h_mm=2.0,
        refine_point_mm=(L / 2, L / 2, H),
        refine_h_mm=0.25,
        refine_radius_mm=1.0,
    )
    m = TetMesh(m.nodes_mm, m.tets, {"bone": m.facets["bottom"], "patch": m.facets["top"]})
    d = 0.15
    ind = Indenter(
        "sphere", axis=(0, 0, -1), start_mm=(L / 2, L / 2, H + 0.3), end_mm=(L / 2, L / 2, H - d)
    )
    r = solve_indentation(m, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert r.converged, r.reason
    # weighted gaps closed to 0.1 % of a facet; between the nodes the facets follow the sphere to a few per cent
    assert r.extra["node_penetration_rel"] <= 1e-3 + 1e-12 and r.max_penetration_rel < 0.05
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
    assert (
        radial.max() < 3.2 + 0.05 * 1.2 * 2
    )  # penetration between nodes below ~5 % of the facet size (+ facet chord)
    assert r.cast_force_N[0] < 0  # the cast pushes the tissue back toward -x
    free = solve_indentation(limb, material=LAW, indenter=None, bone_motion=motion)
    assert (
        np.linalg.norm(free.displacement_mm[skin, :2] + limb.nodes_mm[skin, :2], axis=1).max()
        > 3.3
    )


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
    motion = BoneMotion(
        rotation_deg=(1.0, -0.5, 0.5), centre_mm=(0.1, -0.2, 3.0), translation_mm=(0.05, -0.1, 0.0)
    )
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
    motion = BoneMotion(
        rotation_deg=(1.0, -0.5, 0.5), centre_mm=(0.1, -0.2, 3.0), translation_mm=(0.05, -0.1, 0.0)
    )
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 3.0), end_mm=(1.5, 0.0, 3.0))
    r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=motion)
    assert r.converged, r.reason
    assert r.load_reached == pytest.approx(4.0)
    cut = [(h.t_start, h.t_end, h.reason) for h in r.history if not h.converged]
    assert not cut, cut
    assert r.newton_iterations <= 80
    assert r.indenter_force_N > 0.0


@pytest.mark.slow
def test_indenter_starting_inside_the_skin_is_backed_off_and_reaches_the_same_end_state(limb):
    # a bar tilted 30 deg whose axis starts 0.8 mm clear still dips its lower end 0.3 mm into the skin
    # (the hard case "bar tilted 30 deg" starts 1.3 mm deep): the solver moves the start back along
    # the axis until the skin is start_clearance_mm clear; the end state does not depend on the path
    a = np.radians(30.0)
    axis = np.array([-np.cos(a), 0.0, np.sin(a)])
    end = np.array([2.7, 0.0, 3.0])
    ind = Indenter(
        "bar",
        axis=tuple(axis),
        start_mm=tuple(end - 0.8 * axis),
        end_mm=tuple(end),
        bar_length_mm=5.0,
    )
    skin = limb.nodes_mm[np.unique(limb.facets["skin"].ravel())]
    assert ind.gap(skin, ind.tip_at(0.0))[0].min() < -0.2
    r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert r.converged, r.reason
    back = r.extra["start_backoff_mm"]
    assert back > 0.3
    clear = ind.gap(skin, ind.tip_at(0.0) - back * axis)[0].min()
    assert clear > 0.5 * SolverSettings().increments.start_clearance_mm
    # the same end state as the solve that starts inside (it converges on this small limb)
    inside = solve_indentation(
        limb,
        material=LAW,
        indenter=ind,
        bone_motion=BoneMotion(),
        settings=SolverSettings(increments=IncrementSettings(start_clearance_mm=1e-9)),
    )
    assert inside.extra["start_backoff_mm"] < back
    assert r.indenter_force_N == pytest.approx(inside.indenter_force_N, rel=1e-3)
    # a start that is clear is left alone
    clear_ind = Indenter(
        "sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 3.0), end_mm=(2.9, 0.0, 3.0)
    )
    assert (
        solve_indentation(limb, material=LAW, indenter=clear_ind, bone_motion=BoneMotion()).extra[
            "start_backoff_mm"
        ]
        == 0.0
    )


def test_wall_time_budget_ends_the_solve_unconverged_with_its_reason(limb):
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(2.5, 0.0, 3.0))
    r = solve_indentation(
        limb,
        material=LAW,
        indenter=ind,
        bone_motion=BoneMotion(),
        settings=SolverSettings(max_wall_s=1e-6),
    )
    assert not r.converged
    assert "wall-time budget" in r.reason
    assert r.load_reached < 4.0


def _homogeneous_stretch(settings):
    """A block stretched 10 % along x by its prescribed faces (no contact): every increment converges."""
    m = block_mesh((2.0, 2.0, 2.0), h_mm=1.0)
    F0 = np.diag([1.1, 1.0, 1.0])
    return m, solve_prescribed(
        m,
        material=LAW,
        bc_sets=list(m.facets),
        displacement_mm=lambda X, s: s * X @ (F0 - np.eye(3)).T,
        settings=settings,
    )


def test_a_solve_whose_load_creeps_stops_with_its_reason_load_and_last_state():
    # increments of 0.01 of the step: over any 3 of them the load advances 0.03, below stall_load 0.05
    inc = IncrementSettings(
        initial_increment=0.01, max_increment=0.01, stall_increments=3, stall_load=0.05
    )
    m, r = _homogeneous_stretch(SolverSettings(increments=inc))
    assert not r.converged and r.reason.startswith("stalled: the load advanced 0.03 in the last 3")
    # stopped before its fifth increment, at the load of the fourth, with that increment's state
    assert len(r.history) == 4 and all(h.converged for h in r.history)
    assert r.load_reached == pytest.approx(3.04)
    np.testing.assert_allclose(r.displacement_mm[:, 0], 0.004 * m.nodes_mm[:, 0], atol=1e-9)
    # the same increments with a looser stall_load reach the end
    ok = _homogeneous_stretch(SolverSettings(increments=replace(inc, stall_load=0.02)))[1]
    assert ok.converged and len(ok.history) == 100


def test_a_solve_that_stops_advancing_for_stall_wall_s_stops():
    inc = IncrementSettings(
        initial_increment=0.01, max_increment=0.01, stall_load=0.5, stall_wall_s=1e-9
    )
    r = _homogeneous_stretch(SolverSettings(increments=inc))[1]
    # the load advances 0.01 per increment, less than stall_load in any window of a few increments' time
    assert not r.converged and r.reason.startswith("stalled: the load advanced ")
    assert " s (stall_load 0.5)" in r.reason
    assert 1 <= len(r.history) < 50 and all(h.converged for h in r.history)


def test_the_stall_window_grows_with_the_slowest_converged_increment():
    from types import SimpleNamespace

    from deeptissue.fem.solver import _stop_reason

    settings = SolverSettings(increments=IncrementSettings(stall_wall_s=300.0))

    def run(longest_ok_s):  # 1000 s into a solve that last advanced 100 s after its start
        return SimpleNamespace(
            job=SimpleNamespace(settings=settings),
            history=[None] * 5,
            t_wall=time.perf_counter() - 1000.0,
            progress=[(100.0, 3.5), (500.0, 3.5), (900.0, 3.5)],
            t=3.5,
            longest_ok_s=longest_ok_s,
        )

    assert "in the last 300 s" in _stop_reason(run(50.0))
    assert "in the last 600 s" in _stop_reason(run(200.0))
    assert _stop_reason(run(400.0)) == ""  # a 1200 s window: not yet


def test_stall_settings_do_not_keep_a_bone_state_from_being_used():
    from deeptissue.fem.solver import _path

    a = SolverSettings()
    b = replace(a, max_wall_s=60.0, increments=replace(a.increments, stall_wall_s=None))
    c = replace(a, increments=replace(a.increments, initial_increment=0.5))
    assert _path(a) == _path(b) and _path(a) != _path(c)


def test_indenter_ending_inside_the_bone_is_reported_infeasible_without_solving(limb):
    # the limb's rigid core has radius 0.8 mm about the z axis: a sphere (R 1.5 mm) whose tip ends at
    # x = 0.6 reaches 0.2 mm into it (less at the core's nodes, which are not all on the tip's line)
    deep = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(0.6, 0.0, 3.0))
    r = solve_indentation(limb, material=LAW, indenter=deep, bone_motion=BoneMotion())
    assert not r.converged and r.reason.startswith("infeasible") and r.extra["infeasible"]
    assert -0.2 - 1e-9 <= r.extra["bone_clearance_mm"] < -0.1
    assert r.newton_iterations == 0 and not r.history  # not solved
    # a clear end is solved, and its clearance reported
    ok_ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(2.9, 0.0, 3.0))
    ok = solve_indentation(limb, material=LAW, indenter=ok_ind, bone_motion=BoneMotion())
    assert ok.converged and 2.1 - 1e-9 <= ok.extra["bone_clearance_mm"] < 2.2


@pytest.mark.slow
def test_variant_started_from_the_shared_bone_state_takes_the_same_path(limb, tmp_path):
    # the bone-rotation steps (t 0 -> 3) do not involve the indenter (1 mm clear until its step): solved
    # once per mesh (solve_bone_rotation) they start every variant, which then reports the same path,
    # iterations and answer as a solve of its own
    from deeptissue.fem.solver import load_bone_state, save_bone_state, solve_bone_rotation

    cast = _cylinder_cast(3.2, 6.0, hole_centre=np.array([3.2, 0.0, 3.0]), hole_radius=1.8)
    motion = BoneMotion(
        rotation_deg=(6.0, -5.0, 4.0), centre_mm=(0.0, 0.0, 3.0), translation_mm=(0.1, 0.0, 0.0)
    )
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.2, 0.0, 3.0), end_mm=(2.3, 0.0, 3.0))
    whole = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=motion, cast=cast)
    assert whole.converged, whole.reason
    rot, state = solve_bone_rotation(limb, material=LAW, bone_motion=motion, cast=cast)
    assert rot.converged and rot.load_reached == 3.0 and state.newton_iterations > 0
    # the cast holds the skin (the state keeps every nonzero multiplier: also the small negative ones a state before
    # the end of the load may hold within its gap tolerance, so that a solve started from it takes the same path)
    assert np.linalg.norm(rot.cast_force_N) > 0 and np.any(state.contact["cast"][1] > 0)
    save_bone_state(tmp_path / "bone_state.npz", state)
    back = load_bone_state(tmp_path / "bone_state.npz")
    assert back.settings == state.settings and back.history == state.history
    np.testing.assert_array_equal(back.contact["cast"][1], state.contact["cast"][1])
    started = solve_indentation(
        limb, material=LAW, indenter=ind, bone_motion=motion, cast=cast, start=back
    )
    assert (
        started.converged
        and started.extra["started_from_bone_state"]
        and not whole.extra["started_from_bone_state"]
    )
    assert started.newton_iterations == whole.newton_iterations
    # the same increments (up to the last bits of a first-touch size) and Newton counts
    assert [h.iterations for h in started.history] == [h.iterations for h in whole.history]
    np.testing.assert_allclose(
        [(h.t_start, h.t_end) for h in started.history],
        [(h.t_start, h.t_end) for h in whole.history],
        rtol=0,
        atol=1e-12,
    )
    np.testing.assert_allclose(started.displacement_mm, whole.displacement_mm, atol=1e-8)
    assert started.indenter_force_N == pytest.approx(whole.indenter_force_N, rel=1e-8)
    # a solve with other settings solves the rotation itself
    other = solve_indentation(
        limb,
        material=LAW,
        indenter=ind,
        bone_motion=motion,
        cast=cast,
        start=back,
        settings=SolverSettings(newton=NewtonSettings(rtol=1e-7)),
    )
    assert not other.extra["started_from_bone_state"]
    # a state of another mesh is refused, naming the mismatch; a file that is not a state names the file
    with pytest.raises(ValueError, match="not this mesh's state"):
        solve_indentation(
            block_mesh((2.0, 2.0, 2.0), h_mm=1.0),
            material=LAW,
            indenter=None,
            bone_motion=motion,
            start=back,
        )
    (tmp_path / "junk.npz").write_bytes(b"not a state")
    with pytest.raises(ValueError, match="junk.npz: not a bone-state file"):
        load_bone_state(tmp_path / "junk.npz")


@pytest.mark.slow
def test_turned_variant_solved_from_the_base_end_state_reaches_the_same_end_state(
    limb, tmp_path, monkeypatch
):
    # hyperelastic and frictionless: the end state does not depend on the path, so a variant whose indenter
    # is the base's turned about the same final tip is solved by turning it from the base's end state
    from deeptissue.fem.solver import end_state, load_end_state, save_end_state, solve_turned
    from deeptissue.rigid import rotation_matrix

    cast = _cylinder_cast(3.2, 6.0, hole_centre=np.array([3.2, 0.0, 3.0]), hole_radius=1.8)
    motion = BoneMotion(
        rotation_deg=(3.0, 0.0, 0.0), centre_mm=(0.0, 0.0, 3.0), translation_mm=(0.05, 0.0, 0.0)
    )
    end = np.array([2.3, 0.0, 3.0])
    base_ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.2, 0.0, 3.0), end_mm=tuple(end))
    axis = rotation_matrix(np.array([0.0, 15.0, 0.0])) @ np.array([-1.0, 0.0, 0.0])
    turned_ind = replace(base_ind, axis=tuple(axis), start_mm=tuple(end - 1.9 * axis))
    base = solve_indentation(limb, material=LAW, indenter=base_ind, bone_motion=motion, cast=cast)
    direct = solve_indentation(
        limb, material=LAW, indenter=turned_ind, bone_motion=motion, cast=cast
    )
    assert base.converged and direct.converged, (base.reason, direct.reason)
    state = end_state(base, limb, indenter=base_ind, bone_motion=motion, settings=SolverSettings())
    save_end_state(tmp_path / "end_state.npz", state)
    back = load_end_state(tmp_path / "end_state.npz")
    assert (
        back.indenter == base_ind
        and back.bone_motion == motion
        and back.settings == SolverSettings()
    )
    assert set(back.contact) == {"indenter", "cast"}
    np.testing.assert_array_equal(back.contact["indenter"][1], state.contact["indenter"][1])
    assert np.any(back.contact["indenter"][1] > 0)  # the multipliers carried over
    turned = solve_turned(limb, material=LAW, base=back, indenter=turned_ind, cast=cast)
    assert turned.converged and turned.extra["turned"], turned.reason
    # only the turn was solved: one load step, the tip held at the common final tip
    assert all(h.step == 4 for h in turned.history) and all(
        np.allclose(h.tip_mm, end) for h in turned.history
    )
    assert turned.newton_iterations < direct.newton_iterations
    # the first increment moves the indenter's surface at the pressed skin nodes by at most half their facet
    # size, and is not cut shorter than that
    nodes, lam = back.contact["indenter"]
    pressed = np.asarray(nodes)[np.asarray(lam) > 0]
    x = limb.nodes_mm[pressed] + back.displacement_mm.reshape(-1, 3)[pressed]

    def first_move(result):
        """The first increment (a fraction of the turn) and the most its turn moves the sphere's surface at
        the pressed nodes [mm]."""
        dt = result.history[0].t_end - result.history[0].t_start
        part = rotation_matrix(np.array([0.0, 15.0 * dt, 0.0])) @ np.array([-1.0, 0.0, 0.0])
        gaps = replace(base_ind, axis=tuple(part)).gap(x, end)[0]
        return dt, float(np.max(np.abs(gaps - base_ind.gap(x, end)[0])))

    dt0, moved = first_move(turned)
    tri = limb.nodes_mm[limb.facets["patch"][:, :3]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    h = np.full(len(limb.nodes_mm), np.inf)
    np.minimum.at(h, limb.facets["patch"].ravel(), np.repeat(np.sqrt(2 * area), 6))
    h_mm = float(np.median(h[pressed]))
    assert moved <= 0.55 * h_mm and (dt0 == 1.0 or moved >= 0.45 * h_mm), (dt0, moved, h_mm)
    # on this coarse limb the turn goes whole; held to a tenth of a facet, it is cut to that motion and ends
    # in the same state
    import deeptissue.fem.solver as solver_module

    monkeypatch.setattr(solver_module, "_TURN_STEP_FACETS", 0.1)
    short = solve_turned(limb, material=LAW, base=back, indenter=turned_ind, cast=cast)
    _, moved = first_move(short)
    assert 0.09 * h_mm <= moved <= 0.11 * h_mm, (moved, h_mm)
    assert short.converged and short.indenter_force_N == pytest.approx(
        turned.indenter_force_N, rel=1e-3
    )
    assert turned.indenter_force_N == pytest.approx(direct.indenter_force_N, rel=5e-3)
    np.testing.assert_allclose(
        turned.force_on_tissue_N,
        direct.force_on_tissue_N,
        atol=5e-3 * np.linalg.norm(direct.force_on_tissue_N),
    )
    # the two end states differ by what the tolerances leave open: far less than the facets' penetration
    pen = max(turned.max_penetration_mm, direct.max_penetration_mm)
    assert np.max(np.abs(turned.displacement_mm - direct.displacement_mm)) < 0.5 * pen
    # a different end tip or shape is no turn; a state of another mesh is refused; junk names the file
    with pytest.raises(ValueError, match="is not a turn of"):
        solve_turned(
            limb,
            material=LAW,
            base=back,
            indenter=replace(turned_ind, end_mm=(2.2, 0.0, 3.0)),
            cast=cast,
        )
    with pytest.raises(ValueError, match="is not a turn of"):
        solve_turned(
            limb, material=LAW, base=back, indenter=replace(turned_ind, kind="bar"), cast=cast
        )
    with pytest.raises(ValueError, match="not this mesh's state"):
        solve_turned(
            block_mesh((2.0, 2.0, 2.0), h_mm=1.0), material=LAW, base=back, indenter=turned_ind
        )
    (tmp_path / "junk.npz").write_bytes(b"not a state")
    with pytest.raises(ValueError, match="junk.npz: not an end-state file"):
        load_end_state(tmp_path / "junk.npz")


def test_tissue_passing_through_the_indenter_is_not_reported_converged(limb):
    # a bar (R 1.5 mm) moved 1.7 mm into the skin in one increment (first touch not limited): its core line
    # ends past the skin nodes, the nearest-surface gap pushes them out behind the bar, and Newton converges to
    # the bar under the skin, pulling on it
    ind = Indenter(
        "bar", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(1.3, 0.0, 3.0), bar_length_mm=5.0
    )
    one_jump = SolverSettings(
        increments=IncrementSettings(first_touch_mm=5.0, initial_increment=1.0)
    )
    r = solve_indentation(
        limb, material=LAW, indenter=ind, bone_motion=BoneMotion(), settings=one_jump
    )
    assert r.increments == 1 and r.load_reached == pytest.approx(4.0)
    assert not r.converged and r.reason.startswith("the tissue passed through the indenter"), (
        r.reason
    )
    assert r.indenter_force_N < 0
    # the first-touch limit keeps the skin in front of the bar
    ok = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert ok.converged and ok.indenter_force_N > 0


def test_indenter_passing_between_the_skin_nodes_is_cut_back_not_accepted(
    limb, monkeypatch, caplog
):
    # the weighted gaps close at the nodes only: where a facet dips too far into the indenter between its nodes
    # (on a mesh coarse for the indenter, the sphere slips through the skin), the increment is cut, never
    # accepted. With the limit at zero every increment in contact is refused and the solve names the reason.
    monkeypatch.setattr("deeptissue.fem.solver._MAX_PENETRATION_REL", 0.0)
    caplog.set_level(logging.INFO, logger="deeptissue.fem.solver")
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(2.5, 0.0, 3.0))
    r = solve_indentation(
        limb,
        material=LAW,
        indenter=ind,
        bone_motion=BoneMotion(),
        settings=SolverSettings(increments=IncrementSettings(min_increment=0.01)),
    )
    assert not r.converged and "the indenter passes between the skin's nodes" in r.reason, r.reason
    assert r.load_reached < 4.0
    cut = [h.reason for h in r.history if not h.converged]
    assert cut and all("passes between the skin's nodes" in c for c in cut)
    # no attempt after a cut is longer than the one that failed, unless an increment converged in between
    length = [h.t_end - h.t_start for h in r.history]
    after_cut = [i for i in range(1, len(length)) if not r.history[i - 1].converged]
    assert len(after_cut) >= 3
    assert all(length[i] <= 0.35 * length[i - 1] + 1e-12 for i in after_cut)
    # each cut names the most compressed point of the state it stopped at: the sphere compresses the tissue
    # (the first cut may come before the indenter has moved it)
    crush = [m for m in caplog.messages if m.startswith("  its smallest det F is ")]
    assert len(crush) == len(cut)
    smallest = [float(m.split()[5].rstrip(",")) for m in crush]
    assert all(0.0 < j <= 1.0 + 1e-9 for j in smallest) and min(smallest) < 0.99, crush


def _scripted_load_step(monkeypatch, k, converges):
    """The increment sizes _load_step attempts in step k when an increment of size dt converges with
    ``converges(dt)`` -> Newton iterations, or fails (None); no mesh: the increments are scripted."""
    from types import SimpleNamespace

    from deeptissue.fem import solver

    tried = []

    def increment(run, k, dt):
        tried.append(dt)
        iters = converges(dt)
        if iters is not None:
            run.t += dt
        run.progress.append((0.0, run.t))
        run.history.append(None)
        return iters is not None, "" if iters is not None else "scripted failure", iters or 0, 0

    monkeypatch.setattr(solver, "_increment", increment)
    run = SimpleNamespace(
        job=SimpleNamespace(settings=SolverSettings(), indenter=None),
        history=[],
        progress=[],
        t_wall=time.perf_counter(),
        longest_ok_s=0.0,
        k_ind=None,
        contact=None,
        lam=np.zeros(1),
        sched=None,
        fail=lambda reason: None,
    )
    assert solver._load_step(run, k)
    return tried


def test_after_a_cut_an_increment_without_iterations_does_not_jump_to_the_end(monkeypatch):
    # increments longer than 0.05 fail; shorter ones converge at once (a loose intermediate state in a pinch).
    # The indentation step then grows by 2 after each, never tries the whole rest again after its first cut
    tried = _scripted_load_step(monkeypatch, 3, lambda dt: 0 if dt <= 0.05 else None)
    failed = [dt for dt in tried if dt > 0.05]
    assert tried[0] == 0.25 and failed[:2] == [0.25, 0.0875]
    assert all(b <= 2.0 * a + 1e-12 for a, b in zip(tried[2:], tried[3:]))
    # a bone-rotation step, where the rigid predictor is exact, is still finished at once
    assert _scripted_load_step(monkeypatch, 0, lambda dt: 0) == [1.0]


def test_one_tangent_per_newton_direction(limb, monkeypatch):
    # the test of convergence after a step reads the force and gaps of the line search's last merit evaluation:
    # a tangent is assembled for each Newton direction, and for the first test of an increment only (none for the
    # test that ends an increment after a step)
    from deeptissue.fem.assembly import Assembler

    calls = []
    tangent = Assembler.tangent
    monkeypatch.setattr(Assembler, "tangent", lambda self, u: calls.append(1) or tangent(self, u))
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.5, 0.0, 3.0), end_mm=(2.3, 0.0, 3.0))
    r = solve_indentation(limb, material=LAW, indenter=ind, bone_motion=BoneMotion())
    assert r.converged, r.reason
    assert all(h.converged for h in r.history) and sum(h.iterations > 0 for h in r.history) > 1
    assert len(calls) == r.newton_iterations + sum(h.iterations == 0 for h in r.history)


def test_freed_memory_is_kept_for_the_next_allocation():
    # glibc returns a freed large array to the kernel at once, and the next one is page-faulted in afresh; once
    # kept, freeing 200 MB leaves the process's resident memory where it was
    import sys

    from deeptissue.fem.heap import keep_freed_memory

    if not sys.platform.startswith("linux") or not keep_freed_memory():
        pytest.skip("needs glibc's mallopt")

    def resident_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * 4096 / 2**20

    a = np.ones(25_000_000)  # 200 MB
    before = resident_mb()
    del a
    assert resident_mb() > before - 50.0
