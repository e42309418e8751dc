"""A pipe or a device where a file is expected is refused before it is
opened (a FIFO would block the read for ever, /dev/zero never end)."""
import os

import pytest

from support.cli import run_cli


@pytest.fixture
def fifo(tmp_path):
    path = tmp_path / "pipe.exr"
    os.mkfifo(path)
    return path


@pytest.mark.parametrize("argv", [("info", "{f}"), ("lens", "info", "{f}"),
                                  ("correct", "--image", "{f}", "--lens", "mos-s1", "--method", "deconv",
                                   "--one-depth", "2", "-o", "{d}/out.exr"),
                                  ("olf", "info", "{f}")])
def test_a_pipe_is_refused_not_waited_on(tmp_path, fifo, capsys, argv):
    code, _, err = run_cli(capsys, *(a.format(f=fifo, d=tmp_path) for a in argv))
    assert code == 2 and "not a regular file" in err and err.count("\n") == 1, err


def test_a_device_is_refused_as_an_image(tmp_path, capsys):
    link = tmp_path / "zero.exr"
    os.symlink("/dev/zero", link)
    code, _, err = run_cli(capsys, "info", link)
    assert code == 2 and "not a regular file" in err, err
