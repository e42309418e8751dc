"""What every shipped .npz with a JSON ``meta`` record shares (the networks'
files, the PSF bases): a checked reader, the checks of the metadata's
fields, the checksum over the record and the arrays, and a cache that reads
a file once until it changes on disk. numpy only.

A model or basis file may come from anyone (``dcdi depth estimate --refine
FILE``, ``--olf``, ``--basis``, ``--model``), so :func:`read_npz` reads it
as hostile: nothing is allocated that the file's size does not bound.

- the file: at most :data:`MAX_FILE_BYTES` on disk, checked before it is
  opened (the largest shipped one, the OLF, is 10.5 MB; a float32 paper-size
  radial OLF of four lenses would be about 450 MB);
- its members: at most :data:`MAX_MEMBERS`, each a ``.npy`` array, stored or
  deflated (numpy's ``savez`` / ``savez_compressed``), not encrypted;
  together at most :data:`MAX_ARRAY_BYTES` uncompressed and at most
  :data:`EXPANSION` times the file's size (plus 1 MiB), so a small file
  never inflates to gigabytes (the shipped files store 1.0-1.2 bytes per
  byte on disk);
- each array: its header read first (no pickle, ever: object and structured
  dtypes are refused), booleans, integers or floats of at most
  :data:`MAX_DIMS` dimensions whose declared size is exactly the bytes the
  member holds; floats must be finite (a NaN weight otherwise runs silently);
- ``meta``: one JSON object of at most :data:`MAX_META_CHARS` characters.

Each caller passes ``fail(message, field=None, allowed=None) -> exception``:
its own error class (``ModelFileError``, ``BasisFileError``), so every
problem is one line naming the file, the field and what is allowed.
:class:`Record` checks the metadata's fields (required keys, integer and
number ranges, names) the same way, before anything they size is allocated.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import stat
import struct
import zipfile
import zlib
from pathlib import Path

from .jsontext import loads

MIB = 1 << 20
MAX_FILE_BYTES = 1024 * MIB           # a file on disk
MAX_ARRAY_BYTES = 2048 * MIB          # all its arrays, uncompressed
EXPANSION = 16                        # uncompressed bytes per byte on disk, at most (+ 1 MiB): weights deflate 1-4x
MAX_MEMBERS = 4096                    # arrays in one file (a paper-size DACN holds about 1,000)
MAX_DIMS = 8                          # dimensions of one array
MAX_META_CHARS = 1 * MIB              # the JSON record (the shipped ones: 0.6-6.5 thousand)
# what a file's metadata may make the engine allocate beyond its own arrays
# (a PSF library of its grid and kernel size: the shipped 6P's is 251 MB; 3x that keeps a job on a
# file of a few MB under 1.5 GB)
MAX_DECLARED_BYTES = 768 * MIB
_HEADER_CHARS = 10_000                # numpy's own limit of an .npy header
_CHUNK = 4 * MIB                      # bytes read at a time

# what reading a damaged file raises: truncated or not a zip (BadZipFile,
# EOFError), a member's bytes changed (BadZipFile: CRC, zlib.error), not an
# .npz of arrays (ValueError: pickled or bad header), unreadable (OSError)
READ_ERRORS = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error, RuntimeError,
               NotImplementedError, OverflowError, struct.error)


def file_error_text(path, message: str, field=None, allowed=None) -> str:
    """The one line of a file's error: 'FILE, field 'F': MESSAGE; allowed: A'
    (as ``errors.ModelFileError`` writes it)."""
    text = str(path) + (f", field '{field}'" if field is not None else "") + f": {message}"
    return text + (f"; allowed: {allowed}" if allowed is not None else "")


def check_file_size(path, fail, limit: int | None = None) -> int:
    """The size (bytes) of ``path``, refused (``fail``) over ``limit``
    (default :data:`MAX_FILE_BYTES`) before a byte of it is read."""
    limit = MAX_FILE_BYTES if limit is None else limit
    try:
        st = os.stat(path)
    except OSError as e:
        raise fail(f"cannot be read ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):             # a FIFO would block the read for ever
        raise fail("not a regular file (a folder, a pipe or a device)")
    size = st.st_size
    if size > limit:
        raise fail(f"{size} bytes, over the limit", field="file size",
                   allowed=f"at most {limit} bytes ({limit / MIB:g} MiB)")
    return size


def read_npz(path, fail, *, meta_required: bool = True) -> tuple[dict | None, dict]:
    """(meta, arrays) of an .npz read as hostile (module docstring); any
    damage or excess is ``fail(message, field=None, allowed=None)``.
    ``meta``: the JSON object of the member ``meta`` (None if absent and not
    ``meta_required``)."""
    from ..errors import DcdiError
    path = Path(path)
    size = check_file_size(path, fail)
    try:
        with zipfile.ZipFile(path) as zf:
            infos = _members(zf, size, fail)
            arrays = {name: _read_array(zf, info, name, fail) for name, info in infos.items()}
    except DcdiError:
        raise
    except (READ_ERRORS + (MemoryError, RecursionError)) as e:
        raise fail(f"not a readable .npz file ({type(e).__name__}: {str(e)[:200]})") from None
    meta = _meta(arrays.pop("meta", None), fail, meta_required)
    for name, a in arrays.items():
        _check_finite(name, a, fail)
    return meta, arrays


def save_npz(file, arrays: dict, *, compressed: bool = True) -> None:
    """numpy's ``savez_compressed`` (``compressed`` False: ``savez``) of
    ``arrays`` to ``file`` (a path or an open binary file), the same bytes,
    with the zip closed on every path: numpy leaves it open when a write
    fails (a full disk), and the collector closing it later onto the closed
    file prints "Exception ignored ... seek of closed file" after the error,
    or after a run that went on."""
    import zipfile

    import numpy as np
    kind = zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED
    with zipfile.ZipFile(file, mode="w", compression=kind, allowZip64=True) as z:
        for name, value in arrays.items():
            with z.open(f"{name}.npy", "w", force_zip64=True) as fid:
                np.lib.format.write_array(fid, np.asanyarray(value), allow_pickle=False)


def write_format(path, meta: dict, arrays: dict, fmt: str, version: int) -> None:
    """Write ``arrays`` and ``meta`` (JSON) with its ``format``, ``version``
    and :func:`checksum`, compressed and atomically: what :func:`read_format` reads."""
    import numpy as np

    from ..atomic import atomic_path
    meta = dict(meta, format=fmt, version=version)
    meta["checksum"] = checksum(meta, arrays)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            save_npz(f, {"meta": np.array(json.dumps(meta)), **arrays})


def read_format(path, fail, fmt: str, version: int) -> tuple[dict, dict]:
    """:func:`read_npz` of a file that names its ``format`` and ``version``
    and carries a :func:`checksum` in its metadata: each checked, in that
    order, before any field is read."""
    meta, arrays = read_npz(path, fail)
    if meta.get("format") != fmt:
        raise fail(f"format {str(meta.get('format'))[:80]!r}", field="format", allowed=repr(fmt))
    if meta.get("version") != version:
        raise fail(f"version {str(meta.get('version'))[:80]!r}", field="version",
                   allowed=f"{version} (what this software reads)")
    if meta.get("checksum") != checksum(meta, arrays):
        raise fail("checksum mismatch (the file is corrupt or was edited)", field="checksum")
    return meta, arrays


def _members(zf: zipfile.ZipFile, size: int, fail) -> dict:
    """{array name: ZipInfo}, refused before any is read if there are too
    many, one is not a plain .npy member, or together they would inflate
    beyond the limits."""
    infos = zf.infolist()
    if len(infos) > MAX_MEMBERS:
        raise fail(f"{len(infos)} members", field="arrays", allowed=f"at most {MAX_MEMBERS}")
    out, total = {}, 0
    for info in infos:
        if not info.filename.endswith(".npy") or info.filename[:-4] in out:
            raise fail(f"member {info.filename[:80]!r} is not one .npy array", field="arrays")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED) or info.flag_bits & 0x1:
            raise fail(f"member {info.filename[:80]!r} is encrypted or compressed by method {info.compress_type}",
                       field="arrays", allowed="stored or deflated (numpy's savez, savez_compressed)")
        out[info.filename[:-4]] = info
        total += info.file_size
    limit = min(MAX_ARRAY_BYTES, EXPANSION * size + MIB)
    if total > limit:
        raise fail(f"its arrays would take {total} bytes uncompressed", field="arrays",
                   allowed=f"at most {limit} bytes ({EXPANSION} x the file's size + 1 MiB, "
                           f"{MAX_ARRAY_BYTES / MIB:g} MiB in all)")
    return out


def _read_array(zf: zipfile.ZipFile, info: zipfile.ZipInfo, name: str, fail):
    """One member's array: its header checked before its data is allocated."""
    import numpy as np
    from numpy.lib import format as npy
    with zf.open(info) as f:
        version = npy.read_magic(f)
        if version not in ((1, 0), (2, 0)):
            raise fail(f"array {name!r}: .npy format version {version}", field=name, allowed="1.0 or 2.0")
        read_header = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
        shape, fortran, dtype = read_header(f, max_header_size=_HEADER_CHARS)
        _check_dtype(name, dtype, shape, fail)
        nbytes = math.prod(shape) * dtype.itemsize
        held = info.file_size - f.tell()
        if nbytes != held:
            raise fail(f"array {name!r} declares {shape} {dtype} ({nbytes} bytes) but holds {held} bytes",
                       field=name)
        buf = bytearray(nbytes)
        view, at = memoryview(buf), 0
        while at < nbytes:
            got = f.readinto(view[at:at + _CHUNK])
            if not got:
                raise fail(f"array {name!r} is truncated ({at} of {nbytes} bytes)", field=name)
            at += got
        f.read(1)                     # at the end: the member's CRC is checked
    a = np.frombuffer(buf, dtype=dtype) if nbytes else np.zeros(0, dtype)
    return a.reshape(shape[::-1]).transpose() if fortran else a.reshape(shape)


