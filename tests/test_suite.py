"""The suite's own set-up: what `make test` relies on to stay fast."""

import re
import subprocess
import sys


def test_make_tests_loadgroup_keeps_a_group_on_one_worker(tmp_path):
    """`make test` runs `-n 2 --dist loadgroup`: tests marked with one `xdist_group` share a worker and so
    its module fixtures (an expensive campaign or model built once, not once per worker). pytest 9.2
    with pytest-xdist 3.8 drops the group silently (pytest-xdist#1386) - hence the pinned pytest."""
    (tmp_path / "test_grouped.py").write_text(
        "import pytest\n"
        "pytestmark = pytest.mark.xdist_group('one')\n"
        "@pytest.mark.parametrize('i', range(6))\n"
        "def test_member(i):\n"
        "    pass\n")
    done = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v", "-p",
                           "no:cacheprovider", "test_grouped.py"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    workers = re.findall(r"\[(gw\d+)\] .*PASSED test_grouped.py::test_member", done.stdout)
    assert len(workers) == 6 and len(set(workers)) == 1, done.stdout
