"""Aggregation across animals: tables, exclusion policy, VOI change, section sampling, figures."""

import numpy as np
import pandas as pd
import pytest
from study_meshes import box_tet10, centroids

from deeptissue.pose import Pose, save_pose
from deeptissue.report import (
    AggregateJob,
    SectionGrid,
    aggregate_study,
    exclusions,
    locate_points,
    sample_sections,
    section_frame,
    summary_tables,
    voi_changes,
)
from deeptissue.summary import (
    Summary,
    failed_summary,
    summarize_solution,
    write_result_vtu,
    write_summary,
)

LABELS = ["0.3-0.4", "0.4-0.5", "0.5-0.6", "0.6-0.7", "0.7-0.8", "0.8-0.9", "0.9-1.0", ">1.0"]
VARIANTS = ["sphere", "bar", "sphere_rx+15"]


def _ok(animal, variant, voi, first_bin=100.0):
    bins = dict.fromkeys(LABELS, 0.0)
    bins["0.3-0.4"], bins[">1.0"] = first_bin, 100.0 - first_bin
    return Summary(
        animal=animal,
        variant=variant,
        converged=True,
        voi_mm3=voi,
        bins_percent=bins,
        below_threshold_percent=90.0,
        peak_gamma=1.1,
        strain_energy_mJ=0.01,
        indenter_force_N=0.2,
        n_elements=100,
        n_dofs=900,
        increments=3,
        newton_iterations=12,
        wall_s=4.0,
        skin_mean_mm=0.1,
        skin_p95_mm=0.3,
    )


def _study():
    return [
        _ok("ratA", "sphere", 10.0, 60.0),
        _ok("ratA", "bar", 15.0),
        _ok("ratA", "sphere_rx+15", 8.0),
        _ok("ratB", "sphere", 20.0),
        failed_summary(
            animal="ratB", variant="bar", reason="inverted element at 40% depth", n_elements=100
        ),
        _ok("ratB", "sphere_rx+15", 22.0),
    ]


def test_tables_flag_the_whole_animal_when_one_variant_fails(tmp_path):
    voi, bins = summary_tables(_study(), animals=["ratA", "ratB"], variants=VARIANTS)
    assert list(zip(voi["animal"], voi["variant"])) == [
        (a, v) for a in ("ratA", "ratB") for v in VARIANTS
    ]
    assert voi.loc[voi["animal"] == "ratA", "excluded"].eq(False).all()
    b = voi[voi["animal"] == "ratB"]
    assert b["excluded"].all()
    assert b["exclusion_reason"].iloc[0] == "not converged: bar: inverted element at 40% depth"
    # a variant that was not solved because it is infeasible is named as such
    infeasible = failed_summary(
        animal="ratB",
        variant="bar",
        reason="infeasible: the indenter ends 0.2 mm inside the moved bone",
    )
    assert (
        exclusions([infeasible])["ratB"]
        == "bar: infeasible: the indenter ends 0.2 mm inside the moved bone"
    )
    both = exclusions(
        [infeasible, failed_summary(animal="ratB", variant="sphere", reason="line search failed")]
    )
    assert both["ratB"].startswith("not converged: bar: infeasible")
    assert (b["converged"].tolist(), b["voi_mm3"].iloc[0]) == ([True, False, True], 20.0)
    for col in [
        "voi_mm3",
        "below_threshold_percent",
        "peak_gamma",
        "strain_energy_mJ",
        "indenter_force_N",
        "n_elements",
        "n_dofs",
        "increments",
        "newton_iterations",
        "wall_s",
        "skin_mean_mm",
        "skin_p95_mm",
        "reason",
        "bins_percent.0.3-0.4",
        "bins_percent.>1.0",
    ]:
        assert col in voi.columns, col
    assert voi.loc[0, "bins_percent.0.3-0.4"] == 60.0 and voi.loc[0, "bins_percent.>1.0"] == 40.0
    assert "bins_percent" not in voi.columns and np.isnan(b["bins_percent.0.3-0.4"].iloc[1])
    assert len(bins) == 2 * 3 * len(LABELS)
    assert list(bins.columns) == ["animal", "variant", "bin", "percent", "err_pp", "excluded"]
    failed = bins[(bins["animal"] == "ratB") & (bins["variant"] == "bar")]
    assert list(failed["bin"]) == LABELS and failed["percent"].isna().all()
    a_sphere = bins[(bins["animal"] == "ratA") & (bins["variant"] == "sphere")].set_index("bin")[
        "percent"
    ]
    assert a_sphere["0.3-0.4"] == 60.0 and a_sphere.sum() == pytest.approx(100.0)

    all_failed = [failed_summary(animal="ratC", variant="sphere", reason="diverged")]
    _, b2 = summary_tables(all_failed, animals=["ratC"], variants=["sphere"], bin_edges=(0.3, 0.5))
    assert list(b2["bin"]) == ["0.3-0.5", ">0.5"] and b2["percent"].isna().all()

    with pytest.raises(ValueError, match="no summary for ratC/sphere"):
        summary_tables(_study(), animals=["ratA", "ratC"], variants=["sphere"])


