"""`sine demo` checks every option before any work (no training that ends in a KeyError)."""

from __future__ import annotations

import pytest

from edit.demo import DemoConfig, check_options
from sine_cli import main


@pytest.mark.parametrize(
    "args, message",
    [
        (["--procedural", "figurine", "--paint-part", "cabin"], "not a part of the figurine"),
        (["--edit-view", "36"], "--edit-view 36 is out of range: the demo renders 36 views"),
        (["--views", "8", "--edit-view", "8"], "(0 to 7)"),
        (["--views", "2"], "--views must be >= 3"),
        (["--edit-view", "-1"], "--edit-view must be >= 0"),
    ],
)
def test_bad_options_fail_before_any_work(tmp_path, capsys, args, message):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()  # nothing synthesised, nothing trained


def test_out_naming_a_file_is_an_error(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    assert main(["demo", "--out", str(tmp_path / "file")]) == 2
    assert "is an existing file" in capsys.readouterr().err


def test_auto_paint_part_follows_the_object(tmp_path):
    assert check_options(DemoConfig(out=tmp_path, procedural="toycar")) == "cabin"
    assert check_options(DemoConfig(out=tmp_path, procedural="figurine")) == "head"
    assert check_options(DemoConfig(out=tmp_path, procedural="figurine", paint_part="hat")) == "hat"
