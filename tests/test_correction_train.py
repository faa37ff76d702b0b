"""Triplet datasets and triplet-loss training of correction trunks, on real NAIP date pairs.

The data checks are independent of the dataset code: a positive patch must look like its
anchor (gradient correlation computed here with numpy) more than the shifted and temporal
negatives do, and every search region must lie inside its strip of the map, measured from
the views' geometry with rotation maths written out here. Training runs are tiny (8 samples
of 64 px, ResNet18 cut at stage 1, one torch thread): they check behaviour, not accuracy.
Runs on a 2-core CPU in about 12 s.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("torchvision")

pytestmark = pytest.mark.usefixtures("torch_one_thread")

from conftest import NAIP_DIR, naip_path  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

from orthonav.cli.main import app  # noqa: E402
from orthonav.errors import OrthonavError  # noqa: E402
from orthonav.geo import GeoRaster, LocalFrame  # noqa: E402
from orthonav.models import dataset  # noqa: E402
from orthonav.models import train as train_module  # noqa: E402
from orthonav.models.dataset import TripletConfig, TripletSet, year_pair_triplets  # noqa: E402
from orthonav.models.train import TrainConfig, evaluate, train, train_on_dates  # noqa: E402
from orthonav.models.trunks import DenseFeatures, load_model  # noqa: E402

YEARS = ("20180716", "20200831")
TRAIN_AREA = (0.0, 0.5)
VAL_AREA = (0.55, 1.0)
SMALL = TripletConfig(samples=8, size_px=64, area=TRAIN_AREA, seed=0)
TINY_TRAINING = TrainConfig(backbone="resnet18", stage=1, epochs=2, batch=4, seed=0)

runner = CliRunner()


# --- data ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def orthos() -> list[Path]:
    return [naip_path(year) for year in YEARS]


@pytest.fixture(scope="module")
def built(orthos: list[Path]) -> dict:
    """Training and validation sets, with every view the dataset cut (spied, kept or not)."""
    made: list = []
    real_make_views = dataset.make_views

    def spy(*args, **kwargs):
        views = real_make_views(*args, **kwargs)
        made.append(views)
        return views

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(dataset, "make_views", spy)
        train_set = year_pair_triplets(orthos, SMALL)
        train_views, made[:] = list(made), []
        val_set = year_pair_triplets(orthos, TripletConfig(samples=4, size_px=64, area=VAL_AREA, seed=1))
        val_views = list(made)
    return {"train": train_set, "val": val_set, "train_views": train_views, "val_views": val_views}


def _sample_views(data: TripletSet, made: list) -> list:
    """The spied views each sample of ``data`` was made from (found by its anchor image)."""
    found = [[v for v in made if np.array_equal(v.frame, anchor)] for anchor in data.anchors]
    assert all(len(f) >= 1 for f in found)
    return [f[0] for f in found]


def _gradient(rgb: np.ndarray) -> np.ndarray:
    gy, gx = np.gradient(rgb.astype(np.float64).mean(axis=2))
    return np.hypot(gx, gy)


def _ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    a, b = a[mask] - a[mask].mean(), b[mask] - b[mask].mean()
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))


def test_triplet_sets_have_the_promised_shapes(built: dict) -> None:
    data: TripletSet = built["train"]
    assert len(data) == SMALL.samples
    assert data.anchors.shape == (8, 48, 64, 3) and data.anchors.dtype == np.uint8
    assert data.regions.shape == (8, 96, 128, 3)  # search factor 2
    assert data.margin_px == (32, 24)
    assert data.anchor_masks.mean() > 0.98
    # both directions of the date pair, half the samples each
    names = [f"m_4709963_se_14_1_{y}.tif" for y in YEARS]
    assert data.sources.count(f"{names[0]} -> {names[1]}") == 4
    assert data.sources.count(f"{names[1]} -> {names[0]}") == 4
    # the temporal negative: 10 s at 15 m/s behind the vehicle (down in the heading-up view), in
    # each sample's own pixels: altitudes, hence ground resolutions, differ between samples
    gsd = np.array([v.geometry.gsd_m for v in _sample_views(data, built["train_views"])])
    assert np.ptp(gsd) > 0.01 * gsd.mean()
    assert np.allclose(data.temporal_px[:, 0], 0.0)
    assert np.allclose(data.temporal_px[:, 1] * gsd, 150.0, rtol=1e-5)
    assert np.all(data.temporal_px[:, 1] <= data.margin_px[1])
    assert len(built["val"]) == 4
    with pytest.raises(OrthonavError, match="beyond the region's margin"):
        data.patch(0, 33, 0)


def test_positive_patch_looks_like_its_anchor_more_than_the_negatives(built: dict) -> None:
    data: TripletSet = built["train"]
    mx, my = data.margin_px
    scores = {"positive": [], "temporal": [], "shifted": []}
    for i in range(len(data)):
        anchor, mask = _gradient(data.anchors[i]), data.anchor_masks[i]
        temporal = np.round(data.temporal_px[i]).astype(int)
        patches = {
            "positive": data.patch(i),
            "temporal": data.patch(i, *temporal),
            "shifted": data.patch(i, mx // 2, -(my // 2)),
        }
        for name, patch in patches.items():
            scores[name].append(_ncc(anchor, _gradient(patch), mask))
    means = {name: float(np.mean(values)) for name, values in scores.items()}
    print(f"\nmean gradient correlation with the anchor: {means}")
    assert means["positive"] > means["temporal"] + 0.1
    assert means["positive"] > means["shifted"] + 0.1
    assert np.mean(np.array(scores["positive"]) > np.array(scores["temporal"])) >= 0.75


def _region_columns(raster: GeoRaster, geometry) -> np.ndarray:
    """Map columns of a region view's four corners, by rotation written out here."""
    w, h = geometry.region_size
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    right = (corners[:, 0] - w / 2) * geometry.gsd_m
    forward = -(corners[:, 1] - h / 2) * geometry.gsd_m
    hd = math.radians(geometry.heading_deg)
    east = geometry.centre_en[0] + right * math.cos(hd) + forward * math.sin(hd)
    north = geometry.centre_en[1] - right * math.sin(hd) + forward * math.cos(hd)
    lat, lon = LocalFrame(geometry.prior_lat, geometry.prior_lon).to_latlon(east, north)
    cols, _ = raster.latlon_to_pixel(lat, lon)
    return np.asarray(cols)


