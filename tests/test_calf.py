"""The real scan (human calves, ../shared/data/calf): closed skin hugging the non-zero region, the tibia on every
slice (area, and a centroid that does not jump), the fibula along the slab (a centroid that does not jump), the leg
picked by a point, and the README's command through snakemake."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import ndimage
from skimage.measure import find_contours

from deeptissue.config import validate_config
from deeptissue.contours import (
    load_contours,
    point_to_polygon_distance,
    points_in_polygon,
    polygon_area_centroid,
)
from deeptissue.imaging import crop_volume, load_nifti, split_legs
from deeptissue.segment import SegmentationSettings, segment_volume

ROOT = Path(__file__).resolve().parents[1]
# CI clones the repository with shared/ beside it; DEEPTISSUE_SHARED may point elsewhere
SHARED = Path(os.environ.get("DEEPTISSUE_SHARED", ROOT.parent / "shared"))
SCAN = SHARED / "data" / "calf" / "water.nii.gz"

pytestmark = pytest.mark.skipif(
    not SCAN.is_file(), reason=f"real calf scan not found at {SCAN} (set DEEPTISSUE_SHARED)"
)


def _config():
    cfg = yaml.safe_load((ROOT / "config" / "calf.yaml").read_text())
    # the config names the scan relative to the repository; validate it where the scan is
    cfg = validate_config(
        cfg, ROOT / "workflow" / "schemas" / "config.schema.yaml", base_dir=SHARED
    )
    a = cfg["animals"]["calf"]
    return a, SegmentationSettings.from_config(cfg["segmentation"], a.get("segmentation"))


@pytest.fixture(scope="module")
def calf():
    a, settings = _config()
    vol = crop_volume(load_nifti(SCAN, animal="calf"), a["crop_mm"])
    contours, info = segment_volume(vol, settings=settings, state="pre")
    return vol, contours


def test_skin_closed_on_every_slice_and_hugs_the_nonzero_region(calf):
    vol, c = calf
    assert c.n_slices == vol.n_slices == 23
    px = vol.pixel_mm[0]
    for k in range(vol.n_slices):
        mask = ndimage.binary_fill_holes(vol.data[:, :, k] > 0)
        lab, n = ndimage.label(mask)
        mask = lab == 1 + np.argmax(ndimage.sum(mask, lab, range(1, n + 1)))
        edge = max(
            find_contours(mask.astype(float), 0.5), key=len
        )  # boundary of the non-zero region
        edge_xy = vol.world(np.column_stack([edge, np.full(len(edge), k)]))[:, :2]
        skin = c.skin[k, :, :2]
        # both ways: every skin point near the edge, every edge point near the skin
        assert point_to_polygon_distance(skin, edge_xy).max() <= px, f"slice {k}"
        assert point_to_polygon_distance(edge_xy, skin).max() <= px, f"slice {k}"


def test_tibia_inside_skin_anterior_and_matching_the_dark_region(calf):
    vol, c = calf
    px = vol.pixel_mm
    for k in range(vol.n_slices):
        img = vol.data[:, :, k]
        bone, skin = c.bone[k, :, :2], c.skin[k, :, :2]
        assert points_in_polygon(bone, skin).all()
        a_bone, cen = polygon_area_centroid(bone)
        a_skin, cen_skin = polygon_area_centroid(skin)
        assert cen[1] > cen_skin[1]  # the anterior (+y) side: the tibia, not the fibula
        # the dark region: pixels below 0.3 of the median leg intensity, connected to the contour's centroid
        leg = ndimage.binary_fill_holes(img > 0)
        dark = leg & (img < 0.3 * np.median(img[img > 0]))
        lab, _ = ndimage.label(dark)
        ij = np.round(vol.voxel([*cen, vol.world([0, 0, k])[2]])[:2]).astype(int)
        assert lab[ij[0], ij[1]] > 0, f"slice {k}: contour centroid not in a dark region"
        area_dark = (lab == lab[ij[0], ij[1]]).sum() * px[0] * px[1]
        assert a_bone == pytest.approx(area_dark, rel=0.10), f"slice {k}"


def test_tibia_centroid_does_not_jump(calf):
    # one bone 6 mm further along the leg moves by less than a pixel here (0.8 mm at most); the fibula lies
    # about 50 mm from the tibia, so a slice that took it (or a vessel) for the tibia moves the centroid far more
    vol, c = calf
    cen = np.array([polygon_area_centroid(c.bone[k, :, :2])[1] for k in range(vol.n_slices)])
    step_mm = np.linalg.norm(np.diff(cen, axis=0), axis=1)
    assert step_mm.max() < vol.pixel_mm[0], step_mm.round(2).tolist()


def test_fibula_centroid_does_not_jump(calf):
    # the fibula runs through the slab, moving by less than a pixel from slice to slice. On slice 22 its dark region
    # runs into a septum (not round: no candidate) and a 10 mm^2 dark spot 37 mm away is the only round dark region
    # left; taken slice by slice, that spot would be the fibula there
    vol, c = calf
    assert c.fibula is not None
    ks = [k for k in range(vol.n_slices) if np.isfinite(c.fibula[k]).all()]
    assert ks == list(range(vol.n_slices - 1)), ks
    cen = np.array([polygon_area_centroid(c.fibula[k, :, :2])[1] for k in ks])
    step_mm = np.linalg.norm(np.diff(cen, axis=0), axis=1)
    assert step_mm.max() < vol.pixel_mm[0], step_mm.round(2).tolist()
    tibia = np.array([polygon_area_centroid(c.bone[k, :, :2])[1] for k in ks])
    assert (cen[:, 1] < tibia[:, 1]).all()  # posterior to the tibia
    area = np.array([polygon_area_centroid(c.fibula[k, :, :2])[0] for k in ks])
    assert area.max() < 1.5 * area.min(), area.round(1).tolist()


def test_a_point_in_the_leg_gives_the_crop_box_contours(calf):
    # both legs in the box; the point inside the leg at lower x picks the same leg the config's crop box holds
    vol, c = calf
    a, settings = _config()
    both = crop_volume(load_nifti(SCAN, animal="calf"), [[300.0, 700.0], *a["crop_mm"][1:]])
    picked, _ = segment_volume(
        split_legs(both, [400.0, 460.0, 130.0]).leg, settings=settings, state="pre"
    )
    np.testing.assert_allclose(picked.skin, c.skin, atol=1e-9)
    np.testing.assert_allclose(picked.bone, c.bone, atol=1e-9)


def _clone_beside_the_data(tmp_path):
    """The workflow's files in tmp_path/deeptissue with the shared data at tmp_path/shared, as in a clean clone."""
    repo = tmp_path / "deeptissue"
    repo.mkdir()
    for name in ("workflow", "config"):
        shutil.copytree(ROOT / name, repo / name)
    shutil.copy(ROOT / "Snakefile", repo)
    (tmp_path / "shared").symlink_to(SHARED.resolve(), target_is_directory=True)
    return repo


