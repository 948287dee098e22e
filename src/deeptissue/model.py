"""The animal model: limb mesh, rigid cast and contact patches from pre contours and pose.

:func:`build_cast` and :func:`build_model` are the two entry points used by the rules ``cast`` and
``mesh``; :func:`save_cast` / :func:`load_cast` and :func:`write_model` write the files of
``results/{animal}/model/`` (``mesh.npz``, ``mesh.msh``, ``mesh.vtu``, ``cast.npz``, ``model.json``);
:func:`model_qc_figure` draws the QC figure and :func:`plot_model_qc` writes it.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import meshio
import numpy as np

from . import geometry as geo
from .contours import Contours, load_contours
from .io import atomic_path, save_npz, write_json
from .mesh import (
    MeshQualityError,
    MeshSpec,
    PatchSpec,
    RefineSegment,
    TetMesh,
    mesh_limb,
    sample_lofted_surface,
    save_tetmesh,
)
from .pose import Pose, load_pose
from .variants import parse_variant, variant_travel

__all__ = [
    "SPHERE_RADIUS_MM",
    "AnimalModel",
    "Cast",
    "MeshFiles",
    "ModelSettings",
    "build_cast",
    "build_model",
    "cast_hole_boundary",
    "load_cast",
    "model_qc_figure",
    "plot_model_qc",
    "run_cast",
    "run_mesh",
    "save_cast",
    "variant_axes",
    "write_model",
    "write_vtu",
]

log = logging.getLogger(__name__)

# indenter head and bar radius: the default Indenter.radius_mm (deeptissue.fem.indenters), 3 mm diameter
SPHERE_RADIUS_MM = 1.5


# the bounds of the schema's section ``model`` (and fem.bar_length_mm, which the rules pass in)
_POSITIVE = (
    "element_size_mm",
    "refine_size_mm",
    "refine_transition_mm",
    "cast_dz_mm",
    "patch_diameter_mm",
    "min_gap_mm",
    "bar_length_mm",
)
_NON_NEGATIVE = (
    "refine_radius_mm",
    "refine_depth_mm",
    "cast_offset_mm",
    "cast_extension_mm",
    "hole_diameter_mm",
    "min_dihedral_deg",
)
_CHOICES = {
    "cast_offset_direction": ("normal", "radial"),
    "loft": ("ruled", "smooth"),
    "algorithm_3d": ("hxt", "delaunay"),
    "element_order": (1, 2),
    "mesh_groups": ("indenter", "animal"),
}


@dataclass(frozen=True)
class ModelSettings:
    """Settings of the model stage (config section ``model``; see the schema for descriptions)."""

    element_size_mm: float = 1.6
    refine_size_mm: float = 0.8
    refine_radius_mm: float = 4.0
    refine_transition_mm: float = 2.0
    refine_depth_mm: float = 4.0
    cast_offset_mm: float = 0.2
    cast_offset_direction: str = "normal"
    cast_extension_mm: float = 1.0
    cast_dz_mm: float = 0.25
    hole_diameter_mm: float = 6.0
    hole_for_variants: bool = True
    patch_diameter_mm: float = 6.0
    bar_length_mm: float = (
        10.0  # the FE core's default (fem.bar_length_mm is passed in by the rules)
    )
    spline_points: int = 100
    loft: str = "ruled"
    curved: bool = True
    algorithm_3d: str = "hxt"
    min_scaled_jacobian: float = 0.05
    min_dihedral_deg: float = 2.0
    min_curved_ratio: float = 0.2
    min_gap_mm: float = 0.05
    element_order: int = 2  # 2: 10-node, 1: 4-node tetrahedra
    mesh_groups: str = "animal"  # which variants share a mesh (deeptissue.variants.mesh_groups; used by the workflow)

    def __post_init__(self):
        """The schema's bounds of the section ``model`` (deeptissue.config checks a config against the same)."""
        for name in _POSITIVE + _NON_NEGATIVE + ("min_scaled_jacobian", "min_curved_ratio"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
                raise ValueError(f"model.{name}: expected a number, got {value!r}")
            if not np.isfinite(value):
                raise ValueError(f"model.{name}: must be a finite number, got {value!r}")
            if (name in _POSITIVE and value <= 0) or (name in _NON_NEGATIVE and value < 0):
                raise ValueError(
                    f"model.{name}: must be {'> 0' if name in _POSITIVE else '>= 0'}, got {value!r}"
                )
        if isinstance(self.spline_points, bool) or not (
            isinstance(self.spline_points, (int, np.integer)) and self.spline_points >= 8
        ):
            raise ValueError(
                f"model.spline_points: must be an integer >= 8, got {self.spline_points!r}"
            )
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"model.{name}: expected one of {list(allowed)}, got {getattr(self, name)!r}"
                )

    @classmethod
    def from_dict(cls, d: dict | None) -> ModelSettings:
        """Settings from the config section ``model`` (None: defaults); an unknown key is a ValueError."""
        d = dict(d or {})
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"model settings: unknown key(s) {unknown}; allowed: {sorted(names)}")
        return cls(**d)

    def to_dict(self) -> dict:
        """The settings as a plain dict (written to model.json)."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Cast:
    """The rigid cast: a triangle surface with normals toward the leg, open at both ends, with the hole."""

    vertices_mm: np.ndarray  # (V, 3) world mm
    triangles: np.ndarray  # (T, 3) int
    log: tuple = ()  # what was done to offset and cut the hole


@dataclass(frozen=True)
class AnimalModel:
    """One animal's model as built by :func:`build_model`: mesh, cast, facts and the gmsh file."""

    animal: str
    mesh: TetMesh
    cast: Cast
    info: dict  # the content of model.json
    msh_bytes: bytes = b""  # the gmsh .msh file as written by gmsh
    log: tuple = field(default_factory=tuple)


