"""The ladder of discretisations and the accuracy goal.

A :class:`Discretisation` is one setting of the ladder (global element size, local refinement near
the indenter or none, element order, Newton and contact tolerances); settings of one *family* differ
only in size (or, for the tolerance family, only in tolerance) and are the lines of the error-vs-time
plot. :func:`default_ladder` builds the ladder of config ``convergence`` around the configured
default; :class:`AccuracyGoal` is what "accurate enough" means for the study's outputs.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

log = logging.getLogger(__name__)

# Element orders the mesh, assembly and contact code support: 4-node (model.element_order 1) and
# 10-node (2) tetrahedra.
SUPPORTED_ELEMENT_ORDERS = (1, 2)


@dataclass(frozen=True)
class AccuracyGoal:
    """The accuracy goal (config ``convergence.goal``): VOI within 2 %, every bin within 1 pp, force
    within 2 % of the reference, the finest converged run of the variant."""

    voi_rel_error: float = 0.02
    bin_error_pp: float = 1.0
    force_rel_error: float = 0.02


@dataclass(frozen=True)
class Discretisation:
    """One setting of the ladder.

    element_size_mm: global element size; refine_size_mm: element size near the indenter travel
    (None: no local refinement); element_order: 1 (4-node) or 2 (10-node tetrahedra); rtol: Newton
    residual tolerance at step ends (``fem.solver.newton.rtol``); gap_tol_rel: contact gap tolerance over
    facet size (``fem.solver.contact.gap_tol_rel``); tolerance: the name of that tolerance pair; family: the
    plot line the setting belongs to.
    """

    name: str
    family: str
    element_size_mm: float
    refine_size_mm: float | None = None
    element_order: int = 2
    rtol: float = 1e-6
    gap_tol_rel: float = 1e-3
    tolerance: str = "default"

    def __post_init__(self):
        if self.element_order not in (1, 2):
            raise ValueError(
                f"setting {self.name}: element_order must be 1 or 2, got {self.element_order}"
            )
        if not self.element_size_mm > 0 or (
            self.refine_size_mm is not None and not self.refine_size_mm > 0
        ):
            raise ValueError(f"setting {self.name}: element sizes must be > 0")
        if not (self.rtol > 0 and self.gap_tol_rel > 0):
            raise ValueError(f"setting {self.name}: tolerances must be > 0")

    @property
    def mesh_key(self) -> str:
        """Identifies the mesh (order and sizes): settings with the same key differ only in tolerance."""
        r = "none" if self.refine_size_mm is None else f"{self.refine_size_mm:g}"
        return f"p{self.element_order}_h{self.element_size_mm:g}_r{r}"

    def model_settings(self, model_cfg: dict | None = None) -> dict:
        """The ``model`` config with this setting's sizes (no refinement: refine size = global size)
        and element order (``model.element_order``)."""
        d = dict(model_cfg or {})
        d["element_order"] = int(self.element_order)
        d["element_size_mm"] = float(self.element_size_mm)
        d["refine_size_mm"] = float(
            self.element_size_mm if self.refine_size_mm is None else self.refine_size_mm
        )
        return d

    def solver_config(self, solver_cfg: dict | None = None) -> dict:
        """The ``fem.solver`` config with this setting's tolerances."""
        d = dict(solver_cfg or {})
        d["newton"] = {**dict(d.get("newton") or {}), "rtol": float(self.rtol)}
        d["contact"] = {**dict(d.get("contact") or {}), "gap_tol_rel": float(self.gap_tol_rel)}
        return d

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Discretisation:
        return cls(**d)


def setting_name(
    *,
    element_size_mm: float,
    refine_size_mm: float | None,
    element_order: int = 2,
    tolerance: str = "default",
) -> str:
    """Wildcard-safe name, e.g. ``p2_h1.2`` (uniform), ``p2_h1_r0.5`` (refined), ``p2_h1_r0.5_tight``."""
    name = f"p{element_order}_h{element_size_mm:g}"
    if refine_size_mm is not None:
        name += f"_r{refine_size_mm:g}"
    if tolerance != "default":
        name += f"_{tolerance}"
    return name


@dataclass(frozen=True)
class Ladder:
    """The settings to run, the name of the one equal to the configured default, and notes."""

    settings: tuple
    default_name: str
    notes: tuple = ()

    def by_name(self, name: str) -> Discretisation:
        for s in self.settings:
            if s.name == name:
                return s
        raise KeyError(
            f"convergence: no setting named {name!r}; known: {[s.name for s in self.settings]}"
        )

    @property
    def names(self) -> list:
        return [s.name for s in self.settings]


