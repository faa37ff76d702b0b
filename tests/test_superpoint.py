"""SuperPoint + SuperGlue backend: published key names, decoding geometry, Sinkhorn, batching, errors.

The public weights are not redistributable, so these tests write randomly initialised weights
(fixed seed) to files and load them through the real path; they check the architecture and the
machinery, not the matching quality of the trained networks.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

pytestmark = pytest.mark.usefixtures("torch_one_thread")

from conftest import naip_path  # noqa: E402

from orthonav.errors import OrthonavError  # noqa: E402
from orthonav.features import FeatureSet, available_backends, create_backend  # noqa: E402
from orthonav.features.superpoint import (  # noqa: E402
    SuperGlueNet,
    SuperPointBackend,
    SuperPointNet,
    keypoints_from_logits,
    log_optimal_transport,
    mutual_matches,
    sample_descriptors,
    simple_nms,
)
from orthonav.geo import GeoRaster  # noqa: E402
from orthonav.geo.raster import PixelWindow  # noqa: E402

SUPERPOINT_KEYS = [
    f"{name}.{kind}"
    for name in (
        "conv1a",
        "conv1b",
        "conv2a",
        "conv2b",
        "conv3a",
        "conv3b",
        "conv4a",
        "conv4b",
        "convPa",
        "convPb",
        "convDa",
        "convDb",
    )
    for kind in ("weight", "bias")
]
MAX_KEYPOINTS = 256  # keeps 100 Sinkhorn iterations cheap on CPU
BORDER = 4


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Random but fixed weight files: a full-size SuperPoint and a 2-layer SuperGlue.

    SuperPoint's convolutions get He initialisation and zero biases: with torch's default
    init every descriptor of an image points the same way and nothing could be matched.
    """
    out = tmp_path_factory.mktemp("weights")
    torch.manual_seed(0)
    superpoint = SuperPointNet()
    for module in superpoint.modules():
        if isinstance(module, torch.nn.Conv2d):
            torch.nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
            torch.nn.init.zeros_(module.bias)
    torch.save(superpoint.state_dict(), out / "superpoint.pth")
    torch.save(SuperGlueNet(gnn_layers=2).state_dict(), out / "superglue.pth")
    return out / "superpoint.pth", out / "superglue.pth"


def make_backend(weights: tuple[Path, Path], **conf) -> SuperPointBackend:
    # Random SuperGlue weights give near-uniform match probabilities, far below the
    # published 0.2 threshold: keep every mutual nearest neighbour instead.
    conf = {"gnn_layers": 2, "max_keypoints": MAX_KEYPOINTS, "match_threshold": 0.0, **conf}
    backend = create_backend(
        "superpoint", superpoint_weights=weights[0], superglue_weights=weights[1], **conf
    )
    assert isinstance(backend, SuperPointBackend)
    return backend


@pytest.fixture(scope="module")
def backend(weights: tuple[Path, Path]) -> SuperPointBackend:
    return make_backend(weights)


@pytest.fixture(scope="module")
def naip_gray() -> np.ndarray:
    """A 240 x 320 grayscale crop of the real NAIP 2020 orthophoto."""
    with GeoRaster(naip_path("20200831")) as raster:
        rgb = raster.read_rgb(PixelWindow(300, 250, 320, 240))
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    assert gray.std() > 5, "the crop should show fields and roads, not nodata"
    return gray


@pytest.fixture(scope="module")
def features(backend: SuperPointBackend, naip_gray: np.ndarray) -> FeatureSet:
    return backend.extract(naip_gray)


# --- architecture ---------------------------------------------------------------------------


def test_superpoint_keys_are_the_published_ones() -> None:
    """The state dict keys are exactly those of superpoint_v1.pth, with the published shapes."""
    state = SuperPointNet().state_dict()
    assert list(state) == SUPERPOINT_KEYS
    assert state["conv1a.weight"].shape == (64, 1, 3, 3)
    assert state["conv3a.weight"].shape == (128, 64, 3, 3)
    assert state["convPb.weight"].shape == (65, 256, 1, 1)
    assert state["convDb.weight"].shape == (256, 256, 1, 1)


