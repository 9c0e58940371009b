"""``make demo``: the whole afmid loop on a simulated soft-polymer trace.

simulate (LDPE-like DMT + viscoelastic sample) -> fit with [dmt] only -> report
(where the model fails, which effect is missing) -> refit with the suggested
effect -> report comparing both runs (the error falls). Every step runs the real
command line, and the equivalent commands are printed so they can be repeated
by hand.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from afmid.cli import main as afmid_main

TEMPLATE = Path(__file__).parent / "templates" / "demo_ldpe.yaml"


def _run(args: list[str]) -> None:
    print("$ afmid " + " ".join(args), flush=True)
    code = afmid_main(args)
    if code != 0:
        raise SystemExit(f"demo step failed with exit code {code}: afmid {' '.join(args)}")


def run_demo(output: Path) -> Path:
    """Run the demo into ``output`` (replaced); returns the path of the final report."""
    if output.exists():
        shutil.rmtree(output)
    output.mkdir(parents=True)
    config = output / "ldpe_demo.yaml"
    shutil.copyfile(TEMPLATE, config)
    trace = output / "trace.h5"
    print("1. Simulate 50 periods of a stiff cantilever tapping an LDPE-like polymer (hidden: viscoelasticity)")
    _run(["-q", "simulate", str(config), "-o", str(trace)])
    print("\n2. Fit with the elastic DMT model only")
    _run(["-q", "fit", str(config), "-o", str(output / "run1.h5")])
    print("\n3. Report: where does the model fail, which effect is missing?")
    _run(["report", str(output / "run1.h5"), "-o", str(output / "report_run1")])
    summary = json.loads((output / "report_run1" / "summary.json").read_text())
    if not summary.get("suggestions"):
        print("\nNo missing effect was found; the demo stops here.")
        return output / "report_run1" / "report.html"
    effect = summary["suggestions"][0]["effect"]
    print(f"\n4. Refit with the suggested effect: --add {effect}")
    _run(["-q", "fit", str(config), "--add", effect, "-o", str(output / "run2.h5")])
    print("\n5. Compare the runs: the error falls")
    _run(["report", str(output / "run1.h5"), str(output / "run2.h5"), "-o", str(output / "report")])
    final = output / "report" / "report.html"
    print(f"\nDemo finished. Open the report: {final.resolve()}")
    return final


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m afmid.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=Path("demo_output"), help="folder to write (replaced)")
    args = parser.parse_args(argv)
    run_demo(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
