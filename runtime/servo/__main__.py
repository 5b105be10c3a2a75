"""``python -m pmask.runtime.servo --include | --sources``: where the servo core's C files are, on one line
each, for a Makefile (the module's command line: its output is the point, so it prints)."""
from __future__ import annotations

import argparse
import sys

from pmask.runtime.servo import include_dir, sources


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m pmask.runtime.servo", description=__doc__)
    p.add_argument("--include", action="store_true", help="the include folder")
    p.add_argument("--sources", action="store_true", help="the C files, space-separated")
    a = p.parse_args(argv)
    if a.include or not a.sources:
        print(include_dir())
    if a.sources:
        print(" ".join(str(f) for f in sources()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
