"""The small test map (tests/configs/map_small.yaml: 3x3, a glassy matrix and a soft domain 1 nm higher)
simulated into a folder and read back as a map worker reads it, for the tests of the pixel fits."""

from __future__ import annotations

from pathlib import Path

from repo_paths import REPO_ROOT

CONFIG = REPO_ROOT / "tests" / "configs" / "map_small.yaml"


def simulated_pixels(folder: Path, seed: int | None = None):
    """(config, library, [trace per pixel, row-major]) of the small map simulated into ``folder`` (``seed``: the
    simulator's, None: the config's)."""
    import yaml

    from afmid.config import build_config, dump_config
    from afmid.maps.input_file import open_map, pixel_trace, read_pixels
    from afmid.maps.simulate import simulate_map, write_map_file
    from afmid.maps.task import map_config
    from afmid.physics.library import build_library
    from afmid.physics.tips import tip_geometry

    raw = yaml.safe_load(CONFIG.read_text())
    if seed is not None:
        raw["simulate"]["seed"] = seed
    config = build_config(raw, source=folder / "run.yaml")
    text = dump_config(config)
    path = folder / "map.h5"
    write_map_file(path, simulate_map(config), text)
    config = map_config(text, str(folder / "run.yaml"))
    source = open_map(path, config)
    library = build_library(config.model, config.source, tip_geometry(config.cantilever))
    n = source.rows * source.cols
    return config, library, [pixel_trace(source, row, config, i) for i, row in enumerate(read_pixels(source, 0, n))]
