"""Write afmid's example data into data/ (run from anywhere: python scripts/make_example_data.py).

Everything here is SIMULATED (no measured LDPE trace is public) and labelled so
in the files and in data/README.md:

1. ``data/ldpe_like_50periods.h5``: ``afmid simulate configs/ldpe_like.yaml``,
   50 drive periods of a stiff cantilever tapping an LDPE-like viscoelastic
   polymer, with its ground truth in ``/truth``.
2. ``data/example_trace.h5``: the same config, 20 periods at 100 samples per
   period (an afmid trace file with ground truth; the reference motion).
3. The same motion in every supported format, each in a different but
   realistic form (units, sign, where the sample rate is), with a fit config
   ``data/example_<format>.yaml`` that loads it back to the same deflection in
   metres: CSV (volts, time column, needs data.invols), NPY (bare nm array),
   NPZ (pm, sample rate in the archive), plain HDF5 (nm dataset in a group with
   a time dataset), MAT v5 (nm, positive away from the sample), IBW (metres,
   x scaling in seconds), TDMS (nm, wf_increment).

The simulation is seeded, so the samples are the same on every run (file
bytes differ only in creation timestamps). Needs the ``formats`` extra (npTDMS).
"""

from __future__ import annotations

import argparse
import struct
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from afmid.cli import main as afmid_main  # noqa: E402

LDPE_CONFIG = ROOT / "configs" / "ldpe_like.yaml"
LABEL = (
    "SIMULATED with afmid simulate (configs/ldpe_like.yaml): a stiff cantilever tapping an LDPE-like "
    "viscoelastic polymer (DMT + Kelvin-Voigt); not a measurement"
)
#: Inverse optical lever sensitivity used for the volts example, m/V (a typical 50-100 nm/V).
INVOLS = 60.0e-9
PERIODS = 20
SAMPLES_PER_PERIOD = 100

#: The common part of every example fit config: the calibration a user would have from a thermal tune.
FIT_SECTIONS = """\
cantilever:                    # calibration (thermal tune of the simulated lever)
  spring_constant: 40.0        # N/m
  resonance_frequency: 3.0e+5  # Hz
  quality_factor: 250
  tip_radius: 10.0e-9          # m

drive:
  frequency: 3.0e+5            # Hz, nominal; the fit re-measures it

sample:
  a0: 0.165e-9                 # m; the rest separation is estimated by the fit

model:
  effects: [dmt, viscoelastic] # the physics the trace was simulated with

fit: {}
"""


def simulate(output: Path, *extra: str) -> None:
    code = afmid_main(["-q", "simulate", str(LDPE_CONFIG), "-o", str(output), "--overwrite", *extra])
    if code != 0:
        raise SystemExit(f"afmid simulate failed ({code})")
    import h5py

    with h5py.File(output, "a") as h5:
        h5.attrs["simulated"] = True
        h5.attrs["description"] = LABEL
    output.chmod(0o644)  # afmid writes outputs through mkstemp, which leaves them private (0600)


