"""Linear (4-node) tetrahedra end to end, and how they compare with quadratic ones.

Truths: a homogeneous deformation (the patch test: P1 reproduces any linear displacement exactly),
a rigid motion (zero strain), skfem's own P1 linear-elasticity matrix, central differences of the
contact potential, the P2 solution of the same problem (a P1 mesh is stiffer, never softer), the
analytic prismatoid volume of the synthetic leg and the P2 mesh of the same size field (the same
corner tetrahedra).
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from skfem import Basis, ElementTetP1, ElementVector, asm
from skfem.models.elasticity import linear_elasticity

from deeptissue.fem.assembly import Assembler, as_material_law
from deeptissue.fem.contact import ContactSurface
from deeptissue.fem.indenters import Indenter
from deeptissue.fem.material import Ogden
from deeptissue.fem.skmesh import to_skfem
from deeptissue.fem.solver import solve_indentation, solve_prescribed
from deeptissue.mesh import TetMesh, load_tetmesh, save_tetmesh
from deeptissue.rigid import BoneMotion, apply_rigid
from deeptissue.strain import element_strain
from deeptissue.summary import (
    VoiSpec,
    deformed_surface,
    read_result_vtu,
    summarize_solution,
    write_result_vtu,
)
from deeptissue.verification.shapes import block_mesh, cored_cylinder_mesh, distort_interior

LAW = as_material_law(Ogden())


@pytest.fixture(scope="module")
def limb1():
    return cored_cylinder_mesh(length_mm=6.0, radius_mm=3.0, core_radius_mm=0.8, h_mm=1.0, order=1)


# --------------------------------------------------------------------------- TetMesh


def test_tetmesh_order_is_checked_and_round_trips(tmp_path):
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    m = TetMesh(
        nodes_mm=nodes,
        tets=tets,
        facets={"base": np.array([[0, 2, 1]]), "none": np.zeros((0, 3), np.int64)},
    )
    assert m.order == 1 and m.n_tets == 2
    np.testing.assert_allclose(m.volumes_mm3(), [1 / 6, 1 / 3])  # det of the edge vectors / 6
    save_tetmesh(tmp_path / "m.npz", m)
    back = load_tetmesh(tmp_path / "m.npz")
    assert back.order == 1
    np.testing.assert_array_equal(back.tets, tets)
    np.testing.assert_array_equal(back.facets["base"], m.facets["base"])
    assert back.facets["none"].shape == (0, 3)
    with pytest.raises(ValueError, match=r"facets\['base'\].*\(n, 3\)"):
        TetMesh(
            nodes_mm=nodes, tets=tets, facets={"base": np.array([[0, 2, 1, 0, 0, 0]])}
        )  # 6-node facets on 4-node tets
    with pytest.raises(ValueError, match=r"\(n, 6\)"):
        TetMesh(
            nodes_mm=nodes,
            tets=np.zeros((1, 10), np.int64),
            facets={"base": np.array([[0, 2, 1]])},
        )
    with pytest.raises(ValueError, match=r"tets.*\(n, 4\)"):
        TetMesh(nodes_mm=nodes, tets=np.zeros((1, 5), np.int64))
    with pytest.raises(ValueError, match="out of range"):
        TetMesh(nodes_mm=nodes, tets=np.array([[0, 1, 2, 5]]))


def test_shapes_give_linear_meshes_with_the_corners_of_the_quadratic_ones():
    m1 = block_mesh((3.0, 2.0, 2.0), h_mm=0.8, order=1)
    m2 = block_mesh((3.0, 2.0, 2.0), h_mm=0.8)
    assert m1.order == 1 and m2.order == 2 and m1.n_tets == m2.n_tets
    assert all(f.shape[1] == 3 for f in m1.facets.values())
    # same gmsh mesh before setOrder(2): the corner tets are the same (volumes sum to the box's)
    assert m1.volumes_mm3().sum() == pytest.approx(12.0, rel=1e-12)
    np.testing.assert_allclose(np.sort(m1.volumes_mm3()), np.sort(m2.volumes_mm3()), rtol=1e-12)


def test_p1_conversion_and_tangent_at_rest_equals_skfem(limb1):
    sk = to_skfem(limb1)
    assert type(sk.mesh).__name__ == "MeshTet1" and sk.order == 1
    for name, f in limb1.facets.items():  # facet sets map to the same corner triples
        fs = np.sort(sk.tetmesh_node[sk.mesh.facets[:, sk.facets[name]]].T, axis=1)
        np.testing.assert_array_equal(fs, np.sort(f, axis=1))
    A = Assembler(limb1, LAW)
    assert A.n_local == 4 and A.edofs.shape == (limb1.n_tets, 12)
    assert A.volume_mm3 == pytest.approx(limb1.volumes_mm3().sum(), rel=1e-12)
    _, f0, data, _ = A.tangent(np.zeros(A.n_dofs))
    assert np.abs(f0).max() < 1e-14
    mu, K = LAW.mu_mpa, LAW.bulk_mpa
    b = Basis(A.sk.mesh, ElementVector(ElementTetP1()), intorder=2)
    Ksk = asm(linear_elasticity(K - 2 * mu / 3, mu), b)
    _, node = cKDTree(limb1.nodes_mm).query(b.doflocs.T)
    comp = np.zeros(b.N, int)
    for c in range(3):
        comp[b.nodal_dofs[c]] = c
    mine = 3 * node + comp
    x = np.random.default_rng(2).standard_normal(A.n_dofs)
    ref = Ksk @ x[mine]
    assert np.linalg.norm(ref - (A.full_matrix(data) @ x)[mine]) < 1e-12 * np.linalg.norm(ref)
    # and the nonlinear force/tangent are derivatives of the energy
    rng = np.random.default_rng(1)
    u = 0.002 * rng.standard_normal(A.n_dofs)
    _, f, data, _ = A.tangent(u)
    du = 1e-6 * rng.standard_normal(A.n_dofs)
    assert (A.energy(u + du) - A.energy(u - du)) / 2 == pytest.approx(f @ du, rel=1e-6)
    df = (A.force(u + du)[1] - A.force(u - du)[1]) / 2
    Kdu = A.full_matrix(data) @ du
    assert np.linalg.norm(df - Kdu) < 1e-6 * np.linalg.norm(Kdu)


def test_linear_contact_facets_measure_area_and_penetration(limb1):
    surf = ContactSurface(limb1.nodes_mm, limb1.facets["skin"], order=4)
    assert surf.N.shape[1] == 3 and surf.dofs.shape == (surf.n_facets, 9)
    # the reference area is the skin's flat-facet area
    p = limb1.nodes_mm[limb1.facets["skin"]]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    np.testing.assert_allclose(surf.dA0.sum(axis=1), area, rtol=1e-12)
    # a sphere 0.3 mm into the skin: the deepest quadrature point is at most that deep
    ind = Indenter("sphere", axis=(-1, 0, 0), radius_mm=1.5)
    g = surf.gaps(
        np.zeros(limb1.nodes_mm.size),
        lambda x, hessian=True: ind.gap(x, np.array([2.7, 0.0, 3.0]), hessian=hessian),
    )
    assert 0.0 < -g.min() <= 0.3 + 1e-12


# --------------------------------------------------------------------------- solves


def test_p1_patch_test_on_a_distorted_mesh_and_strain_post_processing(tmp_path):
    m = distort_interior(block_mesh((3.0, 2.0, 2.0), h_mm=0.8, order=1), amount=0.3, seed=1)
    assert m.order == 1 and np.any(
        np.abs(m.nodes_mm - block_mesh((3.0, 2.0, 2.0), h_mm=0.8, order=1).nodes_mm) > 0.01
    )
    F0 = np.array([[1.12, 0.05, 0.0], [0.02, 0.93, 0.04], [0.03, 0.0, 1.06]])
    r = solve_prescribed(
        m,
        material=LAW,
        bc_sets=list(m.facets),
        displacement_mm=lambda X, s: s * X @ (F0 - np.eye(3)).T,
    )
    assert r.converged, r.reason
    assert r.n_dofs == 3 * len(m.nodes_mm)
    np.testing.assert_allclose(r.displacement_mm, m.nodes_mm @ (F0 - np.eye(3)).T, atol=1e-9)
    np.testing.assert_allclose(
        r.deformation_gradient, np.broadcast_to(F0, r.deformation_gradient.shape), atol=1e-9
    )
    # post-processing: the same F per element, Green-Lagrange principal values of F0, volumes of the box
    s = element_strain(m, r.displacement_mm)
    np.testing.assert_allclose(s.F, np.broadcast_to(F0, s.F.shape), atol=1e-9)
    E = 0.5 * (F0.T @ F0 - np.eye(3))
    ev = np.sort(np.linalg.eigvalsh(E))[::-1]
    np.testing.assert_allclose(
        s.principal_gl, np.broadcast_to(ev, s.principal_gl.shape), atol=1e-9
    )
    assert s.volume_mm3.sum() == pytest.approx(12.0, rel=1e-12)
    # the deformed top face is the plane F0 maps z = 2 to; its flat facets are the mesh facets
    verts, tris = deformed_surface(m, r.displacement_mm, facet="top")
    np.testing.assert_array_equal(tris, m.facets["top"])
    ms = TetMesh(m.nodes_mm, m.tets, {**m.facets, "skin": m.facets["top"]})
    summary, st = summarize_solution(
        ms,
        r.displacement_mm,
        animal="a",
        variant="v",
        voi=VoiSpec(threshold=0.05, bin_edges=(0.05, 0.1, 1.0)),
        skin_contours_mm=verts[np.unique(tris)],
    )
    assert summary.skin_mean_mm == pytest.approx(0.0, abs=1e-12)
    write_result_vtu(tmp_path / "r.vtu", m, r.displacement_mm, st)
    back, u, cd = read_result_vtu(tmp_path / "r.vtu")
    assert back.order == 1
    np.testing.assert_array_equal(back.tets, m.tets)
    np.testing.assert_allclose(u, r.displacement_mm)
    np.testing.assert_allclose(cd["gamma_gl"], st.gamma_gl)


def test_p1_rigid_bone_motion_gives_zero_strain(limb1, tmp_path):
    motion = BoneMotion(
        rotation_deg=tuple(60.0 * np.array([0.6, -0.48, 0.64])),
        centre_mm=(0.5, -0.2, 3.0),
        translation_mm=(0.3, -0.4, 0.2),
    )
    r = solve_indentation(limb1, material=LAW, indenter=None, bone_motion=motion)
    assert r.converged, r.reason
    moved = apply_rigid(
        limb1.nodes_mm,
        rotation_deg=motion.rotation_deg,
        centre_mm=motion.centre_mm,
        translation_mm=motion.translation_mm,
    )
    np.testing.assert_allclose(limb1.nodes_mm + r.displacement_mm, moved, atol=1e-7)
    s = element_strain(limb1, r.displacement_mm)
    assert np.abs(s.principal_gl).max() < 1e-7 and np.abs(s.gamma_log).max() < 1e-7
    import meshio

    from deeptissue.fem.output import write_result_vtu as write_fem_vtu

    write_fem_vtu(tmp_path / "f.vtu", limb1, r)
    back = meshio.read(tmp_path / "f.vtu")
    np.testing.assert_array_equal(back.cells_dict["tetra"], limb1.tets)
    np.testing.assert_allclose(back.cell_data["J"][0], 1.0, atol=1e-8)


@pytest.mark.slow
def test_p1_sphere_indentation_converges_and_is_stiffer_than_p2():
    # cored cylinder (tissue 0.8..3 mm around a rigid core), sphere R 1.5 mm pressed 0.2 mm, 0.8 mm
    # elements refined to 0.2 mm within 1 mm of the first contact point; P1 and P2 on the same gmsh
    # mesh. P1 gives 0.00235 N, P2 0.00192 N (+22 %; P2 is within ~1 % of its own finer mesh).
    # A linear tet with nu = 0.45 is too stiff (its strain is constant per element), never softer.
    forces = {}
    for order in (1, 2):
        m = cored_cylinder_mesh(
            length_mm=4.0,
            radius_mm=3.0,
            core_radius_mm=0.8,
            h_mm=0.8,
            refine_point_mm=(3.0, 0.0, 2.0),
            refine_h_mm=0.2,
            refine_radius_mm=1.0,
            order=order,
        )
        assert m.order == order
        ind = Indenter("sphere", axis=(-1, 0, 0), start_mm=(3.1, 0.0, 2.0), end_mm=(2.8, 0.0, 2.0))
        r = solve_indentation(m, material=LAW, indenter=ind, bone_motion=BoneMotion())
        assert r.converged, r.reason
        assert r.load_reached == pytest.approx(4.0)
        assert r.extra["node_penetration_rel"] <= 1e-3 + 1e-12 and r.max_penetration_rel < 0.05
        forces[order] = r.indenter_force_N
    assert forces[2] > 0
    assert 0.95 * forces[2] <= forces[1] <= 1.25 * forces[2], forces


# --------------------------------------------------------------------------- model and ladder


def test_p1_limb_mesh_has_the_corner_tets_of_the_p2_mesh():
    from model_synth import leg_contours, leg_pose

    from deeptissue import geometry as geo
    from deeptissue.model import build_model

    c = leg_contours(n_slices=12, n_points=60)
    pose = leg_pose(c, depth_mm=0.5)
    base = {"element_size_mm": 1.6, "refine_size_mm": 1.6}
    m1 = build_model(
        c, pose, variants=["sphere"], settings={**base, "element_order": 1}, animal="synth"
    )
    m2 = build_model(c, pose, variants=["sphere"], settings=base, animal="synth")
    a, b = m1.mesh, m2.mesh
    assert a.order == 1 and b.order == 2 and a.tets.shape[1] == 4
    assert set(a.facets) == set(b.facets) and all(f.shape[1] == 3 for f in a.facets.values())
    assert all(len(a.facets[k]) == len(b.facets[k]) for k in a.facets)

    # the same gmsh mesh up to setOrder(2): the same corner coordinates and tetrahedra
    def corner_sets(m):
        p = np.round(m.nodes_mm[m.tets[:, :4]], 9)  # (n, 4, 3)
        return {tuple(sorted(map(tuple, t))) for t in p}

    assert a.n_tets == b.n_tets
    assert corner_sets(a) == corner_sets(b)
    np.testing.assert_allclose(
        np.sort(a.volumes_mm3()), np.sort(b.volumes_mm3()), rtol=1e-9, atol=1e-12
    )
    assert len(a.nodes_mm) == len(np.unique(b.tets[:, :4]))
    st = m1.info["mesh"]
    assert st["element_order"] == 1 and st["min_curved_ratio"] == 1.0
    assert st["min_det_jacobian_mm3"] > 0 and st["min_scaled_jacobian"] >= 0.05
    # straight tets under-fill the lofted skin a little; still within 1 % of the prismatoid volume
    prism = geo.limb_volume_mm3(c.skin, c.bone)
    assert st["mesh_volume_mm3"] == pytest.approx(a.volumes_mm3().sum(), rel=1e-12)
    from deeptissue.mesh import tet10_min_det_jacobian, tet10_volume_mm3

    assert tet10_volume_mm3(a) == pytest.approx(a.volumes_mm3().sum(), rel=1e-12)
    np.testing.assert_array_equal(tet10_min_det_jacobian(a), a.volumes_mm3())
    # curved P2 boundary edges bulge onto the lofted skin: the P1 volume is a little smaller
    assert st["mesh_volume_mm3"] < m2.info["mesh"]["mesh_volume_mm3"]
    assert abs(st["mesh_volume_mm3"] - prism) < 0.01 * prism
    assert m1.info["settings"]["element_order"] == 1
    assert len(a.facets["patch_sphere"]) > 0


def test_element_order_must_be_1_or_2():
    from model_synth import leg_contours

    from deeptissue.mesh import MeshSpec, mesh_limb

    c = leg_contours(n_slices=6, n_points=40)
    with pytest.raises(ValueError, match="element order 3"):
        mesh_limb(c.skin, c.bone, MeshSpec(order=3), animal="rat7")


@pytest.mark.slow
def test_run_discretisation_runs_a_p1_setting():
    from model_synth import leg_contours, leg_pose

    from deeptissue.convergence import (
        ROW_COLUMNS,
        Discretisation,
        RunJob,
        default_ladder,
        run_discretisation,
    )

    lad = default_ladder(
        {
            "element_orders": [1, 2],
            "element_sizes_mm": [1.6],
            "refined_element_sizes_mm": [],
            "tolerances": [{"name": "default"}],
        },
        model_cfg={"element_size_mm": 1.0, "refine_size_mm": 0.5},
    )
    assert {"p1_h1.6", "p2_h1.6", "p1_h1_r0.5", "p2_h1_r0.5"} <= set(lad.names) and not lad.notes
    assert lad.default_name == "p2_h1_r0.5"
    assert (
        default_ladder({"element_orders": [1, 2]}, model_cfg={"element_order": 1}).default_name
        == "p1_h1.6_r0.8"
    )
    c = leg_contours(n_slices=12, n_points=60)
    pose = leg_pose(c, depth_mm=0.5)
    s = Discretisation(name="p1_h2", family="P1 uniform", element_size_mm=2.0, element_order=1)
    assert s.model_settings({})["element_order"] == 1
    study = {"variants": ["sphere"], "threshold": 0.05, "bin_edges": [0.05, 0.1, 0.2]}
    row = run_discretisation(
        RunJob(animal="synth", variant="sphere", setting=s),
        contours=c,
        pose=pose,
        cast=False,
        study_cfg=study,
    )
    assert set(ROW_COLUMNS) <= set(row)
    assert row["converged"], row["reason"]
    assert row["element_order"] == 1 and row["setting"] == "p1_h2"
    # 3 dofs per corner node: a 4-node tet mesh has far fewer nodes than tets
    assert row["n_elements"] > 100 and row["n_dofs"] < 3 * row["n_elements"]
    assert row["voi_mm3"] > 0 and sum(row["bins_percent"].values()) == pytest.approx(100.0)
    assert row["indenter_force_N"] > 0 and row["linear_wall_s"] > 0


@pytest.mark.slow
def test_p1_model_files_and_solve_job_with_the_cast(tmp_path):
    # the rules' entry points with model.element_order 1: cast, mesh (npz, msh, vtu, json, QC figure),
    # then the solve job with cast contact and the skin agreement (pre contours standing in for the
    # during scan: the deformed skin stays close to them away from the small dent)
    import json

    import meshio
    from model_synth import leg_contours, leg_pose

    from deeptissue.contours import save_contours
    from deeptissue.model import MeshFiles, run_cast, run_mesh
    from deeptissue.pose import save_pose
    from deeptissue.study import SolvePaths, run_solve
    from deeptissue.summary import read_summary

    c = leg_contours(n_slices=12, n_points=60)
    pose = leg_pose(c, depth_mm=0.5)
    save_contours(tmp_path / "contours.npz", c)
    save_pose(tmp_path / "pose.json", pose)
    settings = {"element_size_mm": 2.0, "refine_size_mm": 1.0, "element_order": 1}
    run_cast(
        contours_npz=tmp_path / "contours.npz",
        pose_json=tmp_path / "pose.json",
        cast_npz=tmp_path / "cast.npz",
        variants=["sphere"],
        settings=settings,
        animal="synth",
    )
    out = {k: tmp_path / f"mesh.{k}" for k in ("npz", "msh", "vtu")}
    run_mesh(
        MeshFiles(
            contours_npz=tmp_path / "contours.npz",
            pose_json=tmp_path / "pose.json",
            cast_npz=tmp_path / "cast.npz",
            mesh_npz=out["npz"],
            mesh_msh=out["msh"],
            mesh_vtu=out["vtu"],
            model_json=tmp_path / "model.json",
            qc_png=tmp_path / "qc.png",
        ),
        variants=["sphere"],
        settings=settings,
        animal="synth",
    )
    mesh = load_tetmesh(out["npz"])
    assert mesh.order == 1
    v = meshio.read(out["vtu"])
    assert set(v.cells_dict) == {"tetra", "triangle"} and len(v.cells_dict["tetra"]) == mesh.n_tets
    info = json.loads((tmp_path / "model.json").read_text())
    assert info["settings"]["element_order"] == 1 and info["mesh"]["element_order"] == 1
    assert (tmp_path / "qc.png").read_bytes()[:4] == b"\x89PNG"
    s = run_solve(
        SolvePaths(
            mesh=out["npz"],
            pose=tmp_path / "pose.json",
            summary=tmp_path / "summary.json",
            vtu=tmp_path / "result.vtu",
            cast=tmp_path / "cast.npz",
            during_contours=tmp_path / "contours.npz",
        ),
        animal="synth",
        variant="sphere",
        fem_cfg={},
        study_cfg={"threshold": 0.05, "bin_edges": [0.05, 0.1, 0.2]},
    )
    assert s.converged, s.reason
    back = read_summary(tmp_path / "summary.json")
    assert back.n_elements == mesh.n_tets and back.indenter_force_N > 0 and back.voi_mm3 > 0
    assert 0 < back.skin_mean_mm < 0.1 and back.skin_p95_mm < 0.5
    m2, u, cells = read_result_vtu(tmp_path / "result.vtu")
    assert m2.order == 1 and u.shape == mesh.nodes_mm.shape and np.all(cells["converged"] == 1)
