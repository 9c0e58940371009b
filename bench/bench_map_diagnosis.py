"""Benchmark: what the group diagnosis adds to a 64x64 map's wall time (issue 31), measured end to end.

Workload: configs/maps/blend_hidden_viscous.yaml (a glassy matrix and a soft domain hiding viscoelasticity, fitted
with [dmt]) as a 64x64 map of 9,984-sample traces (78 periods x 128 samples, as bench_map.py's map) over a
128 nm square (2 nm pixels), so that the soft domain covers ~20 % of the map and its pixels make a model-limited
group (the one diagnosed); simulated once and cached in bench/results/ (~250 MB). ``afmid -q map ... -j 2`` (default chunks)
twice: ``--no-diagnosis``, then with the diagnosis (the default); wall and CPU of each whole process tree (client,
dask workers), peak RSS. The share is (with - without) / without in wall time. Both results' pixel maps are
compared (the diagnosis changes only /groups). --quick: a 16x16 map over the same square (8 nm pixels; the share is then no measure of the target: the
diagnosis costs the same, the map 1/16). Cost on a quiet machine (estimated): the 64x64 map's simulation ~6 min of
CPU (once), each map ~3 min of CPU.

Run: python bench/bench_map_diagnosis.py [--quick]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import CONFIGS, RESULTS, SINGLE_THREAD, bench_main, differing, load_average, measured, met_word, row  # noqa: E402

CONFIG = CONFIGS / "maps" / "blend_hidden_viscous.yaml"
AFMID = [sys.executable, "-m", "afmid.cli", "-q"]
PERIODS = 78  # x 128 samples per period = 9,984 samples per pixel
MAP_WIDTH = 128e-9  # m: the soft domain (radius 35 nm, centred at 30 nm, 30 nm) over ~20 % of the map
SHARE_TARGET = 0.20
JOBS = 2


def make_map(side: int) -> Path:
    """The hidden-viscoelasticity map, side x side pixels, simulated once into bench/results/."""
    path = RESULTS / f"map_hidden_{side}x{side}_1e4.h5"
    if not path.exists():
        RESULTS.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial.h5")
        measured(AFMID + ["simulate", str(CONFIG), "-o", str(partial), "--overwrite",
                          "--set", f"simulate.map.rows={side}", "--set", f"simulate.map.cols={side}",
                          "--set", f"simulate.periods={PERIODS}",
                          "--set", f"simulate.map.pixel_size={MAP_WIDTH / side}"],
                 timeout=7200)
        partial.rename(path)
    return path


def groups(result: Path) -> str:
    """Each group's size and verdict, with the number of representatives diagnosed."""
    import h5py

    with h5py.File(result, "r") as h5:
        g = h5["groups"]
        sizes, verdicts = g["pixels"][()], g["verdict"][()]
        representatives = g["representatives"][()]
    parts = []
    for size, verdict, chosen in zip(sizes, verdicts, representatives):
        text = verdict.decode() if isinstance(verdict, bytes) else str(verdict)
        parts.append(f"{int(size)} px: {text} ({int((chosen >= 0).sum())} diagnosed)")
    return "; ".join(parts)


def run(quick: bool = False) -> list[dict]:
    side = 16 if quick else 64
    source = make_map(side)
    with tempfile.TemporaryDirectory(prefix="afmid-bench-mapdiag-") as tmp:
        tmp = Path(tmp)
        got = {}
        for key, switch in (("without", "--no-diagnosis"), ("with", "--diagnosis")):
            load = load_average()
            got[key] = measured(AFMID + ["map", str(CONFIG), "--input", str(source), "-o", str(tmp / f"{key}.h5"),
                                         "-j", str(JOBS), switch], SINGLE_THREAD, timeout=7200, ok_codes=(0, 1))
            got[key]["load"] = load
        verdicts = groups(tmp / "with.h5")
        changed = [k for k in differing(tmp / "without.h5", tmp / "with.h5")
                   if not k.startswith("groups") and k != "maps/group"]
    without, with_ = got["without"], got["with"]
    share = (with_["wall"] - without["wall"]) / without["wall"]
    cpu_share = (with_["cpu"] - without["cpu"]) / without["cpu"]
    return [
        row(f"map {side}x{side} (9,984 samples per pixel, -j {JOBS}), group diagnosis: share of the map's wall time",
            with_["wall"], without["wall"], share, f"<= {SHARE_TARGET:.0%}" if not quick else "(quick: none)",
            share <= SHARE_TARGET if not quick else None,
            f"'afmid' = the map with its group diagnosis, 'reference' = --no-diagnosis, 'ratio' = the share "
            f"(with - without) / without; without {without['wall']:.1f} s wall (CPU {without['cpu']:.1f} s, load at "
            f"start {without['load']}), with {with_['wall']:.1f} s (CPU {with_['cpu']:.1f} s, load {with_['load']}); "
            f"the diagnosis's CPU {with_['cpu'] - without['cpu']:.1f} s ({cpu_share:.1%} of the map's CPU); "
            f"groups: {verdicts}; peak RSS {max(without['rss_gb'], with_['rss_gb']):.2f} GB; datasets other than "
            f"the groups that differ: {changed or 'none'}",
            cpu_s=with_["cpu"], share=share, cpu_share=cpu_share),
    ]


def main() -> None:
    bench_main(__doc__, run, "a 16x16 map",
               describe=lambda r: f"{r['name']}: share {r['ratio']:.1%} ({met_word(r['met'])})\n  {r['notes']}")


if __name__ == "__main__":
    main()