def _check_dtype(name: str, dtype, shape, fail) -> None:
    """Booleans, integers, floats (and the metadata's text): never objects
    (pickles) or structured records."""
    text = name == "meta" and dtype.kind == "U"
    if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None or \
            not (dtype.kind in "biuf" or text) or dtype.itemsize == 0:
        raise fail(f"array {name!r} has dtype {dtype}", field=name,
                   allowed="booleans, integers or floats (no objects: pickles are refused)")
    if len(shape) > MAX_DIMS or any(n < 0 for n in shape):
        raise fail(f"array {name!r} has shape {shape[:MAX_DIMS + 1]}", field=name,
                   allowed=f"at most {MAX_DIMS} dimensions, each >= 0")


def _meta(a, fail, required: bool) -> dict | None:
    """The JSON object held by the ``meta`` member."""
    if a is None:
        if required:
            raise fail("no metadata record (not an exported model or basis file)", field="meta")
        return None
    if a.dtype.kind != "U" or a.size != 1 or a.dtype.itemsize // 4 > MAX_META_CHARS:
        raise fail(f"the metadata record is {a.dtype} of shape {a.shape}", field="meta",
                   allowed=f"one JSON text of at most {MAX_META_CHARS} characters")
    try:
        meta = loads(str(a.reshape(())[()]), "the metadata record")
    except ValueError as e:
        raise fail(f"the metadata record is not JSON ({type(e).__name__}: {str(e)[:120]})", field="meta") from None
    if not isinstance(meta, dict):
        raise fail("the metadata record is not a JSON object", field="meta")
    return meta


