"""Calibration target descriptions: strict YAML parsing, point sets and the printed pattern.

Target frame (docs/conventions.md): origin at the centre of point ``(row 0, col 0)``, x
along increasing column, y along increasing row, z into the target. Internally metres; the
YAML fields are millimetres and say so (``square_mm``, ``pitch_mm``...).

Each planar target also describes its printed pattern as a reflectance function
``reflectance(x_m, y_m) -> [0, 1]`` over the target plane (0 black, 1 white, NaN off the
plate), which the virtual cell's renderer and the printable-target writer both use, so that a
renderer and a detector can never disagree about the geometry.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Final

import numpy as np
import yaml
from numpy.typing import NDArray

from calibration import CalibrationError

MM: Final = 1e-3

FloatArray = NDArray[np.float64]


class TargetError(CalibrationError):
    """A target description is missing a field, has an unknown one, or a nonsensical value."""


@dataclass(frozen=True)
class TargetPoints:
    """Ids and 3D coordinates (metres, target frame) of a target's calibration points."""

    ids: NDArray[np.int64]
    xyz_m: FloatArray


@dataclass(frozen=True)
class Chessboard:
    """Inner corners of a checkerboard: ``cols`` x ``rows`` corners, ``square_mm`` squares.

    The printed board has ``cols + 1`` x ``rows + 1`` squares (the square touching corner (0, 0)
    on its upper left is black) and a white margin one square wide around them.
    """

    cols: int
    rows: int
    square_mm: float
    type: str = "chessboard"

    @property
    def square_m(self) -> float:
        return self.square_mm * MM

    def points(self) -> TargetPoints:
        r, c = np.mgrid[0 : self.rows, 0 : self.cols]
        xyz = np.column_stack([c.ravel(), r.ravel(), np.zeros(r.size)]) * self.square_m
        return TargetPoints((r * self.cols + c).ravel().astype(np.int64), xyz)

    def extent_m(self) -> tuple[float, float, float, float]:
        """Plate outline ``(x_min, y_min, x_max, y_max)`` in metres, margin included."""
        s = self.square_m
        return (-2 * s, -2 * s, (self.cols + 1) * s, (self.rows + 1) * s)

    def reflectance(self, x: FloatArray, y: FloatArray) -> FloatArray:
        s = self.square_m
        i = np.floor(x / s)
        j = np.floor(y / s)
        on_squares = (i >= -1) & (i <= self.cols - 1) & (j >= -1) & (j <= self.rows - 1)
        black = on_squares & (((i + j) % 2) == 0)
        return _on_plate(np.where(black, 0.0, 1.0), x, y, self.extent_m())

    def describe(self) -> str:
        return f"chessboard {self.cols}x{self.rows} inner corners, square {self.square_mm:g} mm"


