"""Simple gmsh test geometries (blocks, cored cylinders) as TetMesh, for verification and benchmarks."""

from __future__ import annotations

import gmsh
import numpy as np

from ..fem.skmesh import reference_jacobians
from ..mesh import TetMesh, edge_midpoints, extract_tetmesh

__all__ = ["block_mesh", "cored_cylinder_mesh", "distort_interior"]


def _start(name: str):

    gmsh.initialize(interruptible=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.model.add(name)
    return gmsh


def _size_field(gmsh, h_mm, refine_point_mm, refine_h_mm, refine_radius_mm, refine_growth=None):
    """Background size: ``refine_h_mm`` within ``refine_radius_mm`` of the point, then growing linearly
    to ``h_mm`` over ``refine_radius_mm`` (or, with ``refine_growth``, at that rate in mm per mm).
    ``refine_point_mm`` may also be a segment ``(a, b)`` (two points): the distance is then to the
    segment (a bar indenter's footprint).

    gmsh samples the background field only at the vertices (and circumcentres) of the mesh it is
    refining, so a small refinement ball inside a coarse initial triangulation of a large face is
    missed: the size must grow gently (``refine_growth`` <= ~0.5) for the refinement to be found.
    The mesh size from points, curvature and boundary extension is switched off so the field alone
    decides (checked in tests/test_fem_hertz.py on the facets under the refine point).
    """
    if refine_point_mm is None:
        gmsh.option.setNumber("Mesh.MeshSizeMax", h_mm)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.2 * h_mm)
        return
    pts = np.asarray(refine_point_mm, float).reshape(-1, 3)
    if len(pts) > 2:
        raise ValueError(
            f"refine_point_mm: a point or a segment (two points), got {len(pts)} points"
        )
    # every number in parentheses: gmsh's expression parser rejects "x--1" and "*-4"
    a, b = ([f"({float(v)!r})" for v in p] for p in (pts[0], pts[-1]))
    d = pts[-1] - pts[0]
    L2 = float(d @ d)
    d = [f"({float(v)!r})" for v in d]
    if L2 > 0:
        t = f"Min(1, Max(0, ((x-{a[0]})*{d[0]}+(y-{a[1]})*{d[1]}+(z-{a[2]})*{d[2]})/{L2!r}))"
        r = f"Sqrt((x-{a[0]}-{t}*{d[0]})^2+(y-{a[1]}-{t}*{d[1]})^2+(z-{a[2]}-{t}*{d[2]})^2)"
    else:
        r = f"Sqrt((x-{a[0]})^2+(y-{a[1]})^2+(z-{a[2]})^2)"
    ramp = refine_radius_mm if refine_growth is None else (h_mm - refine_h_mm) / refine_growth
    f = gmsh.model.mesh.field.add("MathEval")
    gmsh.model.mesh.field.setString(
        f,
        "F",
        f"Min({h_mm}, {refine_h_mm} + ({h_mm} - {refine_h_mm}) * Max(0, {r} - {refine_radius_mm}) / {ramp})",
    )
    gmsh.model.mesh.field.setAsBackgroundMesh(f)
    gmsh.option.setNumber("Mesh.MeshSizeMax", h_mm)
    for k in ("MeshSizeExtendFromBoundary", "MeshSizeFromPoints", "MeshSizeFromCurvature"):
        gmsh.option.setNumber(f"Mesh.{k}", 0)


def _finish(gmsh, order: int = 2) -> TetMesh:
    if order not in (1, 2):
        raise ValueError(f"element order must be 1 or 2, got {order}")
    gmsh.model.mesh.generate(3)
    if order == 2:
        gmsh.model.mesh.setOrder(order)
    return extract_tetmesh(order=order)


def block_mesh(
    size_mm=(10.0, 10.0, 5.0),
    *,
    h_mm=1.0,
    refine_point_mm=None,
    refine_h_mm=None,
    refine_radius_mm=None,
    refine_growth=None,
    order=2,
) -> TetMesh:
    """A box [0, lx] x [0, ly] x [0, lz] meshed with quadratic tets (linear with ``order=1``).

    Facet sets: xmin, xmax, ymin, ymax, bottom (z = 0), top (z = lz). Optional local refinement to
    ``refine_h_mm`` within ``refine_radius_mm`` of ``refine_point_mm`` growing linearly to ``h_mm``
    (over ``refine_radius_mm``, or at ``refine_growth`` mm per mm: use it when the refined region is
    much smaller than ``h_mm`` and the block, see ``_size_field``).
    """
    gmsh = _start("block")
    try:
        lx, ly, lz = size_mm
        gmsh.model.occ.addBox(0, 0, 0, lx, ly, lz)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [1], name="tissue")
        names = {}
        for _, t in gmsh.model.getEntities(2):
            c = gmsh.model.occ.getCenterOfMass(2, t)
            for k, (lo, hi, nlo, nhi) in enumerate(
                [(0, lx, "xmin", "xmax"), (0, ly, "ymin", "ymax"), (0, lz, "bottom", "top")]
            ):
                if abs(c[k] - lo) < 1e-9:
                    names[nlo] = t
                elif abs(c[k] - hi) < 1e-9:
                    names[nhi] = t
        for n, t in names.items():
            gmsh.model.addPhysicalGroup(2, [t], name=n)
        _size_field(gmsh, h_mm, refine_point_mm, refine_h_mm, refine_radius_mm, refine_growth)
        return _finish(gmsh, order)
    finally:
        gmsh.finalize()


