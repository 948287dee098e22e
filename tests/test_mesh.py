"""gmsh -> TetMesh extraction: node order, physical groups, round trip."""

import gmsh
import numpy as np
import pytest

from deeptissue.mesh import TetMesh, extract_tet10, load_tetmesh, save_tetmesh


@pytest.fixture
def box_mesh():
    gmsh.initialize(interruptible=False)
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        gmsh.model.add("box")
        gmsh.model.occ.addBox(0, 0, 0, 2, 3, 4)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], name="tissue")
        # the face at z = 0
        bottom = [
            t
            for d, t in gmsh.model.getEntities(2)
            if abs(gmsh.model.occ.getCenterOfMass(d, t)[2]) < 1e-9
        ]
        gmsh.model.addPhysicalGroup(2, bottom, name="bottom")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 1.0)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        yield extract_tet10()
    finally:
        gmsh.finalize()


def test_extracted_mesh_fills_the_box(box_mesh):
    m = box_mesh
    assert m.volumes_mm3().sum() == pytest.approx(24.0, rel=1e-12)
    assert np.all(m.volumes_mm3() > 0)


def test_mid_edge_nodes_follow_gmsh_order(box_mesh):
    m = box_mesh
    p = m.nodes_mm[m.tets]
    edges = [(0, 1), (1, 2), (0, 2), (0, 3), (2, 3), (1, 3)]
    for k, (a, b) in enumerate(edges):
        np.testing.assert_allclose(p[:, 4 + k], 0.5 * (p[:, a] + p[:, b]), atol=1e-12)


def test_boundary_group_and_round_trip(box_mesh, tmp_path):
    m = box_mesh
    bottom = m.facets["bottom"]
    assert np.allclose(m.nodes_mm[bottom][..., 2], 0.0)
    p = m.nodes_mm[bottom]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    assert area == pytest.approx(6.0, rel=1e-12)
    save_tetmesh(tmp_path / "m.npz", m)
    back = load_tetmesh(tmp_path / "m.npz")
    np.testing.assert_array_equal(back.tets, m.tets)
    np.testing.assert_array_equal(back.facets["bottom"], bottom)


def test_bad_index_is_refused():
    with pytest.raises(ValueError, match="node index out of range"):
        TetMesh(nodes_mm=np.zeros((4, 3)), tets=np.arange(10)[None, :])


def test_edge_midpoints_are_where_a_straight_tet10_has_its_mid_edge_nodes():
    from study_meshes import box_tet10

    from deeptissue.mesh import edge_midpoints

    mesh = box_tet10(np.linspace(0, 2, 3), np.linspace(0, 1, 2), np.linspace(0, 1.5, 2))
    mids, at = edge_midpoints(mesh.tets, mesh.nodes_mm)
    assert mids.shape == (mesh.n_tets, 6) and at.shape == (mesh.n_tets, 6, 3)
    assert np.array_equal(mids, mesh.tets[:, 4:])
    assert np.allclose(at, mesh.nodes_mm[mids], atol=1e-12)
    # moved corners: the midpoints follow them
    x = mesh.nodes_mm + np.array([0.3, -0.1, 0.2]) * mesh.nodes_mm[:, :1] ** 2
    _, moved = edge_midpoints(mesh.tets, x)
    assert np.allclose(moved[:, 0], 0.5 * (x[mesh.tets[:, 0]] + x[mesh.tets[:, 1]]))


def test_containing_tets_finds_what_locate_in_tets_finds_inside_a_hole_and_outside():
    from study_meshes import box_tet10

    from deeptissue.mesh import containing_tets, locate_in_tets

    box = box_tet10(np.linspace(0, 2, 5), np.linspace(0, 3, 7), np.linspace(0, 2, 5))
    rng = np.random.default_rng(4)
    # uneven elements (each node moved up to 0.1 mm) around a hole of radius 0.6 mm
    nodes = box.nodes_mm + rng.uniform(-0.1, 0.1, box.nodes_mm.shape)
    centroids = nodes[box.tets[:, :4]].mean(axis=1)
    kept = box.tets[np.linalg.norm(centroids - [1.0, 1.5, 1.0], axis=1) > 0.6]
    mesh = TetMesh(nodes_mm=nodes, tets=kept)
    corners = nodes[kept[:, :4]]
    faces = (corners.sum(axis=1, keepdims=True) - corners) / 3.0  # on faces shared by two elements
    P = np.vstack(
        [
            rng.uniform([-0.5, -0.5, -0.5], [2.5, 3.5, 2.5], size=(3000, 3)),  # a third inside
            rng.uniform([-3.0, -3.0, -3.0], [5.0, 6.0, 5.0], size=(1000, 3)),  # most far outside
            rng.uniform([0.6, 1.1, 0.6], [1.4, 1.9, 1.4], size=(500, 3)),  # in and around the hole
            nodes[np.unique(kept[:, :4])],  # corners: equal coordinates in several elements
            faces.reshape(-1, 3)[::7],
        ]
    )
    elem, lam = locate_in_tets(mesh, P)
    expected = np.where(lam.min(axis=1) >= -1e-9, elem, -1)
    found = containing_tets(mesh, P)
    assert np.array_equal(found, expected)
    assert (found >= 0).sum() > 1000 and (found < 0).sum() > 1000
    # a point inside the hole is in no element
    assert containing_tets(mesh, [[1.0, 1.5, 1.0]])[0] == -1
