"""Target descriptions: strict parsing and stable ids (calibration.targets)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.targets import (
    Charuco,
    Chessboard,
    CircleGrid,
    CirclePlate,
    Points3D,
    TargetError,
    load_target,
    target_from_dict,
    target_to_dict,
)


@pytest.mark.parametrize("d, cls", [
    ({"type": "chessboard", "cols": 9, "rows": 6, "square_mm": 25.0}, Chessboard),
    ({"type": "charuco", "cols": 8, "rows": 6, "square_mm": 30, "marker_mm": 22, "dictionary": "DICT_5X5_100"},
     Charuco),
    ({"type": "circle_plate", "cols": 7, "rows": 7, "pitch_mm": 12.5, "diameter_mm": 6.25}, CirclePlate),
    ({"type": "circle_grid", "cols": 4, "rows": 11, "pitch_mm": 20, "diameter_mm": 10, "asymmetric": True},
     CircleGrid),
    ({"type": "points3d", "points_mm": {i: [i * 10, 0, i % 2 * 5] for i in range(6)}}, Points3D),
])
def test_each_type_parses_and_round_trips(d: dict, cls: type) -> None:
    t = target_from_dict(d)
    assert isinstance(t, cls)
    assert target_from_dict(target_to_dict(t)) == t


@pytest.mark.parametrize("d, word", [
    ({"type": "chessbord", "cols": 9, "rows": 6, "square_mm": 25.0}, "type"),
    ({"type": "chessboard", "cols": 9, "square_mm": 25.0}, "rows"),
    ({"type": "chessboard", "cols": 9, "rows": 6, "square_mm": 25.0, "colour": "red"}, "colour"),
    ({"type": "chessboard", "cols": 9.5, "rows": 6, "square_mm": 25.0}, "cols"),
    ({"type": "chessboard", "cols": 9, "rows": 6, "square_mm": -1}, "square_mm"),
    ({"type": "circle_plate", "cols": 7, "rows": 7, "pitch_mm": 10, "diameter_mm": 12}, "diameter_mm"),
    ({"type": "charuco", "cols": 8, "rows": 6, "square_mm": 30, "marker_mm": 22, "dictionary": "DICT_NOPE"},
     "dictionary"),
])
def test_bad_descriptions_name_the_field(d: dict, word: str) -> None:
    with pytest.raises(TargetError, match=word):
        target_from_dict(d)


def test_load_target_errors_name_the_file(tmp_path: Path) -> None:
    p = tmp_path / "t.yaml"
    p.write_text("type: [unclosed\n")
    with pytest.raises(TargetError, match="t.yaml"):
        load_target(p)
    with pytest.raises(TargetError, match="cannot read"):
        load_target(tmp_path / "missing.yaml")


def test_ids_are_row_major_in_the_target_frame() -> None:
    t = CirclePlate(7, 5, 10.0, 5.0)
    pts = t.points()
    assert pts.ids.tolist() == list(range(35))
    k = 2 * 7 + 3  # row 2, col 3
    assert np.allclose(pts.xyz_m[k], [0.03, 0.02, 0.0])
    # the orientation triangle sits in the frame corner nearest mark (0, 0): dark there, light at the others
    p = t.pitch_m
    inset = p * 0.15
    corners = [(-p + inset, -p + inset), (7 * p - inset, -p + inset), (7 * p - inset, 5 * p - inset),
               (-p + inset, 5 * p - inset)]
    refl = [float(t.reflectance(np.array([x]), np.array([y]))[0]) for x, y in corners]
    assert refl == [0.0, 1.0, 1.0, 1.0]