def _check_finite(name: str, a, fail) -> None:
    import numpy as np
    if a.dtype.kind == "f":
        bad = int(a.size - np.count_nonzero(np.isfinite(a)))
        if bad:
            raise fail(f"array {name!r} holds {bad} NaN or infinite values", field=name, allowed="finite numbers")


def check_array(arrays: dict, name: str, shape: tuple, fail, kinds: str = "f"):
    """``arrays[name]``, refused unless present with exactly ``shape`` and a
    dtype of a kind in ``kinds`` ('f' floats, 'b' booleans, 'iu' integers)."""
    a = arrays.get(name)
    if a is None:
        raise fail(f"array {name!r} is missing", field=name, allowed=f"shape {tuple(shape)}")
    if tuple(a.shape) != tuple(shape) or a.dtype.kind not in kinds:
        want = {"f": "floats", "b": "booleans"}.get(kinds, "integers")
        raise fail(f"array {name!r} is {a.dtype} of shape {tuple(a.shape)}", field=name,
                   allowed=f"{want} of shape {tuple(shape)}")
    return a


# --------------------------------------------------------------- metadata
class Record:
    """One JSON table of a file's metadata, checked field by field before
    what the fields size is allocated. Each check returns the value or raises
    ``fail`` naming the field (dotted from the record's root: 'spec.width',
    'lenses[1].kernel_size') and what is allowed; a missing required key is
    such an error too, never a KeyError."""

    def __init__(self, table, fail, prefix: str = ""):
        self.fail, self.prefix = fail, prefix
        if not isinstance(table, dict):
            raise fail(f"{type(table).__name__}, not a table", field=prefix.rstrip(".") or "meta",
                       allowed="a JSON object")
        self.table = table

    def where(self, key) -> str:
        return f"{self.prefix}{key}"

    def refuse(self, key, value, allowed: str):
        """The error of a value out of range (a list by its length)."""
        from ..names import shown
        found = f"a list of {len(value)}" if isinstance(value, list) else shown(value)
        return self.fail(f"{found} is out of range", field=self.where(key), allowed=allowed)

    def value(self, key, optional: bool = False, allowed: str = "a value"):
        """The raw value; None for an absent or null optional one."""
        v = self.table.get(key)
        if v is None and not optional:
            raise self.fail("is missing" if key not in self.table else "is null", field=self.where(key),
                            allowed=allowed)
        return v

    def allowed_keys(self, keys) -> None:
        """Refuse a key outside ``keys`` (a table that a constructor takes as keyword arguments)."""
        extra = sorted(set(self.table) - set(keys), key=str)
        if extra:
            raise self.fail(f"unknown key {str(extra[0])[:80]!r}", field=self.where(extra[0]),
                            allowed=", ".join(sorted(keys)))

    def integer(self, key, lo: int, hi: int, *, optional: bool = False, odd: bool = False) -> int | None:
        allowed = f"{'an odd' if odd else 'an'} integer in [{lo}, {hi}]"
        return _integer(self.value(key, optional, allowed), lo, hi, odd, lambda v: self.refuse(key, v, allowed))

    def number(self, key, lo: float, hi: float, *, optional: bool = False, inf: bool = False,
               lo_open: bool = False) -> float | None:
        allowed = _number_range(lo, hi, inf, lo_open)
        return _number(self.value(key, optional, allowed), lo, hi, inf, lo_open,
                       lambda v: self.refuse(key, v, allowed))

    def integers(self, key, lo: int, hi: int, count: tuple[int, int], *, odd: bool = False,
                 optional: bool = False) -> list[int] | None:
        allowed = f"{count[0]}-{count[1]} {'odd ' if odd else ''}integers in [{lo}, {hi}]"
        items = self._list(key, count, optional, allowed)
        return None if items is None else [
            _integer(v, lo, hi, odd, lambda v, i=i: self.refuse(f"{key}[{i}]", v, allowed))
            for i, v in enumerate(items)]

    def numbers(self, key, lo: float, hi: float, count: tuple[int, int], *, inf: bool = False,
                lo_open: bool = False, optional: bool = False) -> list[float] | None:
        allowed = f"{count[0]}-{count[1]} numbers in {_number_range(lo, hi, inf, lo_open)}"
        items = self._list(key, count, optional, allowed)
        return None if items is None else [
            _number(v, lo, hi, inf, lo_open, lambda v, i=i: self.refuse(f"{key}[{i}]", v, allowed))
            for i, v in enumerate(items)]

    def text(self, key, *, optional: bool = False, max_chars: int = 4096) -> str | None:
        allowed = f"a string of at most {max_chars} characters"
        v = self.value(key, optional, allowed)
        if v is not None and (not isinstance(v, str) or len(v) > max_chars):
            raise self.refuse(key, v, allowed)
        return v

    def name(self, key, *, optional: bool = False) -> str | None:
        """A value that becomes part of a file name (a lens id): ``names.NAME_RULE``."""
        from ..names import NAME_RULE, name_problem, shown
        v = self.value(key, optional, NAME_RULE)
        why = None if v is None else name_problem(v)
        if why:
            raise self.fail(f"{shown(v)} is {why}", field=self.where(key), allowed=NAME_RULE)
        return v

    def choice(self, key, choices, *, optional: bool = False):
        allowed = " or ".join(map(repr, choices))
        v = self.value(key, optional, allowed)
        if v is not None and (not isinstance(v, (str, int, float)) or v not in choices):
            raise self.refuse(key, v, allowed)
        return v

    def flag(self, key, *, optional: bool = False) -> bool | None:
        v = self.value(key, optional, "true or false")
        if v is not None and not isinstance(v, bool):
            raise self.refuse(key, v, "true or false")
        return v

    def sub(self, key, *, optional: bool = False) -> "Record | None":
        """The table at ``key``."""
        v = self.value(key, optional, "a table")
        return None if v is None else Record(v, self.fail, f"{self.where(key)}.")

    def subs(self, key, count: tuple[int, int]) -> list["Record"]:
        """The list of tables at ``key``."""
        items = self._list(key, count, False, f"{count[0]}-{count[1]} tables")
        return [Record(v, self.fail, f"{self.where(key)}[{i}].") for i, v in enumerate(items)]

    def strings(self, key, count: tuple[int, int], *, max_chars: int = 256) -> list[str]:
        allowed = f"{count[0]}-{count[1]} strings of at most {max_chars} characters"
        items = self._list(key, count, False, allowed)
        for i, v in enumerate(items):
            if not isinstance(v, str) or len(v) > max_chars:
                raise self.refuse(f"{key}[{i}]", v, allowed)
        return items

    def _list(self, key, count, optional, allowed):
        v = self.value(key, optional, allowed)
        if v is not None and (not isinstance(v, list) or not count[0] <= len(v) <= count[1]):
            raise self.refuse(key, v, allowed)
        return v