# --------------------------------------------------------------------------- cast


def _equidistant(contours: Contours) -> Contours:
    """The contours with points equidistant in arc length (segmentation already delivers them so;
    this makes the model independent of how the points were spaced)."""
    return Contours(
        skin=geo.resample_arclength(contours.skin), bone=geo.resample_arclength(contours.bone)
    )


def build_cast(
    contours: Contours,
    pose: Pose,
    *,
    variants=("sphere",),
    settings: ModelSettings | dict | None = None,
    animal: str = "?",
) -> Cast:
    """Rigid cast around the pre skin contours with the hole where the indenter axis passes.

    With ``settings.hole_for_variants`` the hole is the union of the variants' circles (each
    projected along its own axis, a bar's swept along the bar), so no variant's indenter presses
    the skin against the cast; otherwise the circle about the estimated axis only.

    Parameters
    ----------
    contours : Contours
        Pre-state contours, ``skin`` and ``bone`` (n_slices, n_points, 3) [mm, world].
    pose : Pose
        Indenter axis and tip travel (:mod:`deeptissue.pose`).
    variants : sequence of str
        Variant names (:func:`deeptissue.variants.parse_variant`).
    settings : ModelSettings or dict or None
        Config section ``model`` (None: defaults).
    animal : str
        For messages.

    Returns
    -------
    Cast
        ``vertices_mm`` (V, 3) [mm], ``triangles`` (T, 3) with normals toward the leg, ``log`` of
        what was done to offset it and cut the hole.

    Raises
    ------
    deeptissue.geometry.ModelInputError
        For contours that cannot make a cast.
    """
    s = settings if isinstance(settings, ModelSettings) else ModelSettings.from_dict(settings)
    geo.check_contours(contours.skin, contours.bone, animal=animal, min_gap_mm=s.min_gap_mm)
    contours = _equidistant(contours)
    # the cast is offset from the surface the mesh lies on: the ruled loft is rebuilt here exactly
    # (straight lines between the offset contours); the smooth one is sampled from OpenCASCADE
    surface = (
        sample_lofted_surface(contours.skin, spline_points=s.spline_points, dz_mm=s.cast_dz_mm)
        if s.loft == "smooth"
        else None
    )
    if s.hole_for_variants:
        footprints = [
            (sp.point_mm, sp.axis, sp.half_length_mm, sp.long_dir)
            for sp in _patch_specs(pose, list(variants), s).values()
        ]
    else:
        footprints = [(pose.tip_end_mm, pose.indenter_axis, 0.0, None)]
    spec = geo.CastSpec(
        offset_mm=s.cast_offset_mm,
        offset_direction=s.cast_offset_direction,
        extension_mm=s.cast_extension_mm,
        dz_mm=s.cast_dz_mm,
        ruled=s.loft == "ruled",
        hole_diameter_mm=s.hole_diameter_mm,
    )
    v, t, msgs = geo.build_cast(
        contours.skin,
        footprints,
        spec,
        axis=pose.indenter_axis,
        point_mm=pose.tip_end_mm,
        surface=surface,
        animal=animal,
    )
    for m in msgs:
        log.info("animal %s: %s", animal, m)
    return Cast(vertices_mm=v, triangles=t, log=tuple(msgs))


