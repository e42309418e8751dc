"""The Omni-Lens-Field file is read once for every source opened from it
(a refocus opens a new source), and read again when the file changes."""
import os
import shutil

from dcdi_core.psf import sources as library
from dcdi_core.optics.lens import load_lens


def test_the_olf_file_is_read_once_and_again_when_it_changes(tmp_path):
    path = tmp_path / "olf.npz"
    shutil.copy(library.SHIPPED, path)
    lens = load_lens("6p")
    a = library.psf_source(lens, olf_file=path, focus_m=2.0)
    b = library.psf_source(lens, olf_file=path, focus_m=3.0)
    assert a.kind == b.kind == "olf" and a.library is not b.library
    assert a.library.olf is b.library.olf                   # one file, read once
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    c = library.psf_source(lens, olf_file=path, focus_m=2.0)
    assert c.library.olf is not a.library.olf               # changed on disk: read again