def test_superglue_keys_and_size_are_the_published_ones() -> None:
    """18 GNN layers with the reference names; about 12 M parameters as in the paper."""
    net = SuperGlueNet()
    state = net.state_dict()
    for key in (
        "kenc.encoder.0.weight",
        "kenc.encoder.1.running_var",
        "kenc.encoder.12.bias",
        "gnn.layers.0.attn.merge.weight",
        "gnn.layers.0.attn.proj.0.weight",
        "gnn.layers.0.attn.proj.2.bias",
        "gnn.layers.0.mlp.1.running_mean",
        "gnn.layers.17.mlp.3.bias",
        "final_proj.weight",
        "final_proj.bias",
        "bin_score",
    ):
        assert key in state, key
    assert state["kenc.encoder.0.weight"].shape == (32, 3, 1)
    assert state["gnn.layers.5.mlp.0.weight"].shape == (512, 512, 1)
    assert state["gnn.layers.5.mlp.3.weight"].shape == (256, 512, 1)
    assert state["bin_score"].shape == ()
    assert not any(k.startswith("gnn.layers.18.") for k in state)
    assert net.gnn.names == ["self", "cross"] * 9
    params = sum(p.numel() for p in net.parameters())
    assert 11.9e6 < params < 12.1e6, params


# --- detection and description --------------------------------------------------------------