def test_voi_change_against_the_estimated_orientation():
    voi, _ = summary_tables(_study(), animals=["ratA", "ratB"], variants=VARIANTS)
    ch = voi_changes(voi).set_index(["animal", "variant"])["voi_change_percent"]
    assert ch[("ratA", "bar")] == pytest.approx(50.0)
    assert ch[("ratA", "sphere_rx+15")] == pytest.approx(-20.0)
    assert ch[("ratB", "sphere_rx+15")] == pytest.approx(10.0)
    assert np.isnan(ch[("ratB", "bar")])  # not converged: undefined, not zero


def test_voi_change_carries_the_sum_of_the_two_error_estimates():
    def with_err(animal, variant, voi, err):
        return Summary(**{**_ok(animal, variant, voi).to_dict(), "voi_err_mm3": err})

    study = [
        with_err("ratA", "sphere", 10.0, 0.5),
        with_err("ratA", "sphere_rx+15", 11.0, 0.3),  # +1.0 against 0.8: larger than its error
        with_err("ratA", "sphere_rx-15", 9.5, 0.3),  # -0.5 against 0.8: within it
    ]
    voi, _ = summary_tables(
        study, animals=["ratA"], variants=["sphere", "sphere_rx+15", "sphere_rx-15"]
    )
    ch = voi_changes(voi).set_index("variant")
    assert ch.loc["sphere_rx+15", "change_mm3"] == pytest.approx(1.0)
    assert ch.loc["sphere_rx+15", "change_err_mm3"] == pytest.approx(0.8)
    assert ch.loc["sphere_rx+15", "change_err_percent"] == pytest.approx(8.0)
    assert ch["larger_than_error"].tolist() == [True, False]
    # without error estimates the comparison is undefined, never "larger"
    ch2 = voi_changes(voi.drop(columns="voi_err_mm3"))
    assert ch2["larger_than_error"].isna().all()


def test_tables_put_each_error_estimate_beside_its_number():
    s = Summary(
        **{
            **_ok("ratA", "sphere", 10.0).to_dict(),
            "voi_err_mm3": 0.4,
            "bins_err_pp": dict.fromkeys(LABELS, 0.7),
        }
    )
    voi, bins = summary_tables([s], animals=["ratA"], variants=["sphere"])
    cols = list(voi.columns)
    assert cols[cols.index("voi_mm3") + 1] == "voi_err_mm3"
    for label in LABELS:
        assert cols[cols.index(f"bins_percent.{label}") + 1] == f"bins_err_pp.{label}"
    assert bins["err_pp"].tolist() == [0.7] * len(LABELS)


def test_section_frame_contains_the_axis_and_follows_the_leg():
    axis = np.array([0.2, -1.0, 0.1])
    a, e, n = section_frame(axis)
    np.testing.assert_allclose(a, axis / np.linalg.norm(axis))
    np.testing.assert_allclose(np.array([a, e, n]) @ np.array([a, e, n]).T, np.eye(3), atol=1e-14)
    assert n[2] > 0.99 and abs(np.dot(n, a)) < 1e-14
    with pytest.raises(ValueError, match="parallel"):
        section_frame([0, 0, 1])


def test_point_location_matches_brute_force():
    m = box_tet10(np.linspace(0, 2, 4), np.linspace(0, 3, 5), [0, 0.5, 1.0, 2.0])
    rng = np.random.default_rng(2)
    P = rng.uniform([-0.5, -0.5, -0.5], [2.5, 3.5, 2.5], size=(3000, 3))
    found = locate_points(m, P)
    inside_box = np.all((P > 0) & (P < [2, 3, 2]), axis=1)
    assert np.array_equal(found >= 0, inside_box)
    # the found element contains the point: its barycentric coordinates (solved here directly) are >= 0
    c = m.nodes_mm[m.tets[found[inside_box], :4]]
    p = P[inside_box]
    for k in range(len(p)):
        lam = np.linalg.solve(np.vstack([c[k].T, np.ones(4)]), np.append(p[k], 1.0))
        assert lam.min() > -1e-9


