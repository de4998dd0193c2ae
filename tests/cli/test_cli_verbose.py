"""``cellctl -v`` shows the traceback of an error; without ``-v`` the error stays one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellctl.cli import main


def _render_missing_target(tmp_path: Path, *flags: str) -> list[str]:
    return [*flags, "target", "render", "--target", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "t.svg")]


def test_without_verbose_the_error_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(_render_missing_target(tmp_path))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("cellctl: error:") and "missing.yaml" in err[0]


def test_verbose_shows_the_traceback_then_the_one_line_error(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    code = main(_render_missing_target(tmp_path, "-v"))
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback (most recent call last)" in err
    assert "load_target" in err  # the frame that raised is named
    last = err.strip().splitlines()[-1]
    assert last.startswith("cellctl: error:") and "missing.yaml" in last


def test_verbose_shows_the_traceback_of_a_command_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "obs.csv"
    bad.write_text("not,the,header\n")
    target = tmp_path / "t.yaml"
    target.write_text("type: points3d\npoints_mm:\n" + "".join(f"  {i}: [{i * 10}, {i % 2 * 10}, {i % 3 * 5}]\n"
                                                            for i in range(8)))
    out = str(tmp_path / "c.json")
    code = main(["-v", "calib", "dlt", "--target", str(target), "--points", str(bad), "--out", out])
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback (most recent call last)" in err and "CommandError" in err
    assert err.strip().splitlines()[-1].startswith("cellctl: error:")