def cored_cylinder_mesh(
    *,
    length_mm=20.0,
    radius_mm=5.0,
    core_radius_mm=1.0,
    h_mm=1.0,
    refine_point_mm=None,
    refine_h_mm=None,
    refine_radius_mm=None,
    order=2,
) -> TetMesh:
    """A cylinder along z (0..length) of ``radius_mm`` around a rigid core hole of ``core_radius_mm``,
    meshed with quadratic tets (linear with ``order=1``).

    Facet sets: bone (core surface), skin (outer surface), distal (z = 0), proximal (z = length),
    patch (= skin).
    """
    gmsh = _start("cyl")
    try:
        outer = gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, length_mm, radius_mm)
        inner = gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, length_mm, core_radius_mm)
        gmsh.model.occ.cut([(3, outer)], [(3, inner)])
        gmsh.model.occ.synchronize()
        vols = [t for _, t in gmsh.model.getEntities(3)]
        gmsh.model.addPhysicalGroup(3, vols, name="tissue")
        groups = {"bone": [], "skin": [], "distal": [], "proximal": []}
        for _, t in gmsh.model.getEntities(2):
            c = gmsh.model.occ.getCenterOfMass(2, t)
            if abs(c[2]) < 1e-6:
                groups["distal"].append(t)
            elif abs(c[2] - length_mm) < 1e-6:
                groups["proximal"].append(t)
            else:
                bb = gmsh.model.getBoundingBox(2, t)
                groups[
                    "bone" if bb[3] < radius_mm * 0.5 + core_radius_mm * 0.5 else "skin"
                ].append(t)
        for n, ts in groups.items():
            gmsh.model.addPhysicalGroup(2, ts, name=n)
        gmsh.model.addPhysicalGroup(2, groups["skin"], name="patch")
        _size_field(gmsh, h_mm, refine_point_mm, refine_h_mm, refine_radius_mm)
        return _finish(gmsh, order)
    finally:
        gmsh.finalize()


def distort_interior(
    mesh: TetMesh, *, amount=0.25, seed=0, keep_sets=None, curved=True
) -> TetMesh:
    """Move interior corner nodes randomly by up to ``amount`` x local edge length, and every
    interior mid-node off its straight edge if ``curved`` (order 2); boundary nodes stay. For patch tests."""
    rng = np.random.default_rng(seed)
    p = mesh.nodes_mm.copy()
    boundary = np.zeros(len(p), bool)
    for name, f in mesh.facets.items():
        if keep_sets is None or name in keep_sets:
            boundary[f.ravel()] = True
    t = mesh.tets
    edge_len = np.linalg.norm(p[t[:, 1]] - p[t[:, 0]], axis=1)
    h = np.zeros(len(p))
    np.maximum.at(h, t[:, :4].ravel(), np.repeat(edge_len, 4))
    corner = np.zeros(len(p), bool)
    corner[t[:, :4].ravel()] = True
    move = corner & ~boundary
    p[move] += amount * h[move, None] * rng.uniform(-1, 1, (move.sum(), 3)) / np.sqrt(3)
    if mesh.order == 1:
        out = TetMesh(nodes_mm=p, tets=mesh.tets, facets=mesh.facets)
        if np.any(out.volumes_mm3() <= 0):
            raise ValueError(
                "distort_interior: distortion inverted a tetrahedron; use a smaller amount"
            )
        return out
    # mid-nodes: midpoint of the (moved) corners plus a bump for interior edges
    m, mid = edge_midpoints(t, p)
    p[m] = mid
    mids = np.unique(t[:, 4:])
    mids = mids[~boundary[mids]]
    bump = (0.02 if curved else 0.0) * np.median(edge_len) * rng.uniform(-1, 1, (len(mids), 3))
    p[mids] += bump
    out = TetMesh(nodes_mm=p, tets=mesh.tets, facets=mesh.facets)

    if np.any(out.volumes_mm3() <= 0) or np.any(reference_jacobians(out) <= 0):
        raise ValueError(
            "distort_interior: distortion inverted a tetrahedron; use a smaller amount"
        )
    return out
