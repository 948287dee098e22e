"""FE core: TetMesh -> skfem conversion, vectorised assembly against finite differences and skfem."""

import numpy as np
import pytest
import scipy.sparse as sp
from _standin_material import NeoHooke, NeoHookeLaw
from scipy.spatial import cKDTree
from skfem import Basis, ElementTetP2, ElementVector, asm
from skfem.models.elasticity import linear_elasticity

from deeptissue.fem.assembly import Assembler, MaterialLaw, as_material_law
from deeptissue.fem.material import Ogden
from deeptissue.fem.skmesh import GMSH_TO_SKFEM_TET10, to_skfem
from deeptissue.mesh import TetMesh
from deeptissue.verification.shapes import block_mesh, cored_cylinder_mesh

LAW = as_material_law(Ogden())
# any law with the API of deeptissue.fem.material works: a compressible neo-Hookean (test-only)
NEO = MaterialLaw(NeoHooke(), NeoHookeLaw.energy, NeoHookeLaw.stress, NeoHookeLaw.stress_tangent)


@pytest.fixture(scope="module")
def block():
    return block_mesh((4.0, 3.0, 2.0), h_mm=1.0)


def test_conversion_is_the_8_9_swap_and_keeps_facet_sets(block):
    sk = to_skfem(block)
    np.testing.assert_array_equal(sk.element_nodes(), block.tets[:, GMSH_TO_SKFEM_TET10])
    # skfem P2 node positions are the TetMesh nodes
    np.testing.assert_array_equal(sk.mesh.doflocs.T, block.nodes_mm[sk.tetmesh_node])
    # facet sets: the skfem facets have the same corners, and bottom lies at z = 0 with area 12
    for name, f6 in block.facets.items():
        corners = np.sort(sk.mesh.facets[:, sk.facets[name]].T, axis=1)
        np.testing.assert_array_equal(corners, np.sort(sk.vertex_of_node[f6[:, :3]], axis=1))
    assert np.allclose(sk.mesh.p[2, np.unique(sk.mesh.facets[:, sk.facets["bottom"]])], 0.0)


def test_curved_cylinder_keeps_mid_nodes_and_volume_converges():
    errors = []
    for h in (1.0, 0.25):
        m = cored_cylinder_mesh(length_mm=3.0, radius_mm=2.0, core_radius_mm=0.5, h_mm=h)
        exact = np.pi * (2.0**2 - 0.5**2) * 3.0
        vol_p2 = Basis(to_skfem(m).mesh, ElementTetP2()).dx.sum()
        errors.append(abs(vol_p2 - exact) / exact)
        straight = m.volumes_mm3().sum()
        assert abs(vol_p2 - exact) < 0.1 * abs(straight - exact)  # curved (P2) geometry used
    assert errors[1] < errors[0] / 4 and errors[1] < 1e-5


@pytest.mark.parametrize("law", [LAW, NEO], ids=["ogden", "neohooke"])
def test_internal_force_and_tangent_match_finite_differences(block, law):
    A = Assembler(block, law)
    rng = np.random.default_rng(1)
    u = 0.002 * rng.standard_normal(A.n_dofs)
    W, f, data, _ = A.tangent(u)
    du = 1e-6 * rng.standard_normal(A.n_dofs)
    dW = (A.energy(u + du) - A.energy(u - du)) / 2
    assert dW == pytest.approx(f @ du, rel=1e-6)
    df = (A.force(u + du)[1] - A.force(u - du)[1]) / 2
    Kdu = A.full_matrix(data) @ du
    assert np.linalg.norm(df - Kdu) < 1e-6 * np.linalg.norm(Kdu)


@pytest.mark.parametrize("law", [LAW, NEO], ids=["ogden", "neohooke"])
def test_tangent_at_rest_equals_skfem_linear_elasticity(block, law):
    A = Assembler(block, law)
    _, f0, data, _ = A.tangent(np.zeros(A.n_dofs))
    assert np.abs(f0).max() < 1e-14
    mu, K = law.mu_mpa, law.bulk_mpa
    b = Basis(A.sk.mesh, ElementVector(ElementTetP2()), intorder=2)
    Ksk = asm(linear_elasticity(K - 2 * mu / 3, mu), b)
    _, node = cKDTree(block.nodes_mm).query(b.doflocs.T)
    comp = np.zeros(b.N, int)
    for c in range(3):
        comp[b.nodal_dofs[c]] = c
        comp[b.edge_dofs[c]] = c
    mine = 3 * node + comp
    x = np.random.default_rng(2).standard_normal(A.n_dofs)
    ref = Ksk @ x[mine]
    assert np.linalg.norm(ref - (A.full_matrix(data) @ x)[mine]) < 1e-12 * np.linalg.norm(ref)