@pytest.mark.parametrize(("cell", "channel"), [((0, 0), 0), ((3, 5), 19), ((7, 9), 63), ((9, 1), 56)])
def test_detector_decoding_is_pixel_exact(cell: tuple[int, int], channel: int) -> None:
    """A logit peak in channel 8 dy + dx of cell (i, j) becomes the keypoint (8 j + dx, 8 i + dy)."""
    logits = torch.zeros(1, 65, 10, 12)
    logits[0, 64] = 20.0  # the dustbin ("no keypoint") wins everywhere but at the peak
    i, j = cell
    logits[0, channel, i, j] = 30.0
    kpts, scores = keypoints_from_logits(logits, (96, 80), threshold=0.005, nms_radius=4, border=0)
    assert kpts.tolist() == [[8 * j + channel % 8, 8 * i + channel // 8]]
    assert scores.item() > 0.99


def test_decoding_drops_borders_and_padding() -> None:
    """The same peaks, kept or dropped by the border and by the true (unpadded) image size."""
    logits = torch.zeros(1, 65, 10, 12)
    logits[0, 64] = 20.0
    logits[0, 2 * 8 + 2, 0, 0] = 30.0  # (2, 2): inside a 4 px border
    logits[0, 3 * 8 + 4, 4, 5] = 30.0  # (44, 35)
    logits[0, 7 * 8 + 7, 9, 11] = 30.0  # (95, 79): the last pixel of the padded map
    kpts, _ = keypoints_from_logits(logits, (96, 80), 0.005, 4, border=0)
    assert sorted(map(tuple, kpts.tolist())) == [(2, 2), (44, 35), (95, 79)]
    kpts, _ = keypoints_from_logits(logits, (96, 80), 0.005, 4, border=4)
    assert kpts.tolist() == [[44, 35]]
    kpts, _ = keypoints_from_logits(logits, (90, 75), 0.005, 4, border=0)  # the image is smaller
    assert sorted(map(tuple, kpts.tolist())) == [(2, 2), (44, 35)]


def test_nms_keeps_only_the_strongest_within_the_radius() -> None:
    """Peaks 3 px apart (radius 4): the weaker goes; 5 px apart: both stay."""
    scores = torch.zeros(1, 40, 40)
    scores[0, 10, 10], scores[0, 10, 13] = 0.9, 0.8
    scores[0, 30, 30], scores[0, 30, 35] = 0.7, 0.6
    kept = torch.nonzero(simple_nms(scores, 4)[0]).tolist()
    assert kept == [[10, 10], [30, 30], [30, 35]]
    assert torch.nonzero(simple_nms(scores, 2)[0]).tolist() == [[10, 10], [10, 13], [30, 30], [30, 35]]


def test_descriptor_sampling_follows_the_reference_mapping() -> None:
    """Bilinear sampling at (x - 3.5) / (8 w - 4.5) of the coarse width, per axis, as in the reference."""
    h, w = 6, 10
    rows, cols = torch.meshgrid(
        torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij"
    )
    coarse = torch.stack([cols, rows, torch.ones(h, w)])[None]  # ramps in x and y, and a constant
    kpts = torch.tensor([[4.0, 4.0], [20.0, 13.0], [50.0, 30.0], [79.0, 47.0]])
    desc = sample_descriptors(kpts, coarse)
    assert desc.shape == (4, 3)
    np.testing.assert_allclose(desc.norm(dim=1).numpy(), 1.0, rtol=1e-6)
    expected_col = (kpts[:, 0].numpy() - 3.5) / (8 * w - 4.5) * (w - 1)
    expected_row = (kpts[:, 1].numpy() - 3.5) / (8 * h - 4.5) * (h - 1)
    np.testing.assert_allclose((desc[:, 0] / desc[:, 2]).numpy(), expected_col, rtol=1e-5)
    np.testing.assert_allclose((desc[:, 1] / desc[:, 2]).numpy(), expected_row, rtol=1e-5)


def test_extract_on_real_naip(
    backend: SuperPointBackend, naip_gray: np.ndarray, features: FeatureSet
) -> None:
    """Keypoints inside the image and off its border, at most max_keypoints, unit-norm 256-d float32."""
    h, w = naip_gray.shape
    kp = features.keypoints
    assert 50 <= len(features) <= MAX_KEYPOINTS
    assert kp.dtype == np.float32 and kp.shape == (len(features), 2)
    assert np.all(kp >= BORDER) and np.all(kp[:, 0] < w - BORDER) and np.all(kp[:, 1] < h - BORDER)
    assert np.array_equal(kp, np.round(kp)), "SuperPoint keypoints are pixel centres"
    assert features.descriptors.dtype == np.float32 and features.descriptors.shape == (len(features), 256)
    np.testing.assert_allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, rtol=1e-5)
    assert features.scores.dtype == np.float32
    assert np.all(features.scores > backend.conf["keypoint_threshold"])
    assert np.all(np.diff(features.scores) <= 0), "strongest first"
    assert features.image_size == (w, h)
    assert len(np.unique(kp, axis=0)) == len(kp)


def test_extract_is_deterministic(
    backend: SuperPointBackend, naip_gray: np.ndarray, features: FeatureSet
) -> None:
    again = backend.extract(naip_gray)
    assert np.array_equal(again.keypoints, features.keypoints)
    assert np.array_equal(again.descriptors, features.descriptors)
    assert np.array_equal(again.scores, features.scores)


def test_extract_pads_odd_sizes(backend: SuperPointBackend, naip_gray: np.ndarray) -> None:
    """A 237 x 317 image (not a multiple of 8) is padded, and nothing is found in the padding."""
    gray = np.ascontiguousarray(naip_gray[:237, :317])
    found = backend.extract(gray)
    assert len(found) > 50
    assert found.image_size == (317, 237)
    assert found.keypoints[:, 0].max() < 317 - BORDER and found.keypoints[:, 1].max() < 237 - BORDER


def test_extract_respects_mask(
    backend: SuperPointBackend, naip_gray: np.ndarray, features: FeatureSet
) -> None:
    """Keypoints only where the mask allows; the mask applies before the top-k, so the budget is used."""
    assert np.any(features.keypoints[:, 0] < 160), "unmasked, keypoints lie on both halves"
    mask = np.zeros_like(naip_gray)
    mask[:, 160:] = 255
    masked = backend.extract(naip_gray, mask)
    assert len(masked) == MAX_KEYPOINTS
    assert np.all(masked.keypoints[:, 0] >= 160)
    with pytest.raises(OrthonavError, match="mask shape"):
        backend.extract(naip_gray, mask[:100])


def test_tiny_or_flat_image_gives_empty_set(backend: SuperPointBackend) -> None:
    found = backend.extract(np.zeros((6, 6), np.uint8))
    assert len(found) == 0 and found.descriptors.shape == (0, 256) and found.image_size == (6, 6)


# --- matching -------------------------------------------------------------------------------


def test_sinkhorn_recovers_one_to_one_structure() -> None:
    """Identity-like scores give the identity matches; a pair best left in the dustbin stays unmatched."""
    scores = torch.full((5, 6), -10.0)
    for i in range(4):
        scores[i, i] = 10.0
    scores[4, 4] = -5.0  # mutual nearest neighbours, but far below the dustbin score
    z = log_optimal_transport(scores[None], torch.tensor(1.0), 100)
    assert z.shape == (1, 6, 7)
    indices, confidence = mutual_matches(z, 0.2)
    assert indices[0].tolist() == [0, 1, 2, 3, -1]
    assert torch.all(confidence[0, :4] > 0.9)
    assert z[0, 4, -1].exp() > 0.99, "row 4 goes to the dustbin"
    # Rows and columns of the transport plan (probabilities) sum to 1, except the dustbins.
    p = z[0].exp()
    np.testing.assert_allclose(p[:-1].sum(1).numpy(), 1.0, rtol=1e-4)
    np.testing.assert_allclose(p[:, :-1].sum(0).numpy(), 1.0, rtol=1e-4)


def test_gnn_masks_keep_padding_out() -> None:
    """A padded batch with masks gives the same GNN output as the unpadded pair."""
    torch.manual_seed(1)
    net = SuperGlueNet(gnn_layers=4).eval()
    m, n, pad = 7, 5, 4
    k0, s0, d0 = torch.rand(1, m, 2), torch.rand(1, m), torch.randn(1, 256, m)
    k1, s1, d1 = torch.rand(1, n, 2), torch.rand(1, n), torch.randn(1, 256, n)
    with torch.inference_mode():
        ref0, ref1 = net.propagate(k0, s0, d0, k1, s1, d1)
        padded = (
            torch.cat([k1, torch.rand(1, pad, 2)], 1),
            torch.cat([s1, torch.rand(1, pad)], 1),
            torch.cat([d1, 5 * torch.randn(1, 256, pad)], 2),
        )
        mask = torch.arange(n + pad)[None] < n
        out0, out1 = net.propagate(k0, s0, d0, *padded, mask)
        leaky0, _ = net.propagate(k0, s0, d0, *padded, None)
    torch.testing.assert_close(out0, ref0, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out1[..., :n], ref1, rtol=1e-5, atol=1e-5)
    assert not torch.allclose(leaky0, ref0, atol=1e-3), "without the mask, padding would change the result"


def test_matches_layout(backend: SuperPointBackend, features: FeatureSet) -> None:
    """Index pairs inside both sets, one-to-one, distances 1 - confidence in [0, 1] best first."""
    matches = backend.match(features, features)
    assert len(matches) > 10
    pairs = matches.pairs
    assert pairs.dtype == np.int64 and pairs.shape == (len(matches), 2)
    assert np.all(pairs >= 0) and np.all(pairs < len(features))
    assert len(np.unique(pairs[:, 0])) == len(pairs) and len(np.unique(pairs[:, 1])) == len(pairs)
    d = matches.distances
    assert d.dtype == np.float32 and np.all((d >= 0) & (d <= 1)) and np.all(np.diff(d) >= 0)


def test_max_matches_caps_the_best(
    weights: tuple[Path, Path], backend: SuperPointBackend, features: FeatureSet
) -> None:
    everything = backend.match(features, features)
    assert len(everything) > 5
    capped = make_backend(weights, max_matches=5).match(features, features)
    assert np.array_equal(capped.pairs, everything.pairs[:5])


def test_match_threshold_filters(weights: tuple[Path, Path], features: FeatureSet) -> None:
    """The published threshold (0.2) removes every near-uniform match of the random network."""
    assert len(make_backend(weights, match_threshold=0.2).match(features, features)) == 0


def test_batched_equals_one_by_one(
    backend: SuperPointBackend, naip_gray: np.ndarray, features: FeatureSet
) -> None:
    """One padded pass over tiles of different sizes gives the pairs of matching each on its own."""
    tiles = [
        backend.extract(np.ascontiguousarray(naip_gray[40:200, 30:290])),
        backend.extract(np.ascontiguousarray(naip_gray[:72, :96])),
        features.subset(np.arange(40)),
        features.subset(np.array([3])),  # fewer than 2 keypoints: no matches
    ]
    sizes = [len(t) for t in tiles]
    assert len(set(sizes[:3])) == 3, f"tiles should differ in size to exercise padding: {sizes}"
    batched = backend.match_many(features, tiles)
    assert len(batched) == len(tiles)
    for tile, together in zip(tiles, batched, strict=True):
        alone = backend.match(features, tile)
        assert np.array_equal(together.pairs, alone.pairs)
        np.testing.assert_allclose(together.distances, alone.distances, atol=1e-6)
    assert all(len(m) > 0 for m in batched[:3])
    assert len(batched[3]) == 0


def test_too_few_keypoints_give_no_matches(backend: SuperPointBackend, features: FeatureSet) -> None:
    one = features.subset(np.array([0]))
    assert len(backend.match(one, features)) == 0
    assert len(backend.match(features, one)) == 0
    assert backend.match_many(features, []) == []


# --- configuration and errors ----------------------------------------------------------------


def test_registry_creates_the_backend(backend: SuperPointBackend) -> None:
    assert "superpoint" in available_backends()
    assert backend.name == "superpoint"
    assert backend.rotation_invariant is False
    assert backend.descriptor_size == 256 and backend.descriptor_dtype == np.float32
    assert backend.conf["gnn_layers"] == 2 and backend.conf["nms_radius"] == 4
    assert not backend.superpoint.training and not backend.superglue.training


@pytest.mark.parametrize("given", [{}, {"superpoint_weights": "superpoint_v1.pth"}])
def test_missing_weights_explain_how_to_supply_them(given: dict) -> None:
    with pytest.raises(
        OrthonavError, match=r"not redistributable.*--weights superpoint_v1\.pth,superglue"
    ) as err:
        create_backend("superpoint", **given)
    assert "superpoint_weights=" in str(err.value) and "superglue_weights=" in str(err.value)


def test_nonexistent_weight_file(weights: tuple[Path, Path], tmp_path: Path) -> None:
    with pytest.raises(OrthonavError, match=r"SuperPoint weights .*nope\.pth: no such file"):
        create_backend("superpoint", superpoint_weights=tmp_path / "nope.pth", superglue_weights=weights[1])


def test_superglue_file_as_superpoint_weights(weights: tuple[Path, Path]) -> None:
    with pytest.raises(OrthonavError, match=r"SuperPoint weights .*superglue\.pth: not this architecture"):
        create_backend(
            "superpoint", superpoint_weights=weights[1], superglue_weights=weights[1], gnn_layers=2
        )


@pytest.mark.parametrize("layers", [1, 4, 18])
def test_superglue_layer_count_must_match(weights: tuple[Path, Path], layers: int) -> None:
    with pytest.raises(OrthonavError, match=r"SuperGlue weights .*not this architecture.*gnn_layers \(now"):
        create_backend(
            "superpoint", superpoint_weights=weights[0], superglue_weights=weights[1], gnn_layers=layers
        )


def test_wrong_shapes_are_named(weights: tuple[Path, Path], tmp_path: Path) -> None:
    state = torch.load(weights[0], weights_only=True)
    state["convDb.weight"] = state["convDb.weight"][:128]
    state["convDb.bias"] = state["convDb.bias"][:128]
    torch.save(state, tmp_path / "sp128.pth")
    with pytest.raises(OrthonavError, match=r"wrong shape.*convDb"):
        create_backend(
            "superpoint",
            superpoint_weights=tmp_path / "sp128.pth",
            superglue_weights=weights[1],
            gnn_layers=2,
        )


@pytest.mark.parametrize(
    ("option", "value"),
    [("gnn_layers", 0), ("sinkhorn_iterations", 0), ("match_threshold", 1.5), ("nms_radius", -1)],
)
def test_bad_option_values(weights: tuple[Path, Path], option: str, value: float) -> None:
    with pytest.raises(OrthonavError, match=option):
        make_backend(weights, **{option: value})


# --- the full path: map build, localizer, relocated weights ---------------------------------


def test_map_build_and_localize_run_the_whole_superpoint_path(
    weights: tuple[Path, Path], tmp_path: Path
) -> None:
    """Build a map from a real NAIP crop with our random weights, localize a rendered frame, then
    move the weight files: the map's backend is recreated only with the new paths given.

    Random networks promise no fix, but whatever the localizer says must be honest: an accepted
    fix is on target (frame centre within 2 map px), a rejection carries a reason and no position.
    """
    from conftest import CAMERA, NAIP_ALT_M, true_centre_latlon, write_naip_crop

    from orthonav.frames import Photometric, TruePose, render_frame
    from orthonav.geo import distance_m
    from orthonav.localize import Localizer
    from orthonav.mapdb import MapPackage, TilingConfig, build_map
    from orthonav.types import Prior

    crop = write_naip_crop("20200831", (250, 150, 400, 400), tmp_path / "crop.tif")
    sp, sg = tmp_path / "sp.pth", tmp_path / "sg.pth"
    sp.write_bytes(weights[0].read_bytes())
    sg.write_bytes(weights[1].read_bytes())
    conf = {"superpoint_weights": str(sp), "superglue_weights": str(sg), "gnn_layers": 2}
    conf |= {"max_keypoints": 128, "match_threshold": 0.0}
    package = build_map(
        crop,
        tmp_path / "map",
        CAMERA,
        TilingConfig(nominal_alt_m=NAIP_ALT_M),
        "superpoint",
        conf,
        progress=False,
    )
    assert package.backend_name == "superpoint" and package.keypoint_count > 0

    with GeoRaster(crop) as raster:
        lat, lon = (float(v) for v in raster.pixel_to_latlon(200, 200))
        truth = TruePose(lat, lon, NAIP_ALT_M, 10.0, 1.0, -1.0)
        rng = np.random.default_rng(0)
        frame = render_frame(raster, CAMERA, truth, Photometric.random(rng, 0.3), rng)
    fix = Localizer(package, CAMERA).localize(frame, Prior(lat, lon, NAIP_ALT_M, 10.0, 1.0, -1.0))
    assert fix.method == "superpoint" and fix.quality["keypoints"] > 0
    if fix.accepted:
        centre = true_centre_latlon(CAMERA, truth)
        assert distance_m(*centre, fix.pose.centre_lat, fix.pose.centre_lon) <= 2 * package.gsd_m
    else:
        assert fix.reason and fix.to_dict()["lat"] is None

    moved = tmp_path / "moved"
    moved.mkdir()
    sp.rename(moved / "sp.pth")
    sg.rename(moved / "sg.pth")
    reopened = MapPackage(tmp_path / "map")
    with pytest.raises(OrthonavError, match=r"sp\.pth: no such file"):
        reopened.create_backend()
    relocated = reopened.create_backend(
        superpoint_weights=str(moved / "sp.pth"), superglue_weights=str(moved / "sg.pth")
    )
    assert relocated.conf["max_keypoints"] == 128 and relocated.conf["gnn_layers"] == 2
