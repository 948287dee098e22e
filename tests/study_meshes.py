"""Hand-made quadratic tetrahedral meshes for the study tests (no gmsh needed)."""

from itertools import permutations

import numpy as np

from deeptissue.mesh import TetMesh

# gmsh Tetrahedron10: mid-edge nodes 4..9 on these corner pairs (written out here, independent of deeptissue.strain)
GMSH_TET10_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (2, 3), (1, 3))


def box_tet10(xs, ys, zs) -> TetMesh:
    """Structured 10-node tet mesh of the box spanned by the grid lines ``xs × ys × zs`` (mm).

    Every grid cell is split into 6 tetrahedra (Kuhn split along its main diagonal); mid-edge
    nodes are the straight edge midpoints, shared between neighbouring elements; node order is
    gmsh's. Elements never straddle a grid plane, so region boundaries at grid lines are exact.
    """
    xs, ys, zs = (np.asarray(a, float) for a in (xs, ys, zs))
    nx, ny, nz = len(xs), len(ys), len(zs)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    corners = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])

    def vid(i, j, k):
        return (i * ny + j) * nz + k

    tets = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            for k in range(nz - 1):
                for perm in permutations(range(3)):
                    step = np.zeros(3, int)
                    path = [vid(i, j, k)]
                    for ax in perm:
                        step[ax] += 1
                        path.append(vid(i + step[0], j + step[1], k + step[2]))
                    p = corners[path]
                    if np.dot(np.cross(p[1] - p[0], p[2] - p[0]), p[3] - p[0]) < 0:
                        path[1], path[2] = path[2], path[1]
                    tets.append(path)
    tets = np.array(tets)
    # shared mid-edge nodes
    edges = np.sort(np.concatenate([tets[:, [a, b]] for a, b in GMSH_TET10_EDGES]), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    mid = 0.5 * (corners[uniq[:, 0]] + corners[uniq[:, 1]])
    mid_ids = (len(corners) + inv.ravel()).reshape(6, len(tets)).T
    nodes = np.vstack([corners, mid])
    return TetMesh(nodes_mm=nodes, tets=np.hstack([tets, mid_ids]).astype(np.int64))


def centroids(mesh: TetMesh) -> np.ndarray:
    return mesh.nodes_mm[mesh.tets[:, :4]].mean(axis=1)


# gmsh Triangle6 faces of a Tetrahedron10 (local nodes: 3 corners, then mid-edges (0,1), (1,2), (2,0))
_TET_FACES6 = [
    (0, 2, 1, 6, 5, 4),
    (0, 1, 3, 4, 9, 7),
    (0, 3, 2, 7, 8, 6),
    (1, 2, 3, 5, 8, 9),
]


def boundary_tri6(mesh: TetMesh, keep) -> np.ndarray:
    """6-node triangles (outward normal) of the boundary faces whose three corners all satisfy
    ``keep(points (k, 3)) -> bool (k,)``."""
    faces = np.concatenate([mesh.tets[:, list(f)] for f in _TET_FACES6])
    key = np.sort(faces[:, :3], axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = counts[inv.ravel()] == 1
    ok = np.all(keep(mesh.nodes_mm[faces[:, :3]].reshape(-1, 3)).reshape(-1, 3), axis=1)
    return faces[boundary & ok]
