"""VTU output of an FE result (ParaView): quadratic (or linear) tets, nodal displacement, per-element F."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_path
from ..mesh import TetMesh
from .skmesh import GMSH_TO_SKFEM_TET10

__all__ = ["GMSH_TO_VTK_TET10", "write_result_vtu", "write_tet_vtu"]

# VTK_QUADRATIC_TETRA edge order (0,1),(1,2),(2,0),(0,3),(1,3),(2,3) = gmsh with nodes 8/9 swapped
GMSH_TO_VTK_TET10 = GMSH_TO_SKFEM_TET10


def write_tet_vtu(path: str | Path, mesh: TetMesh, *, point_data: dict, cell_data: dict) -> None:
    """Write ``mesh`` (reference nodes; VTK ``tetra10``, or ``tetra`` for a linear mesh) with point data
    (n_nodes, ...) and cell data (n_tets, ...) arrays by name to a .vtu file (atomically)."""
    import meshio

    for k, v in cell_data.items():
        if len(v) != len(mesh.tets):
            raise ValueError(
                f"{path}: cell data {k!r} has {len(v)} rows, the mesh has {len(mesh.tets)} tets"
            )
    for k, v in point_data.items():
        if len(v) != len(mesh.nodes_mm):
            raise ValueError(
                f"{path}: point data {k!r} has {len(v)} rows, the mesh has {len(mesh.nodes_mm)} nodes"
            )
    cells = [
        ("tetra10", mesh.tets[:, GMSH_TO_VTK_TET10]) if mesh.order == 2 else ("tetra", mesh.tets)
    ]
    m = meshio.Mesh(
        mesh.nodes_mm,
        cells,
        point_data={k: np.asarray(v) for k, v in point_data.items()},
        cell_data={k: [np.asarray(v)] for k, v in cell_data.items()},
    )
    with atomic_path(path) as tmp:
        meshio.write(tmp, m, file_format="vtu")


def write_result_vtu(
    path: str | Path,
    mesh: TetMesh,
    result,
    *,
    cell_data: dict | None = None,
    point_data: dict | None = None,
) -> None:
    """Write ``mesh`` with ``result.displacement_mm`` (point data 'displacement_mm', (n_nodes, 3)) and
    ``result.deformation_gradient`` (cell data 'F', (n_tets, 9) row-major, and 'J') to a .vtu file.

    cell_data / point_data: extra arrays by name, (n_tets, ...) / (n_nodes, ...).
    """
    cd = {
        "F": np.asarray(result.deformation_gradient).reshape(len(mesh.tets), 9),
        "J": np.linalg.det(result.deformation_gradient),
        **(cell_data or {}),
    }
    pd = {"displacement_mm": np.asarray(result.displacement_mm), **(point_data or {})}
    write_tet_vtu(path, mesh, point_data=pd, cell_data=cd)
