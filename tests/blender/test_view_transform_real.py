"""The viewport preview's colours in a real Blender binary (Debian's 5.2:
Python 3.14, numpy 2): `blender -b --factory-startup --python
blender_addon/tools/view_transform_error.py -- --json` bakes each case's
table with that Blender's colour management and compares it with that
Blender's own display; the assertions of tests/addon/test_view_transform.py
(pip bpy) are made on what it measured."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "addon"))

import test_view_transform as _vt  # noqa: E402
# the fixtures by import: a conftest.py here would shadow tests/conftest.py's helpers
from realblender_support import blender, our_tracebacks  # noqa: E402,F401

pytestmark = pytest.mark.realblender

for _n in [n for n in dir(_vt) if n.startswith("test_")]:
    globals()[_n] = getattr(_vt, _n)


@pytest.fixture(scope="module")
def measured(blender, tmp_path_factory):  # noqa: F811
    res = _vt.run_tool(tmp_path_factory.mktemp("view-transform-real"), blender=blender)
    assert not our_tracebacks(res["log"]), res["log"][-3000:]
    return res


def test_it_ran_in_the_blender_binary(measured, blender):  # noqa: F811
    assert measured["blender"] and "Blender " + measured["blender"] in measured["log"]
