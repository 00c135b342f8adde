"""Atomic writes: all or nothing, with ordinary file permissions."""

import os

import pytest

from crashfuse.io.atomic import atomic_path, default_mode, write_text


def test_write_text_creates_a_readable_file(tmp_path):
    out = tmp_path / "a" / "b.txt"
    write_text(out, "hello")
    assert out.read_text() == "hello"
    mask = os.umask(0)
    os.umask(mask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~mask


def test_failure_leaves_nothing_behind(tmp_path):
    out = tmp_path / "c.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(out) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_default_mode_is_what_open_and_mkdir_give(tmp_path):
    old = os.umask(0o027)
    try:
        (tmp_path / "d").mkdir()
        (tmp_path / "f").touch()
        assert (default_mode(), default_mode(directory=True)) == (0o640, 0o750)
    finally:
        os.umask(old)
    assert (tmp_path / "d").stat().st_mode & 0o777 == 0o750
    assert (tmp_path / "f").stat().st_mode & 0o777 == 0o640
