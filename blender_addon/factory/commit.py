"""A sample's files written as hidden temporaries (``StagedFiles``) and
renamed into place together with its manifest line (``commit_sample``):
stopped, killed or out of disk space, a sample is in the folder whole with
its line, or not at all (what a kill leaves between the two is removed on
resume: ``folder.remove_unfinished_files``)."""
from __future__ import annotations

import os
from pathlib import Path

from dcdi_core.dataset.factory_folder import append_record


class StagedFiles:
    """A sample's files under hidden temporary names beside their places
    (``.<name>.p<pid>_<random>.tmp.exr``: the form a resume removes as a
    killed run's), renamed into place only with the sample's manifest line
    (:func:`commit_sample`). It stands in for the folder's layout when the
    folder format's writers (``factory_folder.write_rgbd``,
    ``write_lens_images``) ask where each file goes."""

    def __init__(self, layout):
        self.layout = layout
        self.moves: list[tuple[Path, Path]] = []        # (temporary, its place), in the order written

    def aif(self, sid: str) -> Path:
        return self._stage(self.layout.aif(sid))

    def depth(self, sid: str) -> Path:
        return self._stage(self.layout.depth(sid))

    def lens_image(self, lens: str, kind: str, sid: str) -> Path:
        return self._stage(self.layout.lens_image(lens, kind, sid))

    def _stage(self, path: Path) -> Path:
        import secrets
        tmp = path.with_name(f".{path.name}.p{os.getpid()}_{secrets.token_hex(4)}.tmp{path.suffix}")
        self.moves.append((tmp, path))
        return tmp

    def discard(self) -> None:
        """Remove the temporaries not renamed (all of them, unless committed)."""
        for tmp, _ in self.moves:
            tmp.unlink(missing_ok=True)


def commit_sample(files: StagedFiles, manifest: Path, record: dict) -> None:
    """Rename a sample's staged files into place, then append its manifest
    line: both or neither. A stop waits for the commit (``deferred``: a
    few renames and one flushed line, milliseconds), then stops the run
    with the sample kept. A failure (a full disk while appending) removes
    the files already renamed and cuts the manifest back to its length
    before, so the folder holds the sample whole with its line or not at
    all. A kill (SIGKILL, a power cut) between the renames and the line
    leaves files without a line: the next run removes them
    (``folder.remove_unfinished_files``)."""
    from dcdi_core.errors import output_error
    from dcdi_core.signals import deferred
    with deferred():
        size = manifest.stat().st_size if manifest.exists() else None
        placed = []
        try:
            for tmp, path in files.moves:
                try:
                    os.replace(tmp, path)
                except OSError as e:
                    raise output_error(path, e) from None
                placed.append(path)
            append_record(manifest, record)
        except BaseException:
            for path in placed:
                path.unlink(missing_ok=True)
            _cut_back(manifest, size)
            raise


def _cut_back(manifest: Path, size: int | None) -> None:
    """The manifest back to ``size`` bytes (None: it did not exist), best
    effort: a part of a line that stays is dropped as torn on resume."""
    try:
        if size is None:
            manifest.unlink(missing_ok=True)
        else:
            os.truncate(manifest, size)
    except OSError:
        pass