@pytest.mark.slow
def test_the_readme_command_runs_through_snakemake(calf, tmp_path):
    repo = _clone_beside_the_data(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    snakemake = [sys.executable, "-m", "snakemake"]
    r = subprocess.run(
        [
            *snakemake,
            "--cores",
            "2",
            "--configfile",
            "config/calf.yaml",
        ],
        cwd=repo,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert (repo / "results/calf/qc/segmentation_pre.png").stat().st_size > 0
    # every check of the pre-only animal in one table, every one ok
    rows = (repo / "results/calf/qc/checks.csv").read_text().splitlines()
    assert rows[0].startswith("stage,check,slice") and len(rows) > 23
    assert all(r.startswith("segmentation_pre,") and ",fail," not in r for r in rows[1:])
    np.testing.assert_allclose(
        load_contours(repo / "results/calf/contours/pre.npz").bone, calf[1].bone
    )
    # a second run does nothing: the default target of a pre-only study segments and solves nothing
    r = subprocess.run(
        [*snakemake, "-n", "--cores", "2", "--configfile", "config/calf.yaml"],
        cwd=repo,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Nothing to be done" in r.stdout + r.stderr
    # the study is pre-only: only the convergence target, when asked for, says it has nothing to run on
    r = subprocess.run(
        [*snakemake, "-n", "convergence", "--cores", "2", "--configfile", "config/calf.yaml"],
        cwd=repo,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0
    assert (
        "config key convergence.animals: null, and no configured animal has a during scan ['calf']"
        in r.stdout + r.stderr
    )


ANKLE = SHARED / "data" / "calf_ankle" / "water.nii.gz"


@pytest.mark.skipif(not ANKLE.is_file(), reason=f"calf_ankle scan not found at {ANKLE}")
def test_calf_ankle_tibia_not_fibula_and_skin_on_the_masked_edge(tmp_path):
    # config/calf_ankle.yaml: a masked Dixon scan whose tibia opens into zeroed fat, one leg picked by a point
    from deeptissue.segment import SegmentationError, SegmentJob, segment_files

    cfg = yaml.safe_load((ROOT / "config" / "calf_ankle.yaml").read_text())
    cfg = validate_config(
        cfg, ROOT / "workflow" / "schemas" / "config.schema.yaml", base_dir=SHARED
    )
    a = cfg["animals"]["calf_ankle"]
    settings = {**cfg["segmentation"], **a["segmentation"]}
    job = SegmentJob(
        image=ANKLE,
        contours_out=tmp_path / "pre.npz",
        qc_out=tmp_path / "qc.png",
        checks_out=tmp_path / "checks.csv",
        animal="calf_ankle",
        settings=settings,
        leg_point_mm=a["leg_point_mm"],
    )
    c = segment_files(job)
    assert c.n_slices == 26  # slices 5-30; 0-4 (into the ankle joint) left out
    areas = []
    for k in range(c.n_slices):
        a_t, cen_t = polygon_area_centroid(c.bone[k, :, :2])
        areas.append(a_t)
        assert cen_t[0] < -40.0  # the picked leg (lower x)
        if c.fibula is not None and np.isfinite(c.fibula[k]).all():
            a_f, cen_f = polygon_area_centroid(c.fibula[k, :, :2])
            assert cen_t[1] > cen_f[1] and a_t > 2 * a_f, k  # anterior and larger: the tibia
    # slices 7-11, where a septum joins the tibia's dark region to the fibula's, are parted: from slice 6 the tibia's
    # area falls steadily from the ankle's flare (about 1750 mm^2) to the shaft (650 mm^2 on slice 12), by at most
    # 25 % a slice (the joined regions fall by 29 % from slice 8 to 9 and 31 % from 11 to 12)
    steps = np.diff(np.log(areas[1:8]))
    assert np.all(steps < 0.0) and np.all(steps > -0.25), np.round(areas[:8])
    rows = [r.split(",") for r in (tmp_path / "checks.csv").read_text().splitlines()[1:]]
    skin = [float(r[2]) for r in rows if r[0] == "skin_to_mask_mm"]
    assert len(skin) == 26 and max(skin) <= 1.5, skin  # median per slice, one pixel
    assert [int(r[1]) for r in rows if r[0] == "slice_left_out" and r[4] == "warn"] == [
        0,
        1,
        2,
        3,
        4,
    ]
    assert not [r for r in rows if r[4] == "fail"]
    # refused by default: the ankle slices are named in one refusal, with the figure of the failed run
    full = SegmentJob(
        **{
            **job.__dict__,
            "settings": {**settings, "end_slices": "refuse"},
            "leg_point_mm": [-60.0, 0.0, 0.0],
        }
    )
    with pytest.raises(
        SegmentationError,
        match=r"3 of 31 slices cannot be segmented \(slices 1, 3, 4, z -87\.0 to -69\.0 mm\)",
    ):
        segment_files(full)
    assert (tmp_path / "qc_failed.png").stat().st_size > 10_000
