"""Bad-input corpus for ``afmid map`` and ``afmid simulate`` with ``simulate.map`` (contract: tests/corpus.py).

Every case is refused before a cluster starts or a chunk is fitted: one line naming the file and the key,
nothing written (no result, no sidecar folder of chunks).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import yaml

from corpus import Case, check_case, corpus_params

CONFIG = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3.0e5, "quality_factor": 250.0,
                         "tip_radius": 1e-8},
          "drive": {"frequency": 3.0e5}, "model": {"effects": ["dmt"]}}
MAP = ("map", "run.yaml", "--input", "map.h5", "-o", "out.h5")


def files(config: dict | None = None, map_file: str | None = "map.h5", shape=(2, 2, 400), dataset="deflection",
          attrs: dict | None = None, npy: bool = False):
    def write(folder: Path) -> None:
        (folder / "run.yaml").write_text(yaml.safe_dump(config or CONFIG, sort_keys=False))
        values = np.sin(np.arange(int(np.prod(shape))) * 0.0628).reshape(shape) * 5e-9
        if npy:
            np.save(folder / "map.npy", values)
        elif map_file is not None:
            with h5py.File(folder / map_file, "w") as h5:
                ds = h5.create_dataset(dataset, data=values)
                ds.attrs["units"] = "m"
                for key, value in ({"sample_rate": 2.0e7} if attrs is None else attrs).items():
                    h5.attrs[key] = value
    return write


def case(id: str, write, key: str | None, *fragments: str, argv=MAP, exit_code: int = 1, file: str | None = None,
         category: str = "data") -> Case:
    return Case(id=id, category=category, argv=tuple(argv), files=write, exit_code=exit_code, file=file, key=key,
                fragments=fragments)


SIM = dict(CONFIG, sample={"separation": 8e-9}, simulate={"model": "dmt", "parameters": {"E_star": 1e9}, "map": {
    "rows": 2, "cols": 2, "pixel_size": 1e-8, "phases": [{"name": "m"}, {"name": "d", "center": [0, 0]}]}})
SIM_SETPOINT = dict(SIM, simulate=dict(SIM["simulate"], setpoint=0.9, map=dict(SIM["simulate"]["map"],
                                                                                 phases=[{"name": "m"}])))

def with_sidecar_taken(link: bool):
    """The map's files and, at the sidecar's path (``out.h5.afmid-map``), a user's folder or a link to one."""
    def write(folder: Path) -> None:
        files()(folder)
        users = folder / ("elsewhere" if link else "out.h5.afmid-map")
        users.mkdir()
        (users / "notes.txt").write_text("my notes\n")
        (users / "key.json").write_text("{}")
        if link:
            (folder / "out.h5.afmid-map").symlink_to(users, target_is_directory=True)
    return write


CASES = [
    case("map-input-missing", files(map_file=None), "--input", "not found", file="map.h5"),
    case("map-no-deflection-dataset", files(dataset="height"), "/deflection", "no dataset /deflection",
         file="map.h5"),
    case("map-deflection-not-3d", files(shape=(4, 400)), "/deflection", "(rows, cols, samples)", file="map.h5"),
    case("map-unknown-suffix", files(), "--input", "suffix",
         argv=("map", "run.yaml", "--input", "run.yaml", "-o", "out.h5"), file="run.yaml"),
    case("map-npy-without-sample-rate", files(npy=True), "data.sample_rate", "sample rate", exit_code=2,
         argv=("map", "run.yaml", "--input", "map.npy", "-o", "out.h5"), file="run.yaml"),
    case("map-no-drive-frequency", files(config={k: v for k, v in CONFIG.items() if k != "drive"}),
         "drive.frequency", "required", exit_code=2, file="run.yaml"),
    case("map-output-is-the-input", files(), None, "is an input of this command", category="output",
         argv=("map", "run.yaml", "--input", "map.h5", "-o", "map.h5"), file="map.h5"),
    case("map-scheduler-not-an-address", files(), "--scheduler", "tcp://HOST:PORT", exit_code=2, category="config",
         argv=MAP + ("--scheduler", "localhost")),
    case("map-sidecar-name-taken-by-a-users-folder", with_sidecar_taken(link=False), "-o",
         "is not afmid's sidecar folder", category="output", file="out.h5.afmid-map"),
    case("map-sidecar-path-is-a-symlink", with_sidecar_taken(link=True), "-o", "is a symbolic link",
         category="output", file="out.h5.afmid-map"),
    case("map-add-unknown-effect", files(), "model.effects", "--add: unknown effect", exit_code=2, category="config",
         argv=MAP + ("--add", "viscoelastik"), file="run.yaml"),
    case("simulate-map-domain-without-radius", files(config=SIM, map_file=None), "simulate.map", "radius",
         exit_code=2, category="config", argv=("simulate", "run.yaml", "-o", "sim.h5"), file="run.yaml"),
    case("simulate-map-at-a-setpoint", files(config=SIM_SETPOINT, map_file=None), "simulate.setpoint", exit_code=2,
         category="config", argv=("simulate", "run.yaml", "-o", "sim.h5"), file="run.yaml"),
]


@corpus_params(CASES)
def test_map_case(case, tmp_path, capsys, monkeypatch):
    check_case(case, tmp_path / "ws", capsys, monkeypatch)


def test_an_existing_output_is_not_replaced_without_overwrite(tmp_path, capsys, monkeypatch):
    def write(folder: Path) -> None:
        files()(folder)
        (folder / "out.h5").write_bytes(b"keep me")

    check_case(case("map-output-exists", write, None, "output exists", category="output", file="out.h5"),
               tmp_path / "ws", capsys, monkeypatch)