def test_sections_sample_the_planes_through_the_axis():
    m = box_tet10(np.linspace(-5, 5, 21), np.linspace(0, 8, 17), np.linspace(-4, 4, 17))
    cz = centroids(m)
    tip = np.array([0.5, 8.0, 0.25])
    axis = np.array([0.0, -1.0, 0.0])  # into the leg from y = 8; planes have normal z
    s = sample_sections(
        m,
        cz[:, 2],
        axis=axis,
        tip_mm=tip,
        grid=SectionGrid(half_width_mm=3.0, v_range_mm=(-1.0, 5.0), resolution_mm=0.25),
    )
    assert s.values.shape == (7, len(s.v_mm), len(s.u_mm))
    np.testing.assert_allclose(s.offsets_mm, [-3, -2, -1, 0, 1, 2, 3])
    inside = s.v_mm >= 0  # v < 0 lies above the block (y > 8): no tissue
    assert np.isnan(s.values[:, ~inside]).all() and np.isfinite(s.values[:, inside]).all()
    # γ = element-centroid z: every sample within half an element (0.25 mm) of its plane's z
    for k, off in enumerate(s.offsets_mm):
        assert np.nanmax(np.abs(s.values[k] - (tip[2] + off))) <= 0.25 + 1e-12
    # across the plane the sampled field follows x (u along e = n × a = z × -y = +x)
    s2 = sample_sections(
        m,
        cz[:, 0],
        axis=axis,
        tip_mm=tip,
        grid=SectionGrid(half_width_mm=3.0, v_range_mm=(0.5, 4.0), resolution_mm=0.25),
    )
    assert np.max(np.abs(s2.values[3] - (tip[0] + s2.u_mm)[None, :])) <= 0.25 + 1e-12


@pytest.fixture
def synthetic_study(tmp_path):
    """Two animals, three variants; ratB's bar fails; ratA has result.vtu files for the sections."""
    m = box_tet10(np.linspace(-4, 4, 9), np.linspace(0, 6, 7), np.linspace(-4, 4, 9))
    pose = Pose(
        indenter_axis=[0, -1, 0],
        tip_start_mm=[0, 6, 0],
        tip_end_mm=[0, 4, 0],
        depth_mm=2.0,
        bone_com_mm=[0, 1, 0],
        bone_rotation_deg=[0, 0, 0],
        bone_translation_mm=[0, 0, 0],
    )
    save_pose(tmp_path / "ratA" / "pose.json", pose)
    y = m.nodes_mm[:, 1]
    paths, vtus = [], {}
    for s in _study():
        if (
            s.animal == "ratA"
        ):  # a real solution-like field: shear growing towards the indented face
            k = {"sphere": 0.8, "bar": 1.2, "sphere_rx+15": 0.6}[s.variant]
            u = np.column_stack([k * y**2 / 12, 0 * y, 0 * y])
            s, strain = summarize_solution(m, u, animal="ratA", variant=s.variant)
            vtus[s.variant] = tmp_path / "ratA" / s.variant / "result.vtu"
            write_result_vtu(vtus[s.variant], m, u, strain)
        p = tmp_path / s.animal / s.variant / "summary.json"
        write_summary(p, s)
        paths.append(p)
    outs = {
        k: tmp_path / "summary" / f"{k.rsplit('_', 1)[0]}.{k.rsplit('_', 1)[1]}"
        for k in [
            "voi_csv",
            "bins_csv",
            "voi_png",
            "bins_png",
            "voi_change_png",
            "sections_png",
            "orientations_png",
        ]
    }
    return paths, vtus, outs, tmp_path


@pytest.mark.slow
@pytest.mark.parametrize("figure_animal", ["ratA"])
def test_aggregate_study_writes_tables_and_figures(synthetic_study, figure_animal):
    paths, vtus, outs, root = synthetic_study
    aggregate_study(
        AggregateJob(
            summary_paths=paths,
            animals=["ratA", "ratB"],
            variants=VARIANTS,
            outputs=outs,
            figure_animal=figure_animal,
            figure_results=vtus,
            pose_path=root / "ratA" / "pose.json",
        )
    )
    voi = pd.read_csv(outs["voi_csv"])
    assert len(voi) == 6 and voi["excluded"].tolist() == [False] * 3 + [True] * 3
    bins = pd.read_csv(outs["bins_csv"])
    assert len(bins) == 6 * len(LABELS)
    for key in ["voi_png", "bins_png", "voi_change_png", "sections_png", "orientations_png"]:
        assert outs[key].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", key