def save_cast(path: str | Path, cast: Cast) -> None:
    """Write ``cast`` as ``.npz`` (``vertices_mm``, ``triangles``, ``log``), atomically."""
    save_npz(
        path,
        vertices_mm=cast.vertices_mm,
        triangles=cast.triangles,
        log=np.array(cast.log, dtype=str),
    )


def load_cast(path: str | Path) -> Cast:
    """Read a file written by :func:`save_cast`; ValueError naming the file if it is not one."""
    try:
        with np.load(path) as d:
            return Cast(
                vertices_mm=d["vertices_mm"].astype(float),
                triangles=d["triangles"].astype(np.int64),
                log=tuple(d["log"].tolist()) if "log" in d.files else (),
            )
    except (KeyError, OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a cast file ({exc})") from exc


def cast_hole_boundary(cast: Cast) -> np.ndarray:
    """Edges (E, 2) of the cast boundary that are not on its two open ends (the hole rim)."""
    e = np.sort(
        np.concatenate(
            [cast.triangles[:, [0, 1]], cast.triangles[:, [1, 2]], cast.triangles[:, [2, 0]]]
        ),
        axis=1,
    )
    u, c = np.unique(e, axis=0, return_counts=True)
    b = u[c == 1]
    z = cast.vertices_mm[:, 2]
    zlo, zhi = z.min(), z.max()
    at_end = np.all(np.isclose(z[b], zlo, atol=1e-9), axis=1) | np.all(
        np.isclose(z[b], zhi, atol=1e-9), axis=1
    )
    return b[~at_end]


# --------------------------------------------------------------------------- model


def variant_axes(pose: Pose, variants) -> dict:
    """{variant name: (axis, tip_start_mm, tip_end_mm, Variant)} for the configured variants."""
    out = {}
    for name in variants:
        v = parse_variant(name)
        axis, start, end = variant_travel(
            v, axis=pose.indenter_axis, tip_start_mm=pose.tip_start_mm, tip_end_mm=pose.tip_end_mm
        )
        out[name] = (axis, start, end, v)
    return out


def _bar_sweep(v, axis, s: ModelSettings):
    """(half length of the bar's centre segment [mm], unit direction along the bar) of a variant;
    (0.0, None) for a sphere (or a bar no longer than its diameter)."""
    if v.indenter == "bar" and s.bar_length_mm > 2 * SPHERE_RADIUS_MM:
        return 0.5 * s.bar_length_mm - SPHERE_RADIUS_MM, geo.bar_direction(axis)
    return 0.0, None


def _patch_specs(pose: Pose, variants, s: ModelSettings) -> dict:
    """{``patch_<variant>``: PatchSpec}: each variant's contact patch about its final tip."""
    specs = {}
    for name, (axis, _, end, v) in variant_axes(pose, variants).items():
        half, long_dir = _bar_sweep(v, axis, s)
        specs[f"patch_{name}"] = PatchSpec(
            point_mm=end,
            axis=axis,
            radius_mm=0.5 * s.patch_diameter_mm,
            half_length_mm=half,
            long_dir=long_dir,
        )
    return specs


def _facet_geometry(mesh: TetMesh, name: str):
    p = mesh.nodes_mm[mesh.facets[name][:, :3]]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return p.mean(axis=1), 0.5 * np.linalg.norm(n, axis=1)


def build_model(
    contours: Contours,
    pose: Pose,
    *,
    variants=("sphere",),
    settings: ModelSettings | dict | None = None,
    animal: str = "?",
    cast: Cast | None = None,
    size_field=None,
) -> AnimalModel:
    """Limb mesh with bone/skin/proximal/distal facet sets and contact patches, plus cast and facts.

    The mesh is refined around each variant's travel (a bar's swept along the bar). If gmsh's 3D
    algorithm gives a mesh that fails the quality gate, the other one (hxt / delaunay) is tried once.

    Parameters
    ----------
    contours : Contours
        Pre-state ``skin`` and ``bone`` stacks (n_slices, n_points, 3) [mm, world].
    pose : Pose
        Indenter axis and tip travel.
    variants : sequence of str
        Variant names (:mod:`deeptissue.variants`) whose patches ``patch_<name>`` are tagged on the
        mesh, with their union ``patch``.
    settings : ModelSettings or dict or None
        Config section ``model`` (None: defaults).
    animal : str
        For messages.
    cast : Cast or None
        The cast; built with :func:`build_cast` when None.
    size_field : deeptissue.mesh.SizeField or None
        A background size [mm] in place of the refinement around the variants' travel
        (:class:`deeptissue.mesh.MeshSpec`; the adaptive loop's remeshing, :mod:`deeptissue.adapt_limb`).

    Returns
    -------
    AnimalModel
        ``mesh`` (TetMesh, nodes in mm; facet sets ``bone``, ``skin``, ``proximal``, ``distal``,
        ``patch``, ``patch_<variant>``), ``cast``, ``info`` (the content of model.json: volumes
        [mm³], mesh statistics, skin-cast gap [mm], patches, ``wall_s``), ``msh_bytes``, ``log``.

    Raises
    ------
    deeptissue.geometry.ModelInputError
        Contours or a pose that cannot make a model (names the animal).
    deeptissue.mesh.MeshQualityError
        A mesh with inverted or degenerate elements with both 3D algorithms.
    deeptissue.mesh.MeshSizeError
        A mesh estimated to have more elements than fit in memory (before meshing).
    """
    t0 = time.perf_counter()
    s = settings if isinstance(settings, ModelSettings) else ModelSettings.from_dict(settings)
    variants = list(variants)
    if not variants:
        raise ValueError(f"animal {animal}: no variants given")
    facts = geo.check_contours(
        contours.skin, contours.bone, animal=animal, min_gap_mm=s.min_gap_mm
    )
    contours = _equidistant(contours)
    if cast is None:
        cast = build_cast(contours, pose, variants=variants, settings=s, animal=animal)
    specs = _patch_specs(pose, variants, s)
    spec = MeshSpec(
        element_size_mm=s.element_size_mm,
        refine_size_mm=s.refine_size_mm,
        refine_radius_mm=s.refine_radius_mm,
        refine_transition_mm=s.refine_transition_mm,
        refine_segments=_refine_segments(pose, variants, s),
        size_field=size_field,
        patches=specs,
        spline_points=s.spline_points,
        loft=s.loft,
        curved=s.curved,
        min_scaled_jacobian=s.min_scaled_jacobian,
        min_dihedral_deg=s.min_dihedral_deg,
        min_curved_ratio=s.min_curved_ratio,
        algorithm_3d=s.algorithm_3d,
        order=s.element_order,
    )
    msgs: list[str] = []
    mesh, stats, msh_bytes = _mesh_with_fallback(contours, spec, animal=animal, msgs=msgs)
    info = {
        "animal": animal,
        "settings": s.to_dict(),
        "variants": variants,
        "tags": _facet_tags(mesh),
        "patches": _patch_facts(mesh, pose, variants),
        "volumes": _volumes(contours, stats),
        "mesh": {k: v for k, v in stats.items() if k not in ("facet_counts",)},
        "cast": _cast_facts(mesh, cast, pose, list(specs.values()), s),
        "contours": {
            "n_slices": int(contours.n_slices),
            "n_points": int(contours.skin.shape[1]),
            "min_skin_bone_gap_mm": float(facts["min_gap_mm"].min()),
        },
        "refine_segments_mm": [[seg.start_mm, seg.end_mm] for seg in spec.refine_segments],
        "log": msgs,
        "wall_s": time.perf_counter() - t0,
    }
    log.info(
        "animal %s: %d tets (estimated %.0f), %d nodes, min scaled Jacobian %.3f, min dihedral %.1f deg, "
        "volume %.1f mm3 (prismatoid %+.2f %%)",
        animal,
        stats["n_tets"],
        stats["estimated_tets"],
        stats["n_nodes"],
        stats["min_scaled_jacobian"],
        stats["min_dihedral_deg"],
        info["volumes"]["mesh_mm3"],
        info["volumes"]["mesh_vs_prismatoid_percent"],
    )
    return AnimalModel(
        animal=animal, mesh=mesh, cast=cast, info=info, msh_bytes=msh_bytes, log=tuple(msgs)
    )


def _refine_segments(pose: Pose, variants, s: ModelSettings) -> tuple:
    """The segments the mesh is refined around: each variant's travel to ``refine_depth_mm`` past its final
    tip, a bar's swept along the bar (its rounded ends concentrate strain too), duplicates once."""
    segs, seen = [], set()
    for axis, start, end, v in variant_axes(pose, variants).values():
        half, long_dir = _bar_sweep(v, axis, s)
        for off in [-half, 0.0, half] if half > 0 else [0.0]:
            shift = off * long_dir if off else 0.0
            key = tuple(np.round(np.concatenate([axis, start + shift]), 9))
            if key in seen:
                continue
            seen.add(key)
            segs.append(
                RefineSegment(
                    start_mm=start + shift, end_mm=end + shift + s.refine_depth_mm * axis
                )
            )
    return tuple(segs)


def _mesh_with_fallback(contours: Contours, spec: MeshSpec, *, animal: str, msgs: list):
    """(mesh, stats, the .msh file's bytes) of :func:`deeptissue.mesh.mesh_limb`; a mesh the quality gate
    refuses is made once more with the other 3D algorithm, and ``msgs`` says so."""
    with tempfile.TemporaryDirectory() as tmp:
        msh = Path(tmp) / "mesh.msh"
        try:
            mesh, stats = mesh_limb(
                contours.skin, contours.bone, spec, animal=animal, msh_path=msh
            )
        except MeshQualityError as exc:
            other = "delaunay" if spec.algorithm_3d == "hxt" else "hxt"
            msgs.append(f"mesh: {exc}; retried with the {other} 3D algorithm")
            log.warning("animal %s: %s", animal, msgs[-1])
            mesh, stats = mesh_limb(
                contours.skin,
                contours.bone,
                dataclasses.replace(spec, algorithm_3d=other),
                animal=animal,
                msh_path=msh,
            )
        return mesh, stats, msh.read_bytes()


def _facet_tags(mesh: TetMesh) -> dict:
    """{facet set: its facet count and area [mm²]}."""
    tags = {}
    for name in mesh.facets:
        _, a = _facet_geometry(mesh, name)
        tags[name] = {"n_facets": int(len(mesh.facets[name])), "area_mm2": float(a.sum())}
    return tags


def _patch_facts(mesh: TetMesh, pose: Pose, variants) -> dict:
    """{variant: its patch's tag, indenter, axis and travel, facet count and farthest node from the axis [mm]}."""
    patches = {}
    for name, (axis, start, end, v) in variant_axes(pose, variants).items():
        f = mesh.facets[f"patch_{name}"]
        d = geo.axis_distance_mm(mesh.nodes_mm[f], point_mm=end, axis=axis)
        patches[name] = {
            "tag": f"patch_{name}",
            "indenter": v.indenter,
            "axis": axis,
            "tip_start_mm": start,
            "tip_end_mm": end,
            "n_facets": int(len(f)),
            "max_axis_distance_mm": float(d.max()),
        }
    return patches


def _volumes(contours: Contours, stats: dict) -> dict:
    """The mesh's, the prismatoid's and the CAD solid's volume [mm³], and the mesh against the prismatoid [%]."""
    prism = geo.limb_volume_mm3(contours.skin, contours.bone)
    vol = stats["mesh_volume_mm3"]
    return {
        "mesh_mm3": vol,
        "prismatoid_mm3": prism,
        "cad_mm3": stats.get("occ_volume_mm3"),
        "mesh_vs_prismatoid_percent": 100.0 * (vol - prism) / prism,
    }


def _cast_facts(mesh: TetMesh, cast: Cast, pose: Pose, patches: list, s: ModelSettings) -> dict:
    """The cast's size and the skin-cast gap [mm] over the skin nodes away from the hole (QC)."""
    xs = mesh.nodes_mm[np.unique(mesh.facets["skin"])]
    gap = geo.surface_distance_mm(xs, cast.vertices_mm, cast.triangles)
    hole_fps = (
        patches
        if s.hole_for_variants
        else [PatchSpec(point_mm=pose.tip_end_mm, axis=pose.indenter_axis, radius_mm=0.0)]
    )
    near_hole = np.min(
        [
            geo.footprint_distance_mm(
                xs,
                point_mm=f.point_mm,
                axis=f.axis,
                half_length_mm=f.half_length_mm,
                long_dir=f.long_dir,
            )
            for f in hole_fps
        ],
        axis=0,
    )
    away = near_hole > 0.5 * s.hole_diameter_mm + 1.0
    away |= (
        xs - pose.tip_end_mm
    ) @ pose.indenter_axis > 2.0  # far side (the hole is on the near side)
    return {
        "n_vertices": int(len(cast.vertices_mm)),
        "n_triangles": int(len(cast.triangles)),
        "skin_gap_mm": {
            "min": float(gap[away].min()),
            "mean": float(gap[away].mean()),
            "max": float(gap[away].max()),
        },
        "log": list(cast.log),
    }


# --------------------------------------------------------------------------- writers and QC


def write_vtu(path: str | Path, mesh: TetMesh) -> None:
    """ParaView file: the 10-node tets and one block of 6-node triangles per facet set (4-node tets and
    3-node triangles for a linear mesh); cell data ``group`` (0 = tets, i = i-th facet set in sorted
    order, listed in field data)."""
    names = sorted(mesh.facets)
    if mesh.order == 2:
        cells = [
            ("tetra10", mesh.tets[:, [0, 1, 2, 3, 4, 5, 6, 7, 9, 8]])
        ]  # VTK orders edges (1,3) before (2,3)
    else:
        cells = [("tetra", mesh.tets)]
    groups = [np.zeros(len(mesh.tets), np.int32)]
    for i, n in enumerate(names, start=1):
        cells.append(("triangle6" if mesh.order == 2 else "triangle", mesh.facets[n]))
        groups.append(np.full(len(mesh.facets[n]), i, np.int32))
    m = meshio.Mesh(mesh.nodes_mm, cells, cell_data={"group": groups})
    with atomic_path(path) as tmp:
        meshio.write(tmp, m, file_format="vtu")


def write_model(model: AnimalModel, *, mesh_npz, mesh_msh, mesh_vtu, model_json) -> None:
    """Write the model files, each atomically: ``mesh_npz`` (:func:`deeptissue.mesh.save_tetmesh`),
    ``mesh_msh`` (gmsh), ``mesh_vtu`` (:func:`write_vtu`) and ``model_json`` (``model.info`` plus the
    VTU group names)."""
    save_tetmesh(mesh_npz, model.mesh)
    with atomic_path(mesh_msh) as tmp:
        tmp.write_bytes(model.msh_bytes)
    write_vtu(mesh_vtu, model.mesh)
    info = dict(model.info)
    info["vtu_groups"] = {i: n for i, n in enumerate(["tets", *sorted(model.mesh.facets)])}
    write_json(model_json, info)


def plot_model_qc(path, model: AnimalModel, pose: Pose) -> None:
    """Write :func:`model_qc_figure` to ``path`` (PNG, atomically)."""
    import matplotlib.pyplot as plt

    fig = model_qc_figure(model, pose)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def model_qc_figure(model: AnimalModel, pose: Pose):
    """3D QC figure, seen along the indenter axis and from the side: skin (grey), patch union (red), cast
    rings (blue), hole rim (black), axis (orange). Ticks every 5 mm on the two world axes across the line
    of sight (at 2.5 mm steps a 20 mm leg's labels run into each other); the axis seen end-on has none."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, MultipleLocator
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    mesh, cast = model.mesh, model.cast
    a = pose.indenter_axis
    views = [
        ("seen along the indenter axis", a),
        ("seen from the side", np.cross(a, [0.0, 0.0, 1.0])),
    ]
    fig = plt.figure(figsize=(11, 5.5))
    rim = cast_hole_boundary(cast)
    v = cast.vertices_mm
    # cast: every 4th row of the lofted grid, as lines
    ce = np.sort(
        np.concatenate(
            [cast.triangles[:, [0, 1]], cast.triangles[:, [1, 2]], cast.triangles[:, [2, 0]]]
        ),
        axis=1,
    )
    ce = np.unique(ce, axis=0)
    zrow = np.round(v[:, 2] / max(model.info["settings"]["cast_dz_mm"], 1e-6)).astype(int)
    ring = ce[(np.abs(v[ce[:, 0], 2] - v[ce[:, 1], 2]) < 1e-9) & (zrow[ce[:, 0]] % 4 == 0)]
    for k, (title, view) in enumerate(views):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        skin = mesh.nodes_mm[mesh.facets["skin"][:, :3]]
        ax.add_collection3d(
            Poly3DCollection(
                skin,
                facecolor=(0.8, 0.8, 0.8, 0.35),
                edgecolor=(0.5, 0.5, 0.5, 0.15),
                linewidth=0.2,
            )
        )
        ax.add_collection3d(
            Poly3DCollection(
                mesh.nodes_mm[mesh.facets["patch"][:, :3]],
                facecolor=(0.85, 0.1, 0.1, 0.8),
                edgecolor="none",
            )
        )
        ax.add_collection3d(
            Line3DCollection(v[ring], colors=[(0.1, 0.3, 0.9, 0.35)], linewidths=0.4)
        )
        if len(rim):  # a cast without a hole (model.hole_diameter_mm 0) has no rim
            ax.add_collection3d(Line3DCollection(v[rim], colors="k", linewidths=1.5))
        p0, p1 = pose.tip_start_mm - 4 * a, pose.tip_end_mm + 2 * a
        ax.plot(*np.stack([p0, p1]).T, color="orange", lw=2)
        lo, hi = v.min(axis=0), v.max(axis=0)
        c, r = 0.5 * (lo + hi), 0.5 * np.max(hi - lo)
        ax.set(
            xlim=(c[0] - r, c[0] + r),
            ylim=(c[1] - r, c[1] + r),
            zlim=(c[2] - r, c[2] + r),
            xlabel="x [mm]",
            ylabel="y [mm]",
            zlabel="z [mm]",
        )
        vv = -np.asarray(view, float)
        vv /= np.linalg.norm(vv)
        ax.view_init(
            elev=float(np.degrees(np.arcsin(np.clip(vv[2], -1, 1)))),
            azim=float(np.degrees(np.arctan2(vv[1], vv[0]))),
        )
        ax.set_proj_type("ortho")
        # the world axis closest to the line of sight is seen end-on: its ticks would pile up into one blot
        along = "xyz"[int(np.argmax(np.abs(vv)))]
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_major_locator(MultipleLocator(5.0))
            axis.set_major_formatter(FormatStrFormatter("%g"))
        getattr(ax, f"set_{along}ticks")([])
        getattr(ax, f"set_{along}label")("")
        ax.tick_params(labelsize=8)
        ax.set_box_aspect((1, 1, 1), zoom=1.15)
        ax.set_title(title, fontsize=9)
    st = model.info["mesh"]
    fig.suptitle(
        f"{model.animal}: {st['n_tets']} {'quadratic' if mesh.order == 2 else 'linear'} tets, min scaled Jacobian {st['min_scaled_jacobian']:.2f}, "
        f"min dihedral {st['min_dihedral_deg']:.1f} deg; skin grey, contact patch red, cast blue, hole rim black, axis orange",
        fontsize=9,
    )
    fig.subplots_adjust(left=0.02, right=0.98, bottom=0.02, top=0.86, wspace=0.05)
    return fig


# --------------------------------------------------------------------------- rule entry points


def run_cast(
    *,
    contours_npz,
    pose_json,
    cast_npz,
    variants=("sphere",),
    settings: dict | None = None,
    animal: str = "?",
) -> Cast:
    """Rule ``cast``: read the pre contours and the pose, write ``cast.npz``.

    Parameters
    ----------
    contours_npz, pose_json : str or Path
        Pre contours (:func:`deeptissue.contours.load_contours`) and pose (:func:`deeptissue.pose.load_pose`).
    cast_npz : str or Path
        Output (:func:`save_cast`).
    variants, settings, animal
        As in :func:`build_cast`.

    Returns
    -------
    Cast
        What was written.
    """
    cast = build_cast(
        load_contours(contours_npz),
        load_pose(pose_json),
        variants=variants,
        settings=settings,
        animal=animal,
    )
    save_cast(cast_npz, cast)
    return cast


@dataclass(frozen=True)
class MeshFiles:
    """The files of rule ``mesh``: its inputs, pre contours (:func:`deeptissue.contours.load_contours`), pose
    (:func:`deeptissue.pose.load_pose`) and cast (:func:`run_cast`), and its outputs, the mesh files and
    model.json (:func:`write_model`) and the QC figure (:func:`plot_model_qc`)."""

    contours_npz: str | Path
    pose_json: str | Path
    cast_npz: str | Path
    mesh_npz: str | Path
    mesh_msh: str | Path
    mesh_vtu: str | Path
    model_json: str | Path
    qc_png: str | Path


def run_mesh(
    files: MeshFiles, *, variants, settings: dict | None = None, animal: str = "?"
) -> AnimalModel:
    """Rule ``mesh``: read pre contours, pose and cast; write the mesh files, model.json and the QC figure.

    Parameters
    ----------
    files : MeshFiles
        The rule's inputs and outputs.
    variants : sequence of str
        Variants tagged and refined for on this mesh.
    settings, animal
        As in :func:`build_model`.

    Returns
    -------
    AnimalModel
        The model written.
    """
    pose = load_pose(files.pose_json)
    model = build_model(
        load_contours(files.contours_npz),
        pose,
        variants=variants,
        settings=settings,
        animal=animal,
        cast=load_cast(files.cast_npz),
    )
    write_model(
        model,
        mesh_npz=files.mesh_npz,
        mesh_msh=files.mesh_msh,
        mesh_vtu=files.mesh_vtu,
        model_json=files.model_json,
    )
    plot_model_qc(files.qc_png, model, pose)
    return model
