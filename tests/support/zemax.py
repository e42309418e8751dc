"""Zemax .zmx test files: a singlet's text, written as ASCII (CRLF) or UTF-16 with a BOM."""
from __future__ import annotations

import codecs

HEADER = """VERS 190513 80 123
MODE SEQ
NAME Test singlet f/5
PFIL 0 0 0
UNIT {unit} X W X CM MR CPMM
ENPD 10
GCAT SCHOTT OHARA
FTYP 0 0 1 3 0 0 0
XFLN 0 0 0 0 0 0 0 0 0 0 0 0
YFLN 0 14 20 0 0 0 0 0 0 0 0 0
WAVM 1 0.48613270000000001 1
WAVM 2 0.58756180000000004 1
WAVM 3 0.65627250000000003 1
WAVM 4 0.55000000000000004 1
PWAV 2
POLS 1 0 1 0 0 1 0
SURF 0
  TYPE STANDARD
  FIMP

  CURV 0.0 0 0 0 0 ""
  HIDE 0 0 0 0 0 0 0 0 0 0
  MIRR 2 0
  SLAB 1
  DISZ INFINITY
  DIAM 0 0 0 0 1 ""
  POPS 0 0 0 0 0 0 0 0 1 1 1 1 0 0 0 0
"""

STOP_SURF = """SURF 1
  STOP
  COMM aperture "stop"
  TYPE STANDARD
  CURV 0.0 0 0 0 0 ""
  MIRR 2 0
  DISZ 2
  DIAM 5 1 0 0 1 ""
  MEMA 5 0 0 0 1 ""
"""

SINGLET_BODY = """SURF 2
  TYPE STANDARD
  CURV 0.02 0 0 0 0 ""
  HIDE 0 0 0 0 0 0 0 0 0 0
  DISZ 4
  GLAS {glass}
  DIAM 6 1 0 0 1 ""
SURF 3
  TYPE STANDARD
  CURV -0.005 0 0 0 0 ""
  DISZ 95.5
  DIAM 6.2 0 0 0 1 ""
SURF 4
  TYPE STANDARD
  CURV 0.0 0 0 0 0 ""
  DISZ 0
  DIAM 21.6 0 0 0 1 ""
BLNK
TOL TOFF   0   0              0              0   0 0 0 0
MNUM 1 1
"""

MODEL_GLASS = "___BLANK 1 0 1.5168 64.170000000000002 0 0 0 0 0 0"


def singlet_text(glass=MODEL_GLASS, unit="MM", stop=STOP_SURF):
    return HEADER.format(unit=unit) + stop + SINGLET_BODY.format(glass=glass)


def write_ascii(path, text):
    path.write_bytes(text.replace("\n", "\r\n").encode("ascii"))
    return path


def write_utf16(path, text):
    path.write_bytes(codecs.BOM_UTF16_LE + text.replace("\n", "\r\n").encode("utf-16-le"))
    return path
