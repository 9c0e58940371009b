"""Benchmark: ``afmid map`` on a local dask cluster of 1 and 2 worker processes.

Map: configs/maps/blend_map.yaml (a glassy matrix with soft raised domains; 25 periods at 128 samples per period,
3,200 samples per pixel, bootstrap 20), 6x6 pixels (quick: 3x3), simulated once and cached in bench/results/.
Timed: ``afmid -q map ... -j N --chunk 2`` end to end (process start to exit, cluster start-up included) for
N = 1 and 2; per-pixel cost = the 1-worker wall time / pixels. Rows with the issue's targets: the 64x64 map of
10^4-sample traces in < 90 s on 2 cores (extrapolated from the measured per-pixel cost and the trace length,
linear in samples) and the speed-up from 1 to 2 workers >= 1.8x. Accuracy: median E* per phase vs the truth.

Run: python bench/bench_map.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import CONFIGS, RESULTS, row, wall  # noqa: E402

CONFIG = CONFIGS / "maps" / "blend_map.yaml"
AFMID = [sys.executable, "-m", "afmid.cli"]
TARGET_64_S = 90.0
TARGET_SPEEDUP = 1.8


def make_map(side: int) -> Path:
    path = RESULTS / f"map_{side}x{side}.h5"
    if not path.exists():
        RESULTS.mkdir(parents=True, exist_ok=True)
        wall(AFMID + ["-q", "simulate", str(CONFIG), "-o", str(path), "--set", f"simulate.map.rows={side}",
                      "--set", f"simulate.map.cols={side}"])
    return path


def phase_accuracy(result: Path, truth_file: Path) -> str:
    import h5py
    import numpy as np

    with h5py.File(result, "r") as r, h5py.File(truth_file, "r") as t:
        e, ok = r["maps/E_star"][()], r["maps/status"][()] < 2
        phase, truth = t["truth/phase"][()], t["truth/E_star"][()]
        names = [n.decode() if isinstance(n, bytes) else n for n in t["truth/phase_names"][()]]
    parts = []
    for k in np.unique(phase):
        px = ok & (phase == k)
        got, want = np.median(e[px]), truth[px][0]
        parts.append(f"{names[k]} {got / 1e9:.3f} vs {want / 1e9:.3f} GPa ({100 * (got / want - 1):+.1f} %, "
                     f"{int(px.sum())} px)")
    return "; ".join(parts)


def run(quick: bool) -> list[dict]:
    side = 3 if quick else 6
    source = make_map(side)
    n = side * side
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        for jobs in (1, 2):
            out = Path(tmp) / f"result_{jobs}.h5"
            times[jobs] = wall(AFMID + ["-q", "map", str(CONFIG), "--input", str(source), "-o", str(out), "-j",
                                        str(jobs), "--chunk", "2"], timeout=7200)
        accuracy = phase_accuracy(Path(tmp) / "result_2.h5", source)
    per_pixel = times[1] / n
    speedup = times[1] / times[2]
    estimate_64 = per_pixel * 64 * 64 * (1e4 / 3200) / 2
    return [
        row(f"map {side}x{side} (3,200 samples/pixel), 1 worker", times[1], None, None, "", None,
            f"per-pixel cost {per_pixel:.2f} s (cluster start-up included)"),
        row(f"map {side}x{side}, 2 workers", times[2], times[1], speedup, f">= {TARGET_SPEEDUP}x speed-up",
            speedup >= TARGET_SPEEDUP, f"speed-up 1 -> 2 workers {speedup:.2f}x; accuracy: {accuracy}"),
        row("map 64x64 of 10^4 samples on 2 workers (extrapolated)", estimate_64, None, None,
            f"< {TARGET_64_S:.0f} s", estimate_64 < TARGET_64_S,
            "per-pixel cost x 4,096 pixels x (10^4 / 3,200 samples) / 2 workers"),
    ]


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    for r in run(parser.parse_args().quick):
        print(r)
