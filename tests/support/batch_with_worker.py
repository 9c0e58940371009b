"""``afmid batch`` run with one of :mod:`batch_workers`' workers, for the tests whose batch subprocess must hold
or lose a worker mid-item (Ctrl-C mid-fit, a second batch on a busy folder, workers outliving a killed parent).

afmid has no command-line hook for a foreign worker (issue 30: no test hooks in the shipped package). This script
calls what ``afmid batch`` calls, :func:`afmid.batch.run.run_batch`, with ``worker=batch_workers.WORKER`` (its
documented parameter), under afmid's own signal handling (:func:`afmid.interrupts.handled`), and ends as the
command ends: 130 after Ctrl-C (143 after SIGTERM) with the line of what finished and ``interrupted``, 1 (or the
error's own code) with afmid's one-line error, 0 otherwise.

    python tests/support/batch_with_worker.py WORKER [CONFIG] (--inputs GLOB | --configs GLOB) -o OUT [-j N]
        [--set KEY=VALUE ...]

(:data:`batch_workers.HOLD_2S` etc. are such commands without the batch arguments.)

Run as a script, its own folder (tests/support) is first on ``sys.path``; spawned workers inherit it, so they
unpickle the worker function by its module name like any other.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import batch_workers
from afmid.batch.run import BatchInterrupted, run_batch
from afmid.errors import AfmidError
from afmid.interrupts import EXIT_INTERRUPTED, EXIT_TERMINATED, handled

def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="batch_with_worker")
    parser.add_argument("worker")
    parser.add_argument("config", nargs="?", type=Path)
    parser.add_argument("--inputs", action="append", default=[])
    parser.add_argument("--configs", action="append", default=[])
    parser.add_argument("-o", "--output", required=True, type=Path)
    parser.add_argument("-j", "--jobs", type=int)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    args = parser.parse_args(argv)
    worker = getattr(batch_workers, args.worker)
    with handled():
        try:
            result = run_batch(args.config, args.output, inputs=args.inputs, configs=args.configs, jobs=args.jobs,
                               overrides=args.overrides, progress=False, worker=worker)
        except BatchInterrupted as exc:
            print(f"afmid: batch stopped with {exc.result.line()}; interrupted", file=sys.stderr)
            return EXIT_TERMINATED if exc.terminated else EXIT_INTERRUPTED
        except AfmidError as exc:
            print(f"afmid: error: {exc.format()}", file=sys.stderr)
            return exc.exit_code
    print(f"batch: {result.line()}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