def default_ladder(
    conv_cfg: dict | None = None, *, model_cfg: dict | None = None, solver_cfg: dict | None = None
) -> Ladder:
    """The ladder of config ``convergence`` around the configured default (``model``, ``fem.solver``).

    Families, each at every supported order of ``element_orders``: ``P<o> uniform``
    (``element_sizes_mm``, no local refinement), ``P<o> refined x<ratio>`` (``refined_element_sizes_mm``
    with refinement ``refine_ratio`` x size), ``P<o> tolerance`` (the configured default mesh at each
    of ``tolerances``), and the configured default itself (family ``P<o> default`` if it is not
    already one of the above). Sizes use the ``default`` tolerance (``fem.solver.newton.rtol`` /
    ``fem.solver.contact.gap_tol_rel``).

    Parameters
    ----------
    conv_cfg, model_cfg, solver_cfg : dict, optional
        The config sections ``convergence``, ``model`` and ``fem.solver`` (missing keys: the
        defaults of :class:`deeptissue.model.ModelSettings` and of the schema).

    Returns
    -------
    Ladder
        The settings (duplicates merged by name), the name of the configured default, and a note for
        each element order left out because the mesh/FE code does not support it.

    Raises
    ------
    ValueError
        If none of ``element_orders`` is supported.
    """
    c = dict(conv_cfg or {})
    m = dict(model_cfg or {})
    sv = dict(solver_cfg or {})
    from ..fem.solver import solver_settings_from_config

    base = solver_settings_from_config(sv)
    base_rtol, base_gap = base.newton.rtol, base.contact.gap_tol_rel
    from ..model import ModelSettings  # the model stage's defaults, one definition

    h0 = float(m.get("element_size_mm", ModelSettings.element_size_mm))
    r0 = float(m.get("refine_size_mm", ModelSettings.refine_size_mm))
    r0 = None if r0 >= h0 else r0
    tols = {}
    for t in c.get("tolerances", [{"name": "default"}]):
        tols[t["name"]] = (float(t.get("rtol", base_rtol)), float(t.get("gap_tol_rel", base_gap)))
    tols.setdefault("default", (base_rtol, base_gap))
    ratio = float(c.get("refine_ratio", 0.5))
    notes = []
    orders = []
    for o in c.get("element_orders", [1, 2]):
        if o in SUPPORTED_ELEMENT_ORDERS:
            orders.append(int(o))
        else:
            notes.append(
                f"element order {o} left out: the mesh/FE code supports orders {list(SUPPORTED_ELEMENT_ORDERS)} only"
            )
            log.info("convergence: %s", notes[-1])
    if not orders:
        raise ValueError(
            f"config key convergence.element_orders: none of {c.get('element_orders')} is supported "
            f"(supported: {list(SUPPORTED_ELEMENT_ORDERS)})"
        )
    out: dict = {}

    def add(family, h, r, order, tol):
        rt, pt = tols[tol]
        name = setting_name(
            element_size_mm=h, refine_size_mm=r, element_order=order, tolerance=tol
        )
        if name not in out:
            out[name] = Discretisation(
                name=name,
                family=family,
                element_size_mm=float(h),
                refine_size_mm=r,
                element_order=order,
                rtol=rt,
                gap_tol_rel=pt,
                tolerance=tol,
            )
        return name

    for o in orders:
        for h in c.get("element_sizes_mm", [1.6, 1.2, 0.9, 0.7, 0.5]):
            add(f"P{o} uniform", float(h), None, o, "default")
        for h in c.get("refined_element_sizes_mm", [1.6, 1.2, 1.0, 0.7]):
            r = round(ratio * float(h), 6)
            add(f"P{o} refined x{ratio:g}", float(h), r if r < float(h) else None, o, "default")
        add(f"P{o} default", h0, r0, o, "default")
        for t in tols:
            add(f"P{o} tolerance", h0, r0, o, t)
    o = int(m.get("element_order", 2))
    if o not in orders:
        o = 2 if 2 in orders else orders[0]
    default_name = setting_name(element_size_mm=h0, refine_size_mm=r0, element_order=o)
    return Ladder(settings=tuple(out.values()), default_name=default_name, notes=tuple(notes))
