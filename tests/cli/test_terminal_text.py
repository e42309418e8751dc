"""Nothing read from a file drives the user's terminal (a capture record's
or a lens file's text is printed with its control characters escaped), a
reader that goes away ends the command quietly, and an option the command
would drop is refused."""
import subprocess
import sys
from pathlib import Path

import numpy as np

from dcdi_core.cli import main
from dcdi_core.names import printable, terminal_safe

# a forged line of ours, a window title set, the screen cleared, the text turned right to left, a carriage return
HOSTILE = "f/2\ndcdi: error: forged\x1b]0;owned\x07\x1b[2J\u202eevil\r"


def _no_control(text: str) -> None:
    assert not any(c in text for c in "\x1b\x07\u202e"), repr(text)
    assert "evil\r" not in text, repr(text)          # the file's carriage return: escaped (printable)
    assert not [line for line in text.splitlines() if line.startswith("dcdi: error: forged")], text


def test_printable_escapes_every_control_and_keeps_the_rest():
    assert printable("Zeiss Sonnar \u0192/1.5 \u2014 50 mm") == "Zeiss Sonnar \u0192/1.5 \u2014 50 mm"
    out = printable(HOSTILE)
    assert out.isprintable()
    assert all(e in out for e in ("\\n", "\\x1b", "\\x07", "\\u202e", "\\r"))
    assert printable("abcdefgh", 6) == "abc..."
    # the command line's own stream keeps its line breaks, tabs and carriage returns (a progress line), and
    # escapes the rest
    assert terminal_safe("a\tb\nc\x1b[2Jd\re") == "a\tb\nc\\x1b[2Jd\re"


def test_a_capture_records_text_reaches_the_terminal_escaped(tmp_path, capsys):
    from dcdi_core.io.capture_record import CaptureRecord, write_sidecar
    from dcdi_core.io.images import write_image
    img = tmp_path / "cap.png"
    write_image(img, np.full((8, 12, 3), 0.5, np.float32))
    write_sidecar(img, CaptureRecord(kind="rendered", extra={"iris": HOSTILE}))
    assert main(["info", str(img)]) == 0
    out = capsys.readouterr()
    _no_control(out.out + out.err)
    assert "dcdi: error: forged" in out.out            # shown, escaped, on the record's own line


def test_a_lens_files_name_reaches_the_terminal_escaped(tmp_path, capsys):
    text = (Path(__file__).resolve().parents[2] / "lenses" / "mos-s1.toml").read_text(encoding="utf-8")
    name = HOSTILE.replace("\\", "\\\\").replace("\n", "\\n").replace("\r", "\\r").replace("\x1b", "\\u001b") \
        .replace("\x07", "\\u0007").replace("\u202e", "\\u202e")
    lines = [f'name = "{name}"' if line.startswith("name =") else line for line in text.splitlines()]
    f = tmp_path / "hostile.toml"
    f.write_text("\n".join(lines).replace('id = "mos-s1"', 'id = "hostile"'), encoding="utf-8")
    assert main(["lens", "info", str(f)]) == 0
    out = capsys.readouterr()
    _no_control(out.out + out.err)
    assert "\\x1b" in out.out


def test_a_closed_pipe_ends_the_command_quietly():
    """`dcdi lens list | head -n 1`: head goes away before dcdi writes (its
    output leaves at the end, in one block); dcdi ends without a traceback
    or Python's "Exception ignored", exit 141 as a process SIGPIPE ends."""
    p = subprocess.Popen([sys.executable, "-m", "dcdi_core", "lens", "list"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.close()                                   # the reader is gone before anything is written
    err = p.stderr.read().decode()
    code = p.wait(60)
    assert err == "", err
    assert code == 141


def test_blade_rotation_without_blades_is_refused(tmp_path, capsys):
    code = main(["psf", "mos-s1", "--field", "0", "--depth", "1", "--blade-rotation", "30",
                 "--out", str(tmp_path / "p.npz")])
    err = capsys.readouterr().err
    assert code == 2 and "--blade-rotation" in err and "--blades" in err, err
    assert not (tmp_path / "p.npz").exists()


def test_an_output_onto_a_shipped_file_is_refused(tmp_path, capsys):
    """`dcdi psf ... --out` onto the shipped ray map it reads (or any file the
    engine ships) is refused before any work; the file is unchanged."""
    import dcdi_core
    shipped = Path(dcdi_core.__file__).resolve().parent / "psf" / "data" / "raymap" / "zeiss-sonnar-50mm-f1-5.npz"
    before = shipped.read_bytes()
    code = main(["psf", "zeiss-sonnar-50mm-f1-5", "--field", "0", "--depth", "2", "--out", str(shipped)])
    err = capsys.readouterr().err
    assert code == 2 and "ships" in err and "--out" in err, err
    assert shipped.read_bytes() == before
