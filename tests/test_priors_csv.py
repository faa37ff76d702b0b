"""The priors CSV of ``orthonav localize --priors``: common column spellings, and rows that
match no frame, repeat a name, or match nothing at all said out loud instead of ignored."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from orthonav.cli.inputs import read_priors
from orthonav.errors import OrthonavError

FRAMES = ["frame_00.png", "frame_01.png", "frame_02.png"]


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "priors.csv"
    path.write_text(text)
    return path


def warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def test_common_column_spellings_are_read(tmp_path: Path) -> None:
    path = write(tmp_path, "Name,Latitude,Longitude,Alt,Yaw\nframe_00.png,50.45,30.52,300,45\n")
    prior = read_priors(path)["frame_00.png"]
    assert (prior.lat, prior.lon, prior.alt_agl_m, prior.heading_deg) == (50.45, 30.52, 300.0, 45.0)
    lng = write(tmp_path, "name,lat,lng\nframe_00.png,50.45,30.52\n")
    assert read_priors(lng)["frame_00.png"].lon == 30.52


def test_a_file_saved_with_a_utf8_byte_order_mark_is_read(tmp_path: Path) -> None:
    """Excel's "CSV UTF-8" starts the file with a BOM, which would otherwise be part of 'name'."""
    path = tmp_path / "priors.csv"
    path.write_bytes(b"\xef\xbb\xbfname,lat,lon\r\nframe_00.png,50.45,30.52\r\n")
    prior = read_priors(path)["frame_00.png"]
    assert (prior.lat, prior.lon) == (50.45, 30.52)


def test_two_spellings_of_one_field_are_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "name,lat,latitude,lon\nframe_00.png,50.45,50.46,30.52\n")
    with pytest.raises(OrthonavError, match=r"priors\.csv: columns 'lat' and 'latitude' both give lat"):
        read_priors(path)


def test_an_alias_column_error_names_the_column(tmp_path: Path) -> None:
    path = write(tmp_path, "name,latitude,longitude,alt\nframe_00.png,50.45,30.52,high\n")
    with pytest.raises(OrthonavError, match=r"priors\.csv:2: field 'alt' = 'high' is not a number"):
        read_priors(path)


def test_unknown_columns_are_warned_about(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = write(tmp_path, "name,lat,lon,speed\nframe_00.png,50.45,30.52,12\n")
    read_priors(path, FRAMES)
    assert any("columns ignored: 'speed'" in text for text in warnings(caplog))


def test_matched_rows_are_returned_and_logged_the_others_warned_about(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="orthonav")
    path = write(
        tmp_path,
        "name,lat,lon\n"
        "frame_00.png,50.45,30.52\n"
        "other.png,50.46,30.53\n"
        "frame_01.png,50.40,30.50\n"
        "DCIM/frame_02.png,50.47,30.54\n"  # a path: its file name counts
        "frame_01.png,50.41,30.51\n",
    )
    priors = read_priors(path, [Path("/data") / name for name in FRAMES])
    assert set(priors) == set(FRAMES)
    assert priors["frame_01.png"].lat == 50.41  # the last row of a repeated name
    texts = warnings(caplog)
    assert any("name no frame" in t and "line 3 'other.png'" in t for t in texts), texts
    assert any("repeated" in t and "'frame_01.png' (lines 4, 6)" in t for t in texts), texts
    infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert any("priors for 3 of 3 frames" in t for t in infos), infos


def test_a_file_matching_no_frame_is_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "name,lat,lon\nIMG_0001.JPG,50.45,30.52\n")
    with pytest.raises(OrthonavError, match=r"priors\.csv: no row names a frame being localized.*IMG_0001"):
        read_priors(path, FRAMES)


def test_a_header_without_rows_is_refused(tmp_path: Path) -> None:
    with pytest.raises(OrthonavError, match="no priors"):
        read_priors(write(tmp_path, "name,lat,lon\n"))


def test_without_frames_every_named_row_is_returned_and_nameless_rows_warned_about(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = write(tmp_path, "name,lat,lon\nframe_00.png,50.45,30.52\n,50.0,30.0\nelse.png,,\n")
    priors = read_priors(path)
    assert set(priors) == {"frame_00.png", "else.png"} and not priors["else.png"].has_position
    assert any("priors.csv:3: no frame name" in t for t in warnings(caplog))
