"""VTU output of an FE result (ParaView): quadratic (or linear) tets, nodal displacement, per-element F."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_path
from ..mesh import TetMesh
from .skmesh import GMSH_TO_SKFEM_TET10

# VTK_QUADRATIC_TETRA edge order (0,1),(1,2),(2,0),(0,3),(1,3),(2,3) = gmsh with nodes 8/9 swapped
GMSH_TO_VTK_TET10 = GMSH_TO_SKFEM_TET10


def write_result_vtu(path: str | Path, mesh: TetMesh, result, *, cell_data: dict | None = None,
                     point_data: dict | None = None) -> None:
    """Write ``mesh`` with ``result.displacement_mm`` (point data 'displacement_mm', (n_nodes, 3)) and
    ``result.deformation_gradient`` (cell data 'F', (n_tets, 9) row-major) to a .vtu file.

    cell_data / point_data: extra arrays by name, (n_tets, ...) / (n_nodes, ...). Cells: VTK
    ``tetra10``, or ``tetra`` for a linear mesh.
    """
    import meshio

    cd = {"F": [np.asarray(result.deformation_gradient).reshape(len(mesh.tets), 9)],
          "J": [np.linalg.det(result.deformation_gradient)]}
    for k, v in (cell_data or {}).items():
        v = np.asarray(v)
        if len(v) != len(mesh.tets):
            raise ValueError(f"write_result_vtu: cell_data[{k!r}] has {len(v)} rows, mesh has {len(mesh.tets)} tets")
        cd[k] = [v]
    pd = {"displacement_mm": np.asarray(result.displacement_mm)}
    for k, v in (point_data or {}).items():
        pd[k] = np.asarray(v)
    m = meshio.Mesh(mesh.nodes_mm, [("tetra10", mesh.tets[:, GMSH_TO_VTK_TET10]) if mesh.order == 2 else ("tetra", mesh.tets)], point_data=pd, cell_data=cd)
    with atomic_path(path) as tmp:
        meshio.write(tmp, m, file_format="vtu")
