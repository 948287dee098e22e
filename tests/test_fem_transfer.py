"""A solution carried to another mesh: interpolation of nodal fields, and the solve started from it."""

from dataclasses import replace

import numpy as np
import pytest

from deeptissue.fem.assembly import as_material_law
from deeptissue.fem.indenters import Indenter
from deeptissue.fem.material import Ogden
from deeptissue.fem.solver import Scene, SolverSettings, solve_from, solve_indentation
from deeptissue.fem.transfer import interpolate_nodal, mapped_end_state
from deeptissue.rigid import BoneMotion, apply_rigid
from deeptissue.verification.shapes import block_mesh, cored_cylinder_mesh

LAW = as_material_law(Ogden())


def _quadratic(x):
    return np.column_stack(
        [
            1.0 + 0.3 * x[:, 0] ** 2 - 0.2 * x[:, 1] * x[:, 2],
            x[:, 1] - 0.1 * x[:, 2] ** 2,
            0.05 * x[:, 0] * x[:, 1] + 0.4 * x[:, 2],
        ]
    )


def test_a_quadratic_field_is_carried_exactly_between_straight_quadratic_meshes():
    src = block_mesh((3.0, 2.0, 2.0), h_mm=1.0)
    pts = np.random.default_rng(0).uniform(0.0, 1.0, (500, 3)) * [
        3.0,
        2.0,
        2.0,
    ]  # anywhere in the block
    np.testing.assert_allclose(
        interpolate_nodal(src, _quadratic(src.nodes_mm), pts), _quadratic(pts), atol=1e-10
    )
    lin = block_mesh((3.0, 2.0, 2.0), h_mm=1.0, order=1)  # linear elements: a linear field
    np.testing.assert_allclose(
        interpolate_nodal(lin, lin.nodes_mm @ [1.0, -2.0, 0.5], pts),
        pts @ [1.0, -2.0, 0.5],
        atol=1e-10,
    )
    with pytest.raises(ValueError, match="nodal values for a mesh of"):
        interpolate_nodal(src, np.zeros((3, 3)), pts)


def test_points_beyond_the_chords_of_curved_facets_are_extrapolated_from_the_nearest_element():
    src = cored_cylinder_mesh(length_mm=4.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.2)
    dst = cored_cylinder_mesh(length_mm=4.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=0.8)
    out = interpolate_nodal(src, _quadratic(src.nodes_mm), dst.nodes_mm)
    # a field quadratic in x is quadratic in the reference coordinates of straight elements only: the curved
    # ones near the surfaces (and the points between a facet and its chord) are off by far less than the field
    assert np.max(np.abs(out - _quadratic(dst.nodes_mm))) < 0.02 * np.max(
        np.abs(_quadratic(dst.nodes_mm))
    )


def test_a_solve_started_from_a_coarser_mesh_reaches_the_fine_mesh_end_state_in_fewer_iterations():
    coarse = cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.6)
    fine = cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.0)
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 3.0), end_mm=(2.2, 0.0, 3.0))
    motion = BoneMotion(
        rotation_deg=(2.0, 0.0, 0.0), centre_mm=(0.0, 0.0, 3.0), translation_mm=(0.05, 0.0, 0.0)
    )
    first = solve_indentation(coarse, material=LAW, indenter=ind, bone_motion=motion)
    direct = solve_indentation(fine, material=LAW, indenter=ind, bone_motion=motion)
    assert first.converged and direct.converged, (first.reason, direct.reason)
    base = mapped_end_state(
        coarse,
        first.displacement_mm,
        fine,
        indenter=ind,
        bone_motion=motion,
        settings=SolverSettings(),
    )
    assert base.displacement_mm.shape == (3 * len(fine.nodes_mm),) and base.contact == {}
    b = np.unique(fine.facets["bone"])  # the bone's nodes where the solver prescribes them
    moved = apply_rigid(
        fine.nodes_mm[b],
        rotation_deg=motion.rotation_deg,
        centre_mm=motion.centre_mm,
        translation_mm=motion.translation_mm,
    )
    np.testing.assert_allclose(
        base.displacement_mm.reshape(-1, 3)[b], moved - fine.nodes_mm[b], atol=1e-12
    )
    r = solve_from(fine, Scene(LAW, ind, bone_motion=motion), base=base)
    assert r.converged and r.extra["turned"], r.reason
    assert all(h.step == 4 for h in r.history)  # the end load only, not the path
    assert r.newton_iterations <= 0.5 * direct.newton_iterations  # 4 against 8
    assert r.indenter_force_N == pytest.approx(direct.indenter_force_N, rel=5e-3)
    pen = max(r.max_penetration_mm, direct.max_penetration_mm)
    assert np.max(np.abs(r.displacement_mm - direct.displacement_mm)) < max(0.5 * pen, 1e-3)
    # a start that cannot be solved (every element folded): the whole path, the failed try's reason kept
    folded = replace(
        base, displacement_mm=np.random.default_rng(1).normal(0.0, 2.0, base.displacement_mm.shape)
    )
    again = solve_from(fine, Scene(LAW, ind, bone_motion=motion), base=folded)
    assert (
        again.converged
        and not again.extra.get("turned")
        and "inverted element" in again.extra["turn_failed"]
    )
    assert again.indenter_force_N == pytest.approx(direct.indenter_force_N, rel=1e-9)


