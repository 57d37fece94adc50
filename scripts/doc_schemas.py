"""Regenerate the schema tables of docs/formats.md from the declared specs.

    python scripts/doc_schemas.py            # rewrite the marked regions in place
    python scripts/doc_schemas.py --check    # exit 1 if a region is out of date

A region is the text between ``<!-- schema: KIND -->`` and ``<!-- /schema -->``
(KIND one of :data:`mems_stereo.util.schemas.SCHEMAS`); this script owns it.
``tests/test_json_schemas.py`` makes the same comparison.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "formats.md"
REGION = re.compile(r"(<!-- schema: (\S+) -->\n)(.*?)(<!-- /schema -->)", re.S)


def main(argv=None) -> int:
    from mems_stereo.util.schemas import schema_markdown

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if a region is out of date")
    args = ap.parse_args(argv)
    text = DOC.read_text()
    new = REGION.sub(lambda m: m.group(1) + schema_markdown(m.group(2)) + m.group(4), text)
    if args.check:
        if new != text:
            print(f"{DOC}: schema tables out of date; run python scripts/doc_schemas.py")
            return 1
        return 0
    if new != text:
        DOC.write_text(new)
        print(f"rewrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
