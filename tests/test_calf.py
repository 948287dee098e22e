"""The real scan (human calves, ../shared/data/calf): closed skin hugging the non-zero region, tibia area."""

import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import ndimage
from skimage.measure import find_contours

from deeptissue.config import validate_config
from deeptissue.contours import point_to_polygon_distance, points_in_polygon, polygon_area_centroid
from deeptissue.imaging import crop_volume, load_nifti
from deeptissue.segment import SegmentationSettings, segment_volume

ROOT = Path(__file__).resolve().parents[1]
# CI clones the repository with shared/ beside it; DEEPTISSUE_SHARED may point elsewhere
SHARED = Path(os.environ.get("DEEPTISSUE_SHARED", ROOT.parent / "shared"))
SCAN = SHARED / "data" / "calf" / "water.nii.gz"

pytestmark = pytest.mark.skipif(not SCAN.is_file(), reason=f"real calf scan not found at {SCAN} (set DEEPTISSUE_SHARED)")


@pytest.fixture(scope="module")
def calf():
    cfg = yaml.safe_load((ROOT / "config" / "calf.yaml").read_text())
    # the config names the scan relative to the repository; validate it where the scan is
    cfg = validate_config(cfg, ROOT / "workflow" / "schemas" / "config.schema.yaml", base_dir=SHARED)
    a = cfg["animals"]["calf"]
    vol = crop_volume(load_nifti(SCAN, animal="calf"), a["crop_mm"])
    settings = SegmentationSettings.from_config(cfg["segmentation"], a.get("segmentation"))
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
        edge = max(find_contours(mask.astype(float), 0.5), key=len)  # boundary of the non-zero region
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