def test_a_carried_state_that_still_folds_tets_is_not_used():
    src = cored_cylinder_mesh(length_mm=4.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.2)
    dst = cored_cylinder_mesh(length_mm=4.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=0.8)
    u = np.zeros_like(src.nodes_mm)
    inner = np.argmin(
        np.linalg.norm(src.nodes_mm - [1.9, 0.0, 2.0], axis=1)
    )  # a node inside the tissue
    u[inner] = [-3.0, 0.0, 0.0]  # pushed through the core: its elements turn inside out
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 2.0), end_mm=(2.8, 0.0, 2.0))
    assert (
        mapped_end_state(
            src, u, dst, indenter=ind, bone_motion=BoneMotion(), settings=SolverSettings()
        )
        is None
    )


def test_a_state_that_folds_a_tet_at_its_corners_is_untangled_by_a_small_local_move():
    from deeptissue.elements import GMSH_TET10_EDGES
    from deeptissue.fem.transfer import _inverted

    mesh = cored_cylinder_mesh(length_mm=4.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.0)
    X, corners = mesh.nodes_mm, mesh.tets[:, :4]
    bone = np.unique(mesh.facets["bone"])
    # an inner corner of a tet with three corners on the bone (pinched against it, as in the limb's deepest scenes)
    on_bone = np.isin(corners, bone)
    e = np.flatnonzero(on_bone.sum(axis=1) == 3)[0]
    free = corners[e][~on_bone[e]][0]
    face = X[corners[e][on_bone[e]]]
    n = np.cross(face[1] - face[0], face[2] - face[0])
    n /= np.linalg.norm(n)
    dist = float((X[free] - face[0]) @ n)
    u = np.zeros_like(X)
    u[free] = -1.02 * dist * n  # 2 % of its height through the bone's face
    for (
        a,
        b,
    ) in GMSH_TET10_EDGES:  # the edges from it stay straight: only its corners fold the tets
        on_edge = (mesh.tets[:, a] == free) | (mesh.tets[:, b] == free)
        u[mesh.tets[on_edge, 4 + GMSH_TET10_EDGES.index((a, b))]] = 0.5 * u[free]
    assert _inverted(mesh, u, 2)[e]
    ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(4.0, 0.0, 2.0), end_mm=(2.8, 0.0, 2.0))
    state = mapped_end_state(
        mesh, u, mesh, indenter=ind, bone_motion=BoneMotion(), settings=SolverSettings()
    )
    assert state is not None
    v = state.displacement_mm.reshape(-1, 3)
    assert not np.any(_inverted(mesh, v, 2))
    np.testing.assert_allclose(v[bone], 0.0, atol=1e-12)  # the bone held
    moved = np.linalg.norm(v - u, axis=1)
    assert moved.max() < 0.25 * 1.0 and moved[free] > 0.05 * abs(
        dist
    )  # back across the face, not far
    far = np.linalg.norm(X - X[free], axis=1) > 3.0  # untouched away from the fold
    np.testing.assert_allclose(v[far], u[far], atol=1e-12)


def test_a_rigid_motion_is_carried_exactly_through_curved_elements():
    # the old mesh's curved facets on the bone and the skin differ from the new mesh's: the new nodes there
    # are placed by inverting each old element's own quadratic map, so a field linear in x is exact
    src = cored_cylinder_mesh(length_mm=4.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.2)
    dst = cored_cylinder_mesh(length_mm=4.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=0.7)
    motion = dict(
        rotation_deg=(6.0, -4.0, 9.0), centre_mm=(0.2, -0.1, 2.0), translation_mm=(0.3, 0.1, -0.2)
    )
    field = apply_rigid(src.nodes_mm, **motion) - src.nodes_mm
    out = interpolate_nodal(src, field, dst.nodes_mm)
    np.testing.assert_allclose(out, apply_rigid(dst.nodes_mm, **motion) - dst.nodes_mm, atol=1e-9)
