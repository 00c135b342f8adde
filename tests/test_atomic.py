"""Atomic writes: all or nothing, with ordinary file permissions."""

import os

import pytest

from crashfuse.io.atomic import atomic_path, write_text


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
