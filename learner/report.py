"""``learner report``: the results page, ``docs/results.md``, from the CSVs under ``results/``.

The page (:mod:`learner.results_page`) is made of the CSVs of the jobs it names
(:mod:`learner.jobs`): the headline's experiments on fresh seeds and the appendix's studies
(:mod:`learner.appendix`). ``learner report`` runs the jobs whose CSV is missing, then writes
the page; ``--rerun`` runs every job again; ``--reuse`` runs nothing and refuses a missing
CSV, naming the command that makes it. The page depends on the CSVs alone, so ``--reuse``
on a fresh clone rewrites it byte for byte.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from learner.jobs import Job
from learner.results_page import all_jobs, write_page, write_readme_table
from learner.tables import Row, read_csv
from tpsr_ros.cli import positive_int
from tpsr_ros.core.errors import ConfigError

__all__ = ["register", "run", "run_jobs"]


def register(subparsers: Any) -> None:
    """Add the ``report`` subcommand."""
    doc = "regenerate docs/results.md from the experiment and study CSVs under results/"
    parser = subparsers.add_parser(
        "report", help=doc, description=doc[0].upper() + doc[1:] + ". " + __doc__.split("\n\n")[1]
    )
    parser.add_argument(
        "--results",
        type=Path,
        default=Path("results"),
        help="directory of the CSVs (default: results)",
    )
    parser.add_argument("--docs", type=Path, default=Path("docs"), help="(default: docs)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument(
        "--reuse", action="store_true", help="run nothing; every CSV must exist"
    )
    mode.add_argument("--rerun", action="store_true", help="run every job again")
    parser.add_argument("--workers", type=positive_int, default=2)
    parser.set_defaults(run=run)


def run_jobs(jobs: list[Job], results: Path, *, rerun: bool, workers: int) -> None:
    """Run the jobs whose CSV is missing under ``results`` (every job with ``rerun``)."""
    from learner.cli import main as learner_main

    pending = [job for job in jobs if rerun or not job.path(results).exists()]
    for number, job in enumerate(pending, start=1):
        print(f"[{number}/{len(pending)}] {job.command}", file=sys.stderr, flush=True)
        start = time.perf_counter()
        learner_main(job.argv_for(results, workers))
        print(f"      {time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)


def _read(jobs: list[Job], results: Path) -> dict[Job, list[Row]]:
    data = {}
    for job in jobs:
        path = job.path(results)
        if not path.exists():
            raise ConfigError(f"{path} does not exist; make it with: {job.command}")
        data[job] = read_csv(path)
    return data


def run(args: argparse.Namespace) -> int:
    """Run what is needed (unless ``--reuse``), then write the page and its figures."""
    if not args.docs.is_dir():
        raise ConfigError(f"docs directory {str(args.docs)!r} does not exist")
    jobs = all_jobs()
    if not args.reuse:
        run_jobs(jobs, args.results, rerun=args.rerun, workers=args.workers)
    data = _read(jobs, args.results)
    page = write_page(data, args.docs)
    readme = args.docs.parent / "README.md"
    if readme.exists():  # the README's results table and summary line, from the same CSVs
        write_readme_table(data, readme)
    written = f" and the results table and summary of {readme}" if readme.exists() else ""
    print(f"wrote {page}{written}", file=sys.stderr)
    return 0
