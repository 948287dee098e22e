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
