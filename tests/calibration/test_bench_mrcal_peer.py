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


def test_halvings_start_with_even_odd_and_split_every_view_once() -> None:
    splits = real.halvings(13, 4)
    assert len(splits) == 5
    assert splits[0][0].tolist() == list(range(0, 13, 2)) and splits[0][1].tolist() == list(range(1, 13, 2))
    for a, b in splits:
        assert sorted(a.tolist() + b.tolist()) == list(range(13)) and abs(len(a) - len(b)) <= 1
    assert len({tuple(a) for a, _ in splits}) == 5                     # the halvings differ
    assert [a.tolist() for a, _ in real.halvings(13, 4)] == [a.tolist() for a, _ in splits]   # seeded


def test_the_table_gives_the_median_ratio_beside_the_even_odd_one() -> None:
    def row(tool: str, eo: float, med: float) -> dict[str, object]:
        return {"set": "s", "corners": "ours", "tool": tool, "model": "opencv5", "views": 13, "split_px": eo,
                "split_med_px": med, "n_splits": 7, "rms_px": 0.1, "note": ""}
    rows = [row("cellctl, chosen by cross-validation", 0.4, 0.2), row("mrcal", 0.2, 0.5), row("OpenCV", 0.3, 0.4)]
    last = real.real_table(rows)[-1]
    assert "**0.400 / 0.200** | **2.00**" in last and "**0.200 / 0.400** | **0.50**" in last
