"""Table 1 of the paper, reproduced and extended: fruxel display rate with a new model every frame.

Thin wrapper of :mod:`fruxel.render.table1` (method, rows and columns are described there). Prints the table,
records the run in ``benchmarks/results/table1.json`` (one entry per machine), redraws
``benchmarks/results/table1.png`` and rewrites the "## Visualisation (Table 1)" section of BENCHMARKS.md.

    .venv/bin/python benchmarks/table1.py                       # this machine, CPU backends
    python3 benchmarks/table1.py --device cuda --backends warp  # a CUDA machine (frames are CUDA tensors)

Options: ``--size WxH`` (640x480), ``--frames N`` (30 per fast row), ``--grid N`` (128), ``--backend`` (shell
kernel), ``--device``, ``--backends`` (ray-cast rows), ``--no-write``, ``--results DIR``, ``--markdown FILE``, and
``--merge OTHER/table1.json`` (add another machine's runs without measuring).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    from fruxel.cli.common import device_name, grid_size, image_size, positive_int
    from fruxel.cli.render import config_from_args
    from fruxel.render.table1 import format_table, load_runs, record, run, verdicts

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=image_size, default=None, metavar="WxH")
    p.add_argument("--frames", type=positive_int, default=None)
    p.add_argument("--grid", type=grid_size, default=None, metavar="N")
    p.add_argument("--backend", choices=("warp", "opencl"), default=None, help="shell kernel of the mesh rows")
    p.add_argument("--device", type=device_name, default=None)
    p.add_argument("--backends", default=None, help="ray-cast rows, e.g. warp,opencl or warp-cuda")
    p.add_argument("--no-write", action="store_true", help="print only")
    p.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "results", help="folder of table1.json/png")
    p.add_argument("--markdown", type=Path, default=ROOT / "BENCHMARKS.md", help="file whose Table 1 section to write")
    p.add_argument("--merge", type=Path, default=None, metavar="JSON",
                   help="measure nothing: add the runs of another machine's table1.json and rewrite the outputs")
    args = p.parse_args(argv)
    if args.merge is not None:
        runs = load_runs(args.merge)
        if not runs:
            p.error(f"no runs in {args.merge}")
        for path in record(runs, args.results, args.markdown):
            print(path)
        return 0
    result = run(config_from_args(args))
    print()
    print(format_table(result))
    for v in verdicts(result):
        print(f"  {v}")
    if not args.no_write:
        for path in record(result, args.results, args.markdown):
            print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
