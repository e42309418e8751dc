"""`dcdi info FILE`: what an image file remembers of how it was made."""
from __future__ import annotations

import json


def cmd_info(args) -> int:
    from ..io.capture_record import has_header, read_record, sidecar_path
    from ..io.image_checks import image_size
    h, w = image_size(args.file)
    record = read_record(args.file)
    where = None
    if record is not None:
        where = "the EXR header" if has_header(args.file) else str(sidecar_path(args.file))
    if args.json:
        print(json.dumps({"file": str(args.file), "size_px": [h, w], "record_in": where,
                          "record": None if record is None else json.loads(record.as_json())}, indent=2))
        return 0
    print(f"{args.file}: {h} x {w} px (height x width)")
    if record is None:
        print("no capture record: correct, dof and bokeh take this image to span the lens's sensor diagonal "
              "unless told its pixel pitch (--pixel-pitch)")
        return 0
    print(f"capture record (in {where}):")
    for line in record.lines():
        print(f"  {line}")
    if record.image_size is not None and tuple(record.image_size) != (h, w):
        print(f"  note: recorded for {record.image_size[0]} x {record.image_size[1]} px, the file is {h} x {w}: "
              "the record does not describe this file's pixels (resized or cropped since); it is ignored")
    return 0


def add_commands(sub) -> None:
    q = sub.add_parser("info", help="what an image file remembers of how it was made (lens, pixel pitch, axis, ...)",
                       description="Print an image's size and its capture record: the lens and its prescription "
                                   "hash, pixel pitch, optical axis, focus, PSF source, noise model and distortion "
                                   "that dcdi simulate, the factory or the Blender add-on wrote with it (EXR header, "
                                   "or a <file>.dcdi.json sidecar for PNG and JPEG).")
    q.add_argument("file", help="an image file (.exr, .png, .jpg)")
    q.add_argument("--json", action="store_true", help="print JSON")
    q.set_defaults(func=cmd_info)
