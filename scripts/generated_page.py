"""The command line shared by the scripts that write a documentation page from code (parameter tables, the
report's schema): write it, or with ``--check`` exit 1 when the file differs (the tests run that)."""
import argparse
import sys
from pathlib import Path
from typing import Callable


def main_for(out: Path, page: Callable[[], str], script: str, description: str) -> int:
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 when the page is out of date")
    args = ap.parse_args()
    text = page()
    if args.check:
        if not out.exists() or out.read_text() != text:
            print(f"{out} is out of date: run python scripts/{script}", file=sys.stderr)
            return 1
        return 0
    out.write_text(text)
    print(f"wrote {out}")
    return 0
