"""``python -m benchmarks [--quick] [NAME ...]``: every benchmark in one run.

Writes Markdown tables and PNG plots under benchmarks/results/: leave-one-out on the real
brackets against the peer programs (real_loo) and with the peers' alignment (align_loo), the command line's defaults on simulated
brackets against the bound and the peers (cli_defaults), accuracy (every method
against OpenCV, colour-hdri and the Cramer-Rao bound, with speed/error plots), speed
(merge core, end-to-end CLI, peak memory, estimate-crf, calibrate-noise), CRF estimation
on the DoRF curves, noise calibration, alignment and deghosting, and what each program does
with each kind of frame (input_kinds), capture plans against conventional brackets (plan), and every
automatic choice on the real photographs against their stated answers (decisions), and where a left-out
real frame is lost, the response or the merge (loss_parts).  Those that need
../shared/data skip with a note without it; peers that are not installed are skipped with a note.
"""
from __future__ import annotations

import argparse
import importlib
import time

BENCHMARKS = ("real_loo", "align_loo", "cli_defaults", "accuracy", "speed", "crf_dorf", "noise_calibration", "motion",
              "input_kinds", "plan", "decisions", "loss_parts")


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small versions of each benchmark")
    # [] among the choices: Python 3.11's argparse checks an empty nargs="*" default against them
    ap.add_argument("names", nargs="*", choices=[[], *BENCHMARKS], default=[], metavar="NAME",
                    help=f"run only these ({', '.join(BENCHMARKS)})")
    args = ap.parse_args()
    for name in args.names or BENCHMARKS:
        t = time.perf_counter()
        print(importlib.import_module(f"benchmarks.{name}").main(args.quick))
        print(f"[{name}: {time.perf_counter() - t:.0f} s]\n", flush=True)


if __name__ == "__main__":
    main()