@pytest.mark.parametrize("order", [2, 1])
def test_tangent_is_the_assembly_of_the_element_matrices_on_the_free_dofs(order):
    # the tangent's CSR data (upper triangle of K_ff, scattered from element entries in their own layout)
    # and the bc elements' matrices against a plain COO assembly of element_matrices
    m = block_mesh((3.0, 2.0, 2.0), h_mm=0.8, order=order)
    rng = np.random.default_rng(3)
    constrained = np.zeros(3 * len(m.nodes_mm), bool)
    constrained[rng.choice(len(constrained), len(constrained) // 5, replace=False)] = True
    A = Assembler(m, LAW, constrained=constrained)
    u = 0.01 * rng.standard_normal(A.n_dofs)
    _, _, data, Ke_bc = A.tangent(u)
    Ke = A.element_matrices(LAW.stress_tangent(A.deformation_gradient(u), LAW.params)[2])
    assert Ke.shape == (len(m.tets), 3 * A.n_local, 3 * A.n_local)
    np.testing.assert_allclose(Ke, Ke.transpose(0, 2, 1), atol=1e-12 * np.abs(Ke).max())
    rows = np.repeat(A.edofs, A.edofs.shape[1], axis=1).ravel()
    cols = np.tile(A.edofs, (1, A.edofs.shape[1])).ravel()
    K = sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(A.n_dofs, A.n_dofs)).tocsr()[A.free][
        :, A.free
    ]
    assert abs(A.full_matrix(data) - K).max() < 1e-12 * abs(K).max()
    assert len(A.bc_elems) and len(A.bc_elems) < len(m.tets)
    np.testing.assert_array_equal(Ke_bc, Ke[A.bc_elems])


def test_inverted_element_gives_infinite_energy(block):
    A = Assembler(block, LAW)
    u = np.zeros(A.n_dofs)
    u.reshape(-1, 3)[:, 2] = -2.0 * block.nodes_mm[:, 2]  # mirror z: det F < 0
    assert A.energy(u) == np.inf
    assert A.tangent(u)[1] is None


def test_folded_curved_tet_is_straightened():
    from deeptissue.fem.skmesh import reference_jacobians, straighten_invalid

    m = block_mesh((2.0, 2.0, 2.0), h_mm=1.0)
    p = m.nodes_mm.copy()
    t = m.tets[0]
    p[t[4]] = p[t[0]] + 1.5 * (
        p[t[1]] - p[t[0]]
    )  # mid-node of edge (0, 1) pushed past corner 1: folded
    bad = TetMesh(nodes_mm=p, tets=m.tets, facets=m.facets)
    assert np.any(reference_jacobians(bad, order=2) <= 0)
    fixed, n = straighten_invalid(bad)
    assert n >= 1 and np.all(reference_jacobians(fixed, order=2) > 0)
    np.testing.assert_allclose(fixed.nodes_mm[t[4]], 0.5 * (p[t[0]] + p[t[1]]))


def _skin_facet_size_near(m, point):
    f = m.facets["skin"][:, :3]
    c = m.nodes_mm[f].mean(axis=1)
    near = np.argmin(np.linalg.norm(c - np.asarray(point), axis=1))
    area = 0.5 * np.linalg.norm(np.cross(*(m.nodes_mm[f[near, 1:]] - m.nodes_mm[f[near, 0]])))
    return np.sqrt(2 * area)  # the facet size of ContactSurface.h_mm


def test_refinement_along_a_segment_reaches_both_of_its_ends():
    # a bar's footprint: the segment from (5, 0, 6) to (5, 0, 14) on the skin of the cylinder
    a, b = (5.0, 0.0, 6.0), (5.0, 0.0, 14.0)
    seg = cored_cylinder_mesh(
        length_mm=20.0,
        radius_mm=5.0,
        core_radius_mm=1.0,
        h_mm=2.0,
        refine_point_mm=(a, b),
        refine_h_mm=0.5,
        refine_radius_mm=1.0,
    )
    pt = cored_cylinder_mesh(
        length_mm=20.0,
        radius_mm=5.0,
        core_radius_mm=1.0,
        h_mm=2.0,
        refine_point_mm=(5.0, 0.0, 10.0),
        refine_h_mm=0.5,
        refine_radius_mm=1.0,
    )
    for p in (a, b, (5.0, 0.0, 10.0)):
        assert _skin_facet_size_near(seg, p) < 0.8
    assert _skin_facet_size_near(pt, a) > 1.2  # a point refines only around itself
    with pytest.raises(ValueError, match="segment"):
        cored_cylinder_mesh(
            h_mm=2.0, refine_point_mm=(a, b, a), refine_h_mm=0.5, refine_radius_mm=1.0
        )


def test_refinement_along_a_segment_with_negative_components():
    # an indenter's travel from the skin toward the core (-x) and a point at negative coordinates
    a, b = (5.0, 0.0, 10.0), (1.2, 0.0, 10.0)
    m = cored_cylinder_mesh(
        length_mm=20.0,
        radius_mm=5.0,
        core_radius_mm=1.0,
        h_mm=2.0,
        refine_point_mm=(a, b),
        refine_h_mm=0.5,
        refine_radius_mm=1.0,
    )
    X, T = m.nodes_mm, m.tets[:, :4]
    c = X[T].mean(axis=1)
    edge = np.linalg.norm(X[T[:, 0]] - X[T[:, 1]], axis=1)
    near_core = np.linalg.norm(c - np.array([1.5, 0.0, 10.0]), axis=1) < 0.5
    assert near_core.any() and np.median(edge[near_core]) < 0.8
    neg = cored_cylinder_mesh(
        h_mm=2.0, refine_point_mm=(-5.0, -0.5, 10.0), refine_h_mm=0.5, refine_radius_mm=1.0
    )
    assert _skin_facet_size_near(neg, (-5.0, 0.0, 10.0)) < 0.8