def test_area_split_keeps_regions_inside_their_strips(built: dict, orthos: list[Path]) -> None:
    """Every view cut for a set, kept or not, lies in its strip; the kept ones are among them."""
    for name in ("train", "val"):
        views = _sample_views(built[name], built[f"{name}_views"])
        assert all(np.array_equal(v.region, r) for v, r in zip(views, built[name].regions, strict=True))
    with GeoRaster(orthos[0]) as raster:
        train_cols = np.concatenate([_region_columns(raster, v.geometry) for v in built["train_views"]])
        val_cols = np.concatenate([_region_columns(raster, v.geometry) for v in built["val_views"]])
        width = raster.width
    assert train_cols.min() >= TRAIN_AREA[0] * width - 1e-6
    assert train_cols.max() <= TRAIN_AREA[1] * width + 1e-6
    assert val_cols.min() >= VAL_AREA[0] * width - 1e-6
    assert val_cols.max() <= VAL_AREA[1] * width + 1e-6
    assert train_cols.max() < val_cols.min()  # the gap: no validation pixel is trained on
    # the regions do spread over their strips (not all in one spot)
    assert np.ptp(train_cols) > 0.2 * width


def test_bad_triplet_configs(orthos: list[Path]) -> None:
    with pytest.raises(OrthonavError, match="triplet area"):
        TripletConfig(area=(0.6, 0.2))
    with pytest.raises(OrthonavError, match="triplet samples"):
        TripletConfig(samples=0)
    with pytest.raises(OrthonavError, match="at least two different dates"):
        year_pair_triplets(orthos[:1], SMALL)
    with pytest.raises(OrthonavError, match="at least two different dates"):
        year_pair_triplets([orthos[0], orthos[0]], SMALL)
    with pytest.raises(OrthonavError, match="found no pose whose search region lies inside the area"):
        year_pair_triplets(orthos, TripletConfig(samples=2, size_px=64, area=(0.0, 0.05)))


