"""Quadratic tetrahedral meshes from gmsh, as plain arrays (the hand-over between mesher and solver).

A :class:`TetMesh` holds every node of a second-order mesh (corner and mid-edge), the 10-node
tetrahedra in **gmsh's node order**, and named boundary facet sets as 6-node triangles (gmsh
order too). gmsh's Tetrahedron10 order is corners 0-3, then the mid-edge nodes of edges
(0,1), (1,2), (0,2), (0,3), (2,3), (1,3); scikit-fem orders the last two edges (1,3), (2,3), so a
conversion swaps local nodes 8 and 9 (done in the FE core, which owns scikit-fem meshes).
Written and read only by :func:`save_tetmesh` / :func:`load_tetmesh` (``.npz``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io import save_npz

GMSH_TET10 = 11  # gmsh element type of the 10-node tetrahedron
GMSH_TRI6 = 9  # gmsh element type of the 6-node triangle


@dataclass(frozen=True)
class TetMesh:
    nodes_mm: np.ndarray  # (n_nodes, 3) world mm, corner and mid-edge nodes
    tets: np.ndarray  # (n_tets, 10) node indices, gmsh Tetrahedron10 order
    facets: dict = field(default_factory=dict)  # name -> (n_facets, 6) node indices, gmsh Triangle6 order

    def __post_init__(self):
        if self.nodes_mm.ndim != 2 or self.nodes_mm.shape[1] != 3:
            raise ValueError(f"TetMesh.nodes_mm: expected (n, 3), got {self.nodes_mm.shape}")
        if self.tets.ndim != 2 or self.tets.shape[1] != 10:
            raise ValueError(f"TetMesh.tets: expected (n, 10), got {self.tets.shape}")
        for name, f in self.facets.items():
            if f.ndim != 2 or f.shape[1] != 6:
                raise ValueError(f"TetMesh.facets[{name!r}]: expected (n, 6), got {f.shape}")
        n = len(self.nodes_mm)
        for name, arr in [("tets", self.tets), *((f"facets[{k!r}]", v) for k, v in self.facets.items())]:
            if arr.size and (arr.min() < 0 or arr.max() >= n):
                raise ValueError(f"TetMesh.{name}: node index out of range 0..{n - 1}")

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def volumes_mm3(self) -> np.ndarray:
        """Volumes of the straight-sided tetrahedra through the four corners (n_tets,) [mm^3]."""
        p = self.nodes_mm[self.tets[:, :4]]
        return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def extract_tet10(gmsh_module=None) -> TetMesh:
    """Read the current gmsh model (meshed with ``setOrder(2)``) into a :class:`TetMesh`.

    Boundary facet sets are the 2D physical groups, by name; only 10-node tetrahedra of 3D
    physical groups are kept (all of them if there is no 3D physical group). Nodes are
    renumbered 0..n-1 and unused nodes dropped.
    """
    if gmsh_module is None:
        import gmsh as gmsh_module
    g = gmsh_module
    tags, coords, _ = g.model.mesh.getNodes()
    coords = np.asarray(coords, float).reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags] = np.arange(len(tags))

    vol_groups = g.model.getPhysicalGroups(3)
    vol_entities = [e for _, t in vol_groups for e in g.model.getEntitiesForPhysicalGroup(3, t)] if vol_groups else [
        t for _, t in g.model.getEntities(3)
    ]
    tet_chunks = []
    for ent in vol_entities:
        _, nodes = g.model.mesh.getElementsByType(GMSH_TET10, ent)
        tet_chunks.append(np.asarray(nodes, dtype=np.int64).reshape(-1, 10))
    if not tet_chunks or sum(len(c) for c in tet_chunks) == 0:
        raise ValueError("gmsh model has no 10-node tetrahedra: mesh with generate(3) and setOrder(2)")
    tets = index[np.concatenate(tet_chunks)]

    facets = {}
    for dim, tag in g.model.getPhysicalGroups(2):
        name = g.model.getPhysicalName(dim, tag) or f"surface_{tag}"
        chunks = []
        for ent in g.model.getEntitiesForPhysicalGroup(dim, tag):
            _, nodes = g.model.mesh.getElementsByType(GMSH_TRI6, ent)
            chunks.append(np.asarray(nodes, dtype=np.int64).reshape(-1, 6))
        facets[name] = index[np.concatenate(chunks)] if chunks else np.zeros((0, 6), np.int64)

    used = np.unique(np.concatenate([tets.ravel(), *[f.ravel() for f in facets.values()]]))
    renum = np.full(len(coords), -1, dtype=np.int64)
    renum[used] = np.arange(len(used))
    return TetMesh(nodes_mm=coords[used], tets=renum[tets], facets={k: renum[v] for k, v in facets.items()})


def save_tetmesh(path: str | Path, mesh: TetMesh) -> None:
    save_npz(path, nodes_mm=mesh.nodes_mm, tets=mesh.tets, **{f"facets__{k}": v for k, v in mesh.facets.items()})


def load_tetmesh(path: str | Path) -> TetMesh:
    try:
        with np.load(path) as d:
            nodes, tets = d["nodes_mm"], d["tets"]
            facets = {k[len("facets__"):]: d[k] for k in d.files if k.startswith("facets__")}
    except (KeyError, OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a tet mesh file ({exc})") from exc
    try:
        return TetMesh(nodes_mm=nodes.astype(float), tets=tets.astype(np.int64), facets={k: v.astype(np.int64) for k, v in facets.items()})
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
