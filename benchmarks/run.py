"""Run every benchmark in one process and print their tables (``make bench``).

``--smoke`` runs each at a tiny size (used by the test suite to keep the scripts working).
Results worth keeping go to ``benchmarks/README.md`` with the machine description.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import rbo_jax  # noqa: E402,F401  (float64 on before anything else)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, for tests")
    parser.add_argument("--only", nargs="*", default=None,
                        help="subset of: sweep simulate stability fitting")
    args = parser.parse_args(argv)
    import importlib

    import jax

    runs = {
        # first: it splits the CPU into 2 XLA devices, which must happen before JAX starts
        "sweep": ("bench_sweep", ["--n", "60", "--chunk", "30", "--scipy-sample", "2"]
                  if args.smoke else []),
        "simulate": ("bench_simulate", ["--n", "40", "--chunk", "20", "--scipy-sample", "2"]
                     if args.smoke else []),
        "stability": ("bench_stability", ["--n-per-axis", "4", "--numpy-sample", "5", "--chunk", "32"]
                      if args.smoke else []),
        "fitting": ("bench_fitting", ["--samples", "20", "--trajectories", "1"] if args.smoke else []),
    }
    print(f"{time.strftime('%Y-%m-%d')}  {platform.platform()}  {os.cpu_count()} CPUs  "
          f"jax {jax.__version__}  python {platform.python_version()}", flush=True)
    results = {}
    for name, (module, fargs) in runs.items():
        if args.only and name not in args.only:
            continue
        print(f"\n=== {name} ===", flush=True)
        # imported here: a benchmark module may create arrays at import, which starts JAX (the
        # sweep benchmark must set the CPU device count before that)
        results[name] = importlib.import_module(module).main(fargs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
