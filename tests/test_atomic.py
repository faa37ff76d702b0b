"""Atomic writes: the target holds the old or the new content, and no temporary is left behind."""

from __future__ import annotations

from pathlib import Path

import pytest

from orthonav.atomic import atomic_path, write_text_atomic


def test_success_replaces_the_target_and_keeps_the_suffix(tmp_path: Path) -> None:
    target = tmp_path / "plot.png"
    target.write_text("old")
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".png" and tmp != target
        tmp.write_text("new")
        assert target.read_text() == "old"  # not visible before the block ends
    assert target.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["plot.png"]


def test_failure_keeps_the_old_content_and_removes_the_temporary(tmp_path: Path) -> None:
    target = tmp_path / "summary.json"
    write_text_atomic(target, "old")
    with pytest.raises(RuntimeError, match="crash"), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]