@dataclass(frozen=True)
class Charuco:
    """OpenCV ChArUco board: ``cols`` x ``rows`` squares, ArUco markers in the white squares.

    Points are the inner chessboard corners with OpenCV's ids; corner 0 is the target origin.
    """

    cols: int
    rows: int
    square_mm: float
    marker_mm: float
    dictionary: str
    type: str = "charuco"

    @property
    def square_m(self) -> float:
        return self.square_mm * MM

    def cv_board(self) -> Any:
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_mm * MM, d)

    @cached_property
    def _origin_in_board_m(self) -> FloatArray:
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64)[0]

    def points(self) -> TargetPoints:
        corners = np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64)
        xyz = corners - self._origin_in_board_m
        xyz[:, 2] = 0.0
        return TargetPoints(np.arange(len(xyz), dtype=np.int64), xyz)

    def extent_m(self) -> tuple[float, float, float, float]:
        s = self.square_m
        o = self._origin_in_board_m
        return (-o[0] - s / 2, -o[1] - s / 2, -o[0] + (self.cols + 0.5) * s, -o[1] + (self.rows + 0.5) * s)

    @cached_property
    def _marker_cells(self) -> tuple[FloatArray, list[NDArray[np.uint8]]]:
        import cv2

        board = self.cv_board()
        d = board.getDictionary()
        bits = d.markerSize + 2
        quads = np.asarray(board.getObjPoints(), dtype=np.float64)[:, :, :2] - self._origin_in_board_m[:2]
        cells = [cv2.aruco.generateImageMarker(d, int(i), bits, borderBits=1) for i in board.getIds().ravel()]
        return quads, cells

    def reflectance(self, x: FloatArray, y: FloatArray) -> FloatArray:
        s = self.square_m
        o = self._origin_in_board_m
        bx, by = x + o[0], y + o[1]
        i = np.floor(bx / s)
        j = np.floor(by / s)
        on_squares = (i >= 0) & (i < self.cols) & (j >= 0) & (j < self.rows)
        out = np.ones_like(x)
        quads, cells = self._marker_cells
        marker_square = np.zeros((self.rows, self.cols), dtype=bool)
        for quad, cell in zip(quads, cells, strict=True):
            x0, y0 = quad[0]
            side = quad[1, 0] - quad[0, 0]
            marker_square[int((y0 + o[1]) // s), int((x0 + o[0]) // s)] = True
            n = cell.shape[0]
            fu = (x - x0) / side * n
            fv = (y - y0) / side * n
            inside = (fu >= 0) & (fu < n) & (fv >= 0) & (fv < n)
            if np.any(inside):
                out[inside] = cell[fv[inside].astype(int), fu[inside].astype(int)] / 255.0
        ii = np.clip(i, 0, self.cols - 1).astype(int)
        jj = np.clip(j, 0, self.rows - 1).astype(int)
        black_square = on_squares & ~marker_square[jj, ii]
        out[black_square] = 0.0
        return _on_plate(out, x, y, self.extent_m())

    def describe(self) -> str:
        return (f"charuco {self.cols}x{self.rows} squares, square {self.square_mm:g} mm, "
                f"marker {self.marker_mm:g} mm, {self.dictionary}")


@dataclass(frozen=True)
class CirclePlate:
    """HALCON-style plate: black marks, a surrounding frame and an orientation triangle.

    Geometry exactly as docs/targets.md: mark (r, c) at ``(c*pitch, r*pitch)``; the
    frame's inner edge one pitch outside the outer mark centres, ``pitch/2`` wide; a right
    triangle with legs ``pitch/2`` in the frame's inner corner nearest mark (0, 0).
    """

    cols: int
    rows: int
    pitch_mm: float
    diameter_mm: float
    type: str = "circle_plate"

    @property
    def pitch_m(self) -> float:
        return self.pitch_mm * MM

    @property
    def radius_m(self) -> float:
        return self.diameter_mm * MM / 2

    def points(self) -> TargetPoints:
        r, c = np.mgrid[0 : self.rows, 0 : self.cols]
        xyz = np.column_stack([c.ravel(), r.ravel(), np.zeros(r.size)]) * self.pitch_m
        return TargetPoints((r * self.cols + c).ravel().astype(np.int64), xyz)

    def frame_inner_m(self) -> tuple[float, float, float, float]:
        p = self.pitch_m
        return (-p, -p, self.cols * p, self.rows * p)

    def extent_m(self) -> tuple[float, float, float, float]:
        p = self.pitch_m
        x0, y0, x1, y1 = self.frame_inner_m()
        return (x0 - p, y0 - p, x1 + p, y1 + p)

    def reflectance(self, x: FloatArray, y: FloatArray) -> FloatArray:
        p = self.pitch_m
        x0, y0, x1, y1 = self.frame_inner_m()
        w = p / 2
        in_outer = (x >= x0 - w) & (x <= x1 + w) & (y >= y0 - w) & (y <= y1 + w)
        in_inner = (x > x0) & (x < x1) & (y > y0) & (y < y1)
        black = in_outer & ~in_inner
        # Orientation triangle: right angle at (x0, y0), legs p/2 along the inner edges.
        black |= (x >= x0) & (y >= y0) & ((x - x0) + (y - y0) <= p / 2)
        c = np.clip(np.rint(x / p), 0, self.cols - 1)
        r = np.clip(np.rint(y / p), 0, self.rows - 1)
        black |= (x - c * p) ** 2 + (y - r * p) ** 2 <= self.radius_m**2
        return _on_plate(np.where(black, 0.0, 1.0), x, y, self.extent_m())

    def describe(self) -> str:
        return (f"circle_plate {self.cols}x{self.rows} marks, pitch {self.pitch_mm:g} mm, "
                f"diameter {self.diameter_mm:g} mm")


@dataclass(frozen=True)
class CircleGrid:
    """OpenCV circle grid (no frame, no orientation mark).

    Symmetric: circle (r, c) at ``(c*pitch, r*pitch)``. Asymmetric (OpenCV's convention, as in
    its calibration sample): circle (r, c) at ``((2c + r % 2)*pitch, r*pitch)``, so ``pitch`` is
    the spacing between neighbouring rows and half the spacing between circles of one row.
    """

    cols: int
    rows: int
    pitch_mm: float
    diameter_mm: float
    asymmetric: bool = False
    type: str = "circle_grid"

    @property
    def pitch_m(self) -> float:
        return self.pitch_mm * MM

    def points(self) -> TargetPoints:
        r, c = np.mgrid[0 : self.rows, 0 : self.cols]
        r, c = r.ravel(), c.ravel()
        xs = (2 * c + r % 2) if self.asymmetric else c
        xyz = np.column_stack([xs, r, np.zeros(r.size)]).astype(np.float64) * self.pitch_m
        return TargetPoints((r * self.cols + c).astype(np.int64), xyz)

    def extent_m(self) -> tuple[float, float, float, float]:
        xyz = self.points().xyz_m
        m = 1.5 * self.pitch_m
        return (-m, -m, float(xyz[:, 0].max()) + m, float(xyz[:, 1].max()) + m)

    def reflectance(self, x: FloatArray, y: FloatArray) -> FloatArray:
        centres = self.points().xyz_m[:, :2]
        r2 = (self.diameter_mm * MM / 2) ** 2
        black = np.zeros(x.shape, dtype=bool)
        for cx, cy in centres:
            black |= (x - cx) ** 2 + (y - cy) ** 2 <= r2
        return _on_plate(np.where(black, 0.0, 1.0), x, y, self.extent_m())

    def describe(self) -> str:
        kind = "asymmetric" if self.asymmetric else "symmetric"
        return (f"circle_grid {kind} {self.cols}x{self.rows}, pitch {self.pitch_mm:g} mm, "
                f"diameter {self.diameter_mm:g} mm")


@dataclass(frozen=True)
class Points3D:
    """A non-coplanar 3D target given point by point (YAML ``points_mm``: id -> [x, y, z])."""

    points_mm: dict[int, tuple[float, float, float]]
    type: str = "points3d"

    def points(self) -> TargetPoints:
        ids = np.array(sorted(self.points_mm), dtype=np.int64)
        xyz = np.array([self.points_mm[int(i)] for i in ids], dtype=np.float64) * MM
        return TargetPoints(ids, xyz)

    def describe(self) -> str:
        return f"points3d with {len(self.points_mm)} points"


PlanarTarget = Chessboard | Charuco | CirclePlate | CircleGrid
Target = PlanarTarget | Points3D

_FIELDS: Final[dict[str, dict[str, type]]] = {
    "chessboard": {"cols": int, "rows": int, "square_mm": float},
    "charuco": {"cols": int, "rows": int, "square_mm": float, "marker_mm": float, "dictionary": str},
    "circle_plate": {"cols": int, "rows": int, "pitch_mm": float, "diameter_mm": float},
    "circle_grid": {"cols": int, "rows": int, "pitch_mm": float, "diameter_mm": float, "asymmetric": bool},
    "points3d": {"points_mm": dict},
}
_OPTIONAL: Final[dict[str, set[str]]] = {"circle_grid": {"asymmetric"}}


def target_from_dict(d: Any, source: str = "target") -> Target:
    """Parse a target description (the YAML of docs/targets.md), strictly."""
    if not isinstance(d, dict):
        raise TargetError(f"{source}: a target file must be a mapping with a 'type' key")
    kind = d.get("type")
    if kind not in _FIELDS:
        raise TargetError(f"{source}: 'type' must be one of {sorted(_FIELDS)}, got {kind!r}")
    fields = _FIELDS[kind]
    unknown = sorted(set(d) - set(fields) - {"type"})
    if unknown:
        raise TargetError(f"{source}: unknown key(s) {unknown} for type {kind}; allowed: {sorted(fields)}")
    missing = sorted(set(fields) - set(d) - _OPTIONAL.get(kind, set()))
    if missing:
        raise TargetError(f"{source}: type {kind} needs {missing}")
    values: dict[str, Any] = {}
    for name, typ in fields.items():
        if name not in d:
            continue
        values[name] = _coerce(d[name], typ, f"{source}: {name}")
    if kind == "points3d":
        return Points3D(_parse_points(values["points_mm"], source))
    for name in ("cols", "rows"):
        if values[name] < 2:
            raise TargetError(f"{source}: {name} must be at least 2, got {values[name]}")
    for name in ("square_mm", "marker_mm", "pitch_mm", "diameter_mm"):
        if name in values and not values[name] > 0:
            raise TargetError(f"{source}: {name} must be a positive length in mm, got {values[name]}")
    if kind == "chessboard":
        return Chessboard(values["cols"], values["rows"], values["square_mm"])
    if kind == "charuco":
        if values["marker_mm"] >= values["square_mm"]:
            raise TargetError(f"{source}: marker_mm ({values['marker_mm']}) must be smaller than square_mm")
        import cv2

        if not values["dictionary"].startswith("DICT_") or not hasattr(cv2.aruco, values["dictionary"]):
            raise TargetError(f"{source}: dictionary {values['dictionary']!r} is not an OpenCV ArUco "
                              "dictionary (e.g. DICT_5X5_100)")
        return Charuco(values["cols"], values["rows"], values["square_mm"], values["marker_mm"],
                       values["dictionary"])
    if values["diameter_mm"] >= values["pitch_mm"]:
        raise TargetError(f"{source}: diameter_mm ({values['diameter_mm']}) must be smaller than pitch_mm "
                          f"({values['pitch_mm']}), or the marks touch")
    if kind == "circle_plate":
        return CirclePlate(values["cols"], values["rows"], values["pitch_mm"], values["diameter_mm"])
    return CircleGrid(values["cols"], values["rows"], values["pitch_mm"], values["diameter_mm"],
                      bool(values.get("asymmetric", False)))


def load_target(path: str | Path) -> Target:
    """Read and parse a target YAML file; errors name the file and the field."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise TargetError(f"{p}: cannot read target file ({exc.strerror})") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise TargetError(f"{p}: not valid YAML ({exc})") from exc
    return target_from_dict(data, str(p))


def target_to_dict(t: Target) -> dict[str, Any]:
    """The YAML mapping of a target (inverse of ``target_from_dict``)."""
    if isinstance(t, Points3D):
        return {"type": t.type, "points_mm": {int(k): list(v) for k, v in t.points_mm.items()}}
    out: dict[str, Any] = {"type": t.type}
    for name in _FIELDS[t.type]:
        out[name] = getattr(t, name)
    return out


def _coerce(value: Any, typ: type, where: str) -> Any:
    if typ is bool:
        if not isinstance(value, bool):
            raise TargetError(f"{where} must be true or false, got {value!r}")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TargetError(f"{where} must be a whole number, got {value!r}")
        return value
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
            raise TargetError(f"{where} must be a number, got {value!r}")
        return float(value)
    if not isinstance(value, typ):
        raise TargetError(f"{where} must be a {typ.__name__}, got {value!r}")
    return value


def _parse_points(raw: dict[Any, Any], source: str) -> dict[int, tuple[float, float, float]]:
    out: dict[int, tuple[float, float, float]] = {}
    for k, v in raw.items():
        try:
            key = int(k)
        except (TypeError, ValueError) as exc:
            raise TargetError(f"{source}: points_mm key {k!r} must be an integer id") from exc
        if (not isinstance(v, list | tuple) or len(v) != 3
                or not all(isinstance(c, int | float) and not isinstance(c, bool) for c in v)):
            raise TargetError(f"{source}: points_mm[{k}] must be [x, y, z] in mm, got {v!r}")
        out[key] = (float(v[0]), float(v[1]), float(v[2]))
    if len(out) < 6:
        raise TargetError(f"{source}: points_mm needs at least 6 points, got {len(out)}")
    return out


def _on_plate(values: FloatArray, x: FloatArray, y: FloatArray,
              extent: tuple[float, float, float, float]) -> FloatArray:
    x0, y0, x1, y1 = extent
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return np.where(inside, values, np.nan)