# --- training --------------------------------------------------------------------------------


def _no_temporary_files(folder: Path) -> None:
    leftovers = [p.name for p in folder.iterdir() if ".tmp" in p.name]
    assert leftovers == []


def test_tiny_training_lowers_the_loss_and_writes_its_files(built: dict, tmp_path: Path) -> None:
    config = TINY_TRAINING
    torch.manual_seed(config.seed)  # the initial network train() starts from
    start = evaluate(DenseFeatures(config.backbone, config.stage), built["train"], config)["val_loss"]
    result = train(built["train"], built["val"], config, tmp_path, info={"note": "test"}, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt", "history.json", "model.pt"]
    _no_temporary_files(tmp_path)
    history = json.loads((tmp_path / "history.json").read_text())
    assert history["config"]["epochs"] == 2 and history["info"] == {"note": "test"}
    assert [h["epoch"] for h in history["history"]] == [1, 2] == [h["epoch"] for h in result["history"]]
    for entry in history["history"]:
        assert math.isfinite(entry["train_loss"]) and 0.0 <= entry["val_top1"] <= 1.0
    # the last weights (checkpoint) score the training triplets better than the initial ones
    state = torch.load(tmp_path / "checkpoint.pt", map_location="cpu", weights_only=False)
    trained = DenseFeatures(config.backbone, config.stage)
    trained.load_state_dict(state["model"])
    end = evaluate(trained, built["train"], config)["val_loss"]
    print(f"\ntraining-set triplet loss: {start:.3f} -> {end:.3f}")
    assert end < 0.9 * start
    # the model file: the best epoch by validation top-1, with what it was trained on
    net, info = load_model(tmp_path / "model.pt")
    assert (net.backbone, net.stage) == ("resnet18", 1)
    assert info["note"] == "test" and info["train"]["epochs"] == 2
    assert info["validation"]["val_top1"] == result["best_val_top1"]
    assert info["epoch"] in (1, 2)


class _Stop(Exception):
    pass


def test_resume_continues_from_the_checkpoint(built: dict, tmp_path: Path, monkeypatch) -> None:
    config = TINY_TRAINING
    real_checkpoint, real_epoch = train_module._checkpoint, train_module._epoch

    def checkpoint_then_stop(*args, **kwargs):
        real_checkpoint(*args, **kwargs)
        raise _Stop  # as if interrupted right after epoch 1 was saved

    monkeypatch.setattr(train_module, "_checkpoint", checkpoint_then_stop)
    with pytest.raises(_Stop):
        train(built["train"], built["val"], config, tmp_path, progress=False)
    first = torch.load(tmp_path / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert [h["epoch"] for h in first["history"]] == [1]
    _no_temporary_files(tmp_path)

    epochs_run = []

    def counting_epoch(*args, **kwargs):
        epochs_run.append(args[-1])
        return real_epoch(*args, **kwargs)

    monkeypatch.setattr(train_module, "_checkpoint", real_checkpoint)
    monkeypatch.setattr(train_module, "_epoch", counting_epoch)
    result = train(built["train"], built["val"], config, tmp_path, progress=False)
    assert epochs_run == ["epoch 2/2"]  # epoch 1 is not run again
    assert [h["epoch"] for h in result["history"]] == [1, 2]
    assert result["history"][0] == first["history"][0]  # carried over, not recomputed
    # a finished run resumed again does nothing
    epochs_run.clear()
    again = train(built["train"], built["val"], config, tmp_path, progress=False)
    assert epochs_run == [] and again["history"] == result["history"]
    # another configuration in the same folder is refused, and the checkpoint is left alone
    before = (tmp_path / "checkpoint.pt").read_bytes()
    for changed in (replace(config, lr=5e-4), replace(config, epochs=3)):
        with pytest.raises(OrthonavError, match="checkpoint of another training configuration"):
            train(built["train"], built["val"], changed, tmp_path, progress=False)
    assert (tmp_path / "checkpoint.pt").read_bytes() == before


def test_bad_train_configs() -> None:
    with pytest.raises(OrthonavError, match="training mining 'random'"):
        TrainConfig(mining="random")
    for kwargs in ({"epochs": 0}, {"batch": 0}, {"lr": 0.0}, {"margin": -0.1}):
        with pytest.raises(OrthonavError, match="epochs >= 1"):
            TrainConfig(**kwargs)


def test_overlapping_validation_area_is_refused(orthos: list[Path], tmp_path: Path) -> None:
    with pytest.raises(OrthonavError, match="overlaps the training area"):
        train_on_dates(orthos, SMALL, (0.4, 1.0), 2, TINY_TRAINING, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


# --- the command line ------------------------------------------------------------------------


def _train_args(out: Path, **options) -> list[str]:
    values = {
        "data": NAIP_DIR,
        "train-dates": ",".join(YEARS),
        "out": out,
        "backbone": "resnet18",
        "stage": 2,
        "epochs": 1,
        "samples": 4,
        "val-samples": 2,
        "batch": 2,
        "threads": 1,
        **options,
    }
    return ["correction", "train", *[a for k, v in values.items() for a in (f"--{k}", str(v))]]


def test_cli_correction_train_tiny_run(orthos: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = runner.invoke(app, _train_args(out))
    assert result.exit_code == 0, (result.output, result.exception)
    assert "trained 1 epochs" in result.output and str(out / "model.pt") in result.output
    names = sorted(p.name for p in out.iterdir())
    assert names == ["checkpoint.pt", "history.json", "losses.png", "model.pt", "triplets.png"]
    for png in ("losses.png", "triplets.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    net, info = load_model(out / "model.pt")
    assert (net.backbone, net.stage) == ("resnet18", 2)
    assert info["dates"] == [p.name for p in orthos]
    assert info["train_samples"] == 4 and info["val_samples"] == 2
    assert list(info["triplets"]["area"]) == [0.0, 0.5] and list(info["val_area"]) == [0.55, 1.0]


@pytest.mark.parametrize(
    ("options", "fragments"),
    [
        ({"train-area": "0.6,0.2"}, ("--train-area", "0 <= START < END <= 1")),
        ({"train-area": "half"}, ("--train-area", "START,END")),
        ({"train-area": "0,1.5"}, ("--train-area",)),
        ({"train-area": "0,0.7"}, ("overlaps the training area",)),
        ({"val-area": "0.2,0.4"}, ("overlaps the training area",)),
        ({"train-dates": "20180716"}, ("--train-dates", "at least two dates")),
        ({"train-dates": "20180716,19990101"}, ("0 files match date '19990101'",)),
        ({"train-dates": "2018,20180716"}, ("at least two different dates",)),
        ({"data": "/nonexistent/folder"}, ("no GeoTIFFs",)),
        ({"backbone": "alexnet"}, ("backbone 'alexnet'",)),
        ({"mining": "random"}, ("training mining 'random'",)),
    ],
)
def test_cli_correction_train_bad_options(
    orthos: list[Path], tmp_path: Path, options: dict, fragments
) -> None:
    result = runner.invoke(app, _train_args(tmp_path / "run", **options))
    assert isinstance(result.exception, OrthonavError), (result.exception, result.output)
    for fragment in fragments:
        assert fragment in str(result.exception), (fragment, str(result.exception))
    assert not (tmp_path / "run" / "model.pt").exists()
