"""Run every benchmark module (``benchmarks/bench_*.py``) in name order, or those named."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import time

import benchmarks


def main() -> int:
    names = sorted(
        m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_")
    )
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("only", nargs="*", help=f"benchmarks to run (default: all of {names})")
    args = parser.parse_args()
    if unknown := sorted(set(args.only) - set(names)):
        parser.error(f"unknown benchmark(s) {unknown}; choose from {names}")
    for name in args.only or names:
        print(f"== {name} ==", flush=True)
        start = time.perf_counter()
        importlib.import_module(f"benchmarks.{name}").main()
        print(f"   ({name} took {time.perf_counter() - start:.1f} s)\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
