"""The seed paper's Tables 1-4 and Figs. 2, 3, 5 rerun on the virtual rig, side by side with the paper.

The same as ``make paper`` / ``ambfit paper``: every experiment of Tables 1, 3 and 4 as the
paper ran it, 200 replicates for the predicted scatter and spread (noise calibrated on
Table 2 only), the paper's own gap excess.  Writes reports/paper/ (index.html, README.md,
comparison.csv, spread.csv, reproduction.json, PNG figures); about 4.5 minutes.

    .venv/bin/python benchmarks/paper_reproduction.py [--replicates 200] [--workers N | --scheduler ADDRESS]

``--workers N`` runs the replicates on N local worker processes, ``--scheduler`` on a running Dask
cluster (``pip install 'ambfit[dask]'``); the same seed gives the same tables wherever they run.
"""

import argparse
from pathlib import Path

from ambfit.engine import Engine
from ambfit.faces.report import paper_report

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replicates", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "reports" / "paper")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes (default: this process)")
    ap.add_argument("--scheduler", default=None, help="address of a running Dask scheduler, e.g. tcp://host:8786")
    args = ap.parse_args()
    # the report's reproduction runs its replicates on the engine of this block (ambfit.engine.using)
    with Engine(workers=args.workers, scheduler=args.scheduler):
        path = paper_report(args.out, replicates=args.replicates, seed=args.seed,
                            command=f"python benchmarks/paper_reproduction.py --replicates {args.replicates}")
    print((args.out / "README.md").read_text().split("## Table 1")[0])
    print(f"wrote {path}")
