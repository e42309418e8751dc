"""``python -m dcdi_core.demo --out DIR [--factory-sample DIR | --factory-error TEXT]``:
the demo job with the dataset-factory sample that ``python build.py demo``
rendered (or the reason it has none)."""
from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m dcdi_core.demo", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--factory-sample", default=None, metavar="DIR", help="a dataset-factory output folder")
    g.add_argument("--factory-error", default=None, metavar="TEXT", help="why there is no factory sample")
    a = p.parse_args(argv)
    from ..errors import DcdiError
    from .job import run
    try:
        return run(a.out, factory_sample=a.factory_sample, factory_error=a.factory_error)
    except DcdiError as e:
        print("dcdi demo: error: " + " ".join(str(e).split()), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