def write_ibw5(path: Path, data: np.ndarray, step: float, data_units: bytes, x_units: bytes, name: bytes) -> None:
    """A 1-D Igor binary wave, version 5, little-endian float64 (WaveMetrics Technical Note 003).

    igor2 reads but cannot write .ibw files; the layout follows igor2.binarywave:
    version (int16), BinHeader5 (64 bytes with it), WaveHeader5 (320 bytes), data.
    """
    data = np.asarray(data, dtype="<f8")
    wdata = data.tobytes()
    wave_header = (
        struct.pack("<IIIihh6xh32s4xI", 0, 0, 0, data.size, 4, 0, 1, name, 0)  # type 4 = NT_FP64
        + struct.pack("<4i", data.size, 0, 0, 0)
        + struct.pack("<4d", step, 1, 1, 1)  # sfA: x step
        + struct.pack("<4d", 0, 0, 0, 0)  # sfB: x start
        + data_units.ljust(4, b"\0")
        + x_units.ljust(4, b"\0")
        + b"\0" * 12
    ).ljust(320, b"\0")
    bin_header = struct.pack("<hhiiii4i4iiii", 5, 0, 320 + len(wdata), 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    head = bytearray(bin_header + wave_header)
    checksum = -sum(struct.unpack(f"<{len(head) // 2}h", head)) % 65536  # int16 sum of the headers is zero
    head[2:4] = struct.pack("<H", checksum)
    path.write_bytes(bytes(head) + wdata)


def write_formats(out: Path, x: np.ndarray, rate: float) -> dict[str, tuple[str, str]]:
    """The motion ``x`` (m, toward the sample) in every format; returns format -> (file name, data section)."""
    import h5py
    from nptdms import ChannelObject, GroupObject, RootObject, TdmsWriter
    from scipy.io import savemat

    t = np.arange(x.size) / rate
    files: dict[str, tuple[str, str]] = {}

    path = out / "example.csv"
    lines = [f"# {LABEL}", f"# deflection in volts from the photodetector; InvOLS {INVOLS:g} m/V", "time_s,deflection_V"]
    lines += [f"{ti!r},{vi!r}" for ti, vi in zip(t.tolist(), (x / INVOLS).tolist())]
    path.write_text("\n".join(lines) + "\n")
    files["csv"] = (path.name, f"""\
  column: deflection_V         # the photodetector signal, volts
  time_column: time_s          # seconds; the sample rate follows from it
  units: V
  invols: 60.0e-9              # m/V, inverse optical lever sensitivity (from a force curve on a hard surface)
  positive: toward_sample""")

    path = out / "example.npy"
    np.save(path, x * 1e9)
    files["npy"] = (path.name, f"""\
  sample_rate: {rate:.1f}      # Hz: a bare array says nothing about itself
  units: nm""")

    path = out / "example.npz"
    np.savez(path, deflection_pm=x * 1e12, sample_rate=np.float64(rate), note=np.array(LABEL))
    files["npz"] = (path.name, """\
  column: deflection_pm        # units from the array name; the sample rate from the scalar 'sample_rate'""")

    path = out / "example_plain.h5"
    with h5py.File(path, "w") as h5:
        h5.attrs["description"] = LABEL
        group = h5.create_group("AFM")
        group.attrs["sample_rate"] = rate
        group.create_dataset("deflection", data=x * 1e9).attrs["units"] = "nm"
        group.create_dataset("time", data=t).attrs["units"] = "s"
    files["hdf5"] = (path.name, """\
  column: /AFM/deflection      # units from its 'units' attribute, the rate from /AFM's 'sample_rate'""")

    path = out / "example.mat"
    savemat(path, {"defl_nm": -x * 1e9, "sample_rate": rate, "description": LABEL}, format="5")
    files["mat"] = (path.name, """\
  column: defl_nm              # units from the variable name; the rate from the scalar 'sample_rate'
  positive: away_from_sample   # this instrument counts deflection positive away from the sample""")

    path = out / "example.ibw"
    write_ibw5(path, x, 1.0 / rate, b"m", b"s", b"Defl")
    files["ibw"] = (path.name, """\
  # one wave: data units m, x scaling in s give the units and the sample rate""")

    path = out / "example.tdms"
    with TdmsWriter(path) as writer:
        writer.write_segment([
            RootObject(properties={"description": LABEL}),
            GroupObject("AFM"),
            ChannelObject("AFM", "deflection", x * 1e9,
                          properties={"unit_string": "nm", "wf_increment": 1.0 / rate, "wf_start_offset": 0.0}),
        ])
    files["tdms"] = (path.name, """\
  column: AFM/deflection       # group/channel; unit_string and wf_increment give units and rate""")
    return files


def write_configs(out: Path, files: dict[str, tuple[str, str]]) -> None:
    for fmt, (name, data_lines) in files.items():
        text = (f"# Fit config for {name}: the example trace (SIMULATED, see data/README.md) in {fmt} form.\n"
                f"# Run: afmid fit data/example_{fmt}.yaml -o run.h5\n\n"
                f"data:\n  path: {name}\n{data_lines}\n\n{FIT_SECTIONS}")
        (out / f"example_{fmt}.yaml").write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=ROOT / "data", help="folder to write (default: data/)")
    parser.add_argument("--skip-ldpe", action="store_true", help="do not re-simulate the 50-period LDPE trace")
    args = parser.parse_args(argv)
    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    if not args.skip_ldpe:
        simulate(out / "ldpe_like_50periods.h5")
    reference = out / "example_trace.h5"
    simulate(reference, "--set", f"simulate.periods={PERIODS}",
             "--set", f"simulate.samples_per_period={SAMPLES_PER_PERIOD}")
    import h5py

    with h5py.File(reference, "r") as h5:
        x, rate = h5["deflection"][()], float(h5.attrs["sample_rate"])
    files = write_formats(out, x, rate)
    write_configs(out, {"trace": (reference.name, "  # an afmid trace file: units, rate, cantilever and drive "
                                                  "come from the file"), **files})
    total = sum(p.stat().st_size for p in out.iterdir() if p.is_file())
    written = len(files) + (1 if args.skip_ldpe else 2)
    print(f"wrote {written} data files and {len(files) + 1} configs in {out} ({total / 1e6:.2f} MB in the folder)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
