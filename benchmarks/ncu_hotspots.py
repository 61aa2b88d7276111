"""Summarise an Nsight Compute SASS source page: the most executed instructions and the mix by opcode.

    ncu -k regex:trace_first_hit -s 3 -c 1 --section SourceCounters --page source --print-source sass --csv \\
        python benchmarks/profile_cuda.py --only first_hit --repeat 3 > sass.csv
    python benchmarks/ncu_hotspots.py sass.csv

Reads the CSV that ``ncu --page source --print-source sass --csv`` prints (one row per SASS instruction, with its
execution counts) and prints the instructions executed most often, the share of each opcode and the totals, so
that a kernel's instruction budget per thread can be read off without the Nsight GUI.
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
from collections import Counter
from pathlib import Path


def rows(text: str) -> list[dict[str, str]]:
    """The CSV rows of an ncu source page (lines before the header are skipped)."""
    lines = text.splitlines()
    start = next((i for i, ln in enumerate(lines) if ln.startswith('"Address"') or ln.startswith("Address")), None)
    if start is None:
        raise SystemExit("no SASS table found (expected a header row starting with Address)")
    return list(csv.DictReader(io.StringIO("\n".join(lines[start:]))))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("csv", help="output of ncu --page source --print-source sass --csv")
    ap.add_argument("--top", type=int, default=40, help="instructions to list")
    args = ap.parse_args(argv)
    table = rows(Path(args.csv).read_text(encoding="utf-8", errors="replace"))
    key = next(k for k in table[0] if "Instructions Executed" in k and "Predicated" not in k)
    src = next(k for k in table[0] if k.strip('"') in ("Source", "SASS"))

    def count(r: dict[str, str]) -> float:
        try:
            return float(r[key].replace(",", "") or 0)
        except ValueError:
            return 0.0

    total = sum(count(r) for r in table)
    ops: Counter[str] = Counter()
    for r in table:
        op = r[src].split()[0] if r[src].split() else "?"
        if op.startswith("@"):
            op = r[src].split()[1] if len(r[src].split()) > 1 else op
        ops[op.split(".")[0]] += count(r)
    print(f"{len(table)} SASS instructions, {total:,.0f} warp instructions executed ({key})")
    print("by opcode: " + ", ".join(f"{op} {n / total:.1%}" for op, n in ops.most_common(20)))
    for r in sorted(table, key=count, reverse=True)[: args.top]:
        print(f"{count(r):>12,.0f}  {r.get('Address', r.get('# Address', ''))}  {r[src]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
