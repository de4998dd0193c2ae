"""bench/intrinsics_real.py's mrcal peer: without Debian's mrcal the bench refuses with the apt line
(mrcal is a bench peer only; the suite does not need it), and the corner file it writes for
``mrcal-calibrate-cameras`` keeps our ids in mrcal's board order."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import bench.intrinsics_real as real
from calibration.observations import Detection
from calibration.targets import Chessboard


def test_the_bench_refuses_clearly_without_mrcal(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(real, "MRCAL_TOOL", "mrcal-calibrate-cameras-not-installed")
    with pytest.raises(SystemExit, match="apt-get install -y mrcal python3-mrcal"):
        real.require_mrcal()


def test_corner_file_rows_follow_the_board_order(tmp_path: Path) -> None:
    board = Chessboard(3, 2, 10.0)
    ids = np.array([0, 1, 2, 4, 5])                 # corner 3 not seen
    uv = np.column_stack([ids * 10.0, ids * 1.0])
    real._write_corners(tmp_path / "c.vnl", [Detection("a", True, ids=ids, uv=uv)], board, None)
    lines = (tmp_path / "c.vnl").read_text().splitlines()
    assert lines[0] == "# filename x y level" and len(lines) == 1 + 6
    assert lines[1].split() == ["v000.jpg", "0.000000", "0.000000", "0"]
    assert lines[4].split()[3] == "-"               # the missing corner is skipped by mrcal
    assert lines[6].split()[1:3] == ["50.000000", "5.000000"]