def _number_range(lo, hi, inf, lo_open) -> str:
    return f"{'(' if lo_open else '['}{lo:g}, {hi:g}]" + (" or infinity" if inf and hi != math.inf else "")


def _integer(v, lo, hi, odd, refuse):
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi or (odd and v % 2 == 0):
        raise refuse(v)
    return v


def _number(v, lo, hi, inf, lo_open, refuse):
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise refuse(v)
    x = float(v)
    if x == math.inf and inf:
        return x
    if not (lo < x <= hi if lo_open else lo <= x <= hi):
        raise refuse(v)
    return x


def check_declared_bytes(nbytes: int, what: str, field: str, fail, limit: int | None = None) -> None:
    """Refuse metadata that would make the engine allocate ``nbytes`` (``what``
    names it: 'the PSF library of its grid') beyond :data:`MAX_DECLARED_BYTES`."""
    limit = MAX_DECLARED_BYTES if limit is None else limit
    if nbytes > limit:
        raise fail(f"{what} would take {nbytes} bytes", field=field,
                   allowed=f"at most {limit} bytes ({limit / MIB:g} MiB)")


def checksum(meta: dict, arrays: dict) -> str:
    """sha256 of the metadata (without its checksum) and every array (name, dtype, shape, bytes)."""
    import numpy as np
    h = hashlib.sha256()
    h.update(json.dumps({k: v for k, v in meta.items() if k != "checksum"}, sort_keys=True).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


class FileCache:
    """``load(path)`` kept for the next request of the same file (its
    resolved path, size and modification time), at most ``size`` files; a
    file changed on disk is read again. ``stat`` errors pass to the caller."""

    def __init__(self, load, size: int, name: str | None = None):
        self._load, self._size, self._kept = load, size, {}
        from .. import caches           # one registry the add-on's session clears
        caches.register(name or f"{getattr(load, '__qualname__', 'files')}", self.clear, lambda: len(self._kept))

    def clear(self) -> None:
        self._kept.clear()

    def __call__(self, path):
        path = Path(path)
        st = path.stat()
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
        if key not in self._kept:
            if len(self._kept) >= self._size:
                self._kept.clear()
            self._kept[key] = self._load(path)
        return self._kept[key]
