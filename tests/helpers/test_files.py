"""calibration.io.files: a file that is missing, unreadable, not JSON or not YAML is the caller's typed error."""

from __future__ import annotations

from pathlib import Path

import pytest

from calibration.io import read_json, read_text, read_yaml


class MyError(ValueError):
    pass


def test_reads_text_json_and_yaml(tmp_path: Path) -> None:
    (tmp_path / "a.txt").write_text("hello\n")
    (tmp_path / "a.json").write_text('{"K": [[1, 0], [0, 1]], "rms_px": 0.1}')
    (tmp_path / "a.yaml").write_text("type: chessboard\ncols: 9\n")
    assert read_text(tmp_path / "a.txt", "a note", MyError) == "hello\n"
    assert read_json(tmp_path / "a.json", "a camera file", MyError) == {"K": [[1, 0], [0, 1]], "rms_px": 0.1}
    assert read_yaml(str(tmp_path / "a.yaml"), "a target file", MyError) == {"type": "chessboard", "cols": 9}


def test_a_missing_file_names_the_file_the_role_and_the_reason(tmp_path: Path) -> None:
    with pytest.raises(MyError) as err:
        read_json(tmp_path / "cam.json", "camera file", MyError)
    msg = str(err.value)
    assert msg.startswith(str(tmp_path / "cam.json")) and "cannot read camera file" in msg
    assert "No such file or directory" in msg
    assert isinstance(err.value.__cause__, FileNotFoundError)


def test_a_folder_and_a_binary_file_are_refused(tmp_path: Path) -> None:
    with pytest.raises(MyError, match="cannot read the config"):
        read_text(tmp_path, "the config", MyError)
    (tmp_path / "x.png").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00")
    with pytest.raises(MyError, match="not a text file"):
        read_yaml(tmp_path / "x.png", "a target file", MyError)


def test_bad_json_names_line_and_column(tmp_path: Path) -> None:
    p = tmp_path / "cam.json"
    p.write_text('{\n  "K": [1, 2,\n}\n')
    with pytest.raises(MyError) as err:
        read_json(p, "a camera file (cam.json)", MyError)
    assert "not valid JSON (line 3, column 1" in str(err.value)
    assert str(err.value).endswith("expected a camera file (cam.json)")


def test_bad_yaml_names_line_and_column(tmp_path: Path) -> None:
    p = tmp_path / "t.yaml"
    p.write_text("type: chessboard\ncols: [9\nrows: 6\n")
    with pytest.raises(MyError) as err:
        read_yaml(p, "a target file", MyError)
    msg = str(err.value)
    assert msg.startswith(f"{p}: not valid YAML (line ") and "column" in msg and "expected a target file" in msg
