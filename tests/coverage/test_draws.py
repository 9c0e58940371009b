"""What ``afmid coverage`` draws (afmid.coverage.draws, afmid.sections.coverage): the same (seed, index) gives the
same experiment whatever else is drawn, each mode puts the drawn number where its docstring says, whole-number
keys stay whole, the reproduce options read back as the drawn values, and a bad section is one line naming the
key."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from repo_paths import REPO_ROOT

from afmid.config import apply_overrides, build_config, dump_config, load_config, parse_override
from afmid.sections.coverage import Distribution
from afmid.coverage.draws import (apply_draw, default_distributions, distributions, draw, draw_number,
                                  draw_streams, get_value, set_options)
from afmid.errors import ConfigError

AIR = REPO_ROOT / "configs" / "coverage" / "air.yaml"


def _config(raw: dict, tmp_path):
    return build_config(raw, source=tmp_path / "c.yaml")


def _air_raw(**coverage) -> dict:
    raw = yaml.safe_load(AIR.read_text())
    raw["coverage"].update(coverage)
    return raw


def _draws(config, indices):
    raw = yaml.safe_load(dump_config(config))
    return [draw(config, raw, i) for i in indices]


def test_the_same_seed_gives_the_same_draws_and_a_draw_does_not_depend_on_the_others(tmp_path):
    config = _config(_air_raw(), tmp_path)
    first = _draws(config, range(6))
    again = _draws(config, range(6))
    assert first == again
    alone = _draws(config, [4])[0]
    assert alone == first[4]  # draw 4 alone is draw 4 of a run of six
    other = _draws(_config(_air_raw(seed=2802), tmp_path), range(6))
    assert all(a.values != b.values and a.seed != b.seed for a, b in zip(first, other))
    assert len({d.seed for d in first}) == 6  # six different simulation seeds


def test_streams_are_a_function_of_seed_and_index_only():
    values, seed = draw_streams(7, 3)
    values_again, seed_again = draw_streams(7, 3)
    assert seed == seed_again and 0 <= seed <= 2**32 - 1
    assert np.array_equal(values.random(5), values_again.random(5))
    assert draw_streams(7, 4)[1] != seed and draw_streams(8, 3)[1] != seed


def test_each_mode_puts_the_number_where_it_says(tmp_path):
    raw = _air_raw(defaults=False, vary={
        "simulate.parameters.E_star": {"log_uniform": [0.5, 2.0]},
        "sample.separation": {"uniform": [-1.0e-9, 1.0e-9], "mode": "shift"},
        "cantilever.quality_factor": {"log_uniform": [2.0, 600.0], "mode": "absolute"},
        "data.detector.bandwidth": {"log_uniform": [3.0, 30.0], "of": "cantilever.resonance_frequency"},
        "simulate.periods": {"uniform": [20, 80]},
        "simulate.mode": {"choice": ["steady", "transient"], "mode": "absolute"},
    })
    config = _config(raw, tmp_path)
    keys = list(distributions(config))
    assert keys[-1] == "data.detector.bandwidth"  # drawn after the key it refers to
    for one in _draws(config, range(20)):
        v = one.values
        # the same uniform numbers the draw used, one per key in order
        rng, _ = draw_streams(2801, one.index)
        u = {key: rng.random() for key in keys}
        assert v["simulate.parameters.E_star"] == pytest.approx(
            2.0e9 * math.exp(math.log(0.5) + u["simulate.parameters.E_star"] * math.log(4.0)), rel=1e-12)
        assert v["sample.separation"] == pytest.approx(7.5e-9 - 1e-9 + 2e-9 * u["sample.separation"], rel=1e-12)
        assert 2.0 <= v["cantilever.quality_factor"] <= 600.0
        assert 3.0 * 300e3 <= v["data.detector.bandwidth"] <= 30.0 * 300e3
        assert isinstance(v["simulate.periods"], int) and 1000 <= v["simulate.periods"] <= 4000  # x 20-80 of 50
        assert v["simulate.mode"] in ("steady", "transient")


def test_scale_of_a_drawn_key_uses_its_drawn_value(tmp_path):
    raw = _air_raw(defaults=False, vary={
        "cantilever.resonance_frequency": {"uniform": [0.5, 0.5]},
        "drive.frequency": {"uniform": [1.0, 1.0], "of": "cantilever.resonance_frequency"},
    })
    one = _draws(_config(raw, tmp_path), [0])[0]
    assert one.values["cantilever.resonance_frequency"] == 150e3
    assert one.values["drive.frequency"] == 150e3  # driven at the drawn resonance


def test_simulation_and_fit_configs_of_a_draw(tmp_path):
    config = _config(_air_raw(), tmp_path)
    raw = yaml.safe_load(dump_config(config))
    one = draw(config, raw, 2)
    simulated, fitted = apply_draw(raw, one, separation_given=False)
    assert "coverage" not in simulated and simulated["data"]["path"] is None
    assert simulated["simulate"]["seed"] == one.seed
    for key, value in one.values.items():
        assert get_value(simulated, key) == value
        assert key == "sample.separation" or get_value(fitted, key) == value  # the fit is not told d
    assert fitted["sample"]["separation"] is None and simulated["sample"]["separation"] == one.values[
        "sample.separation"]
    _, told = apply_draw(raw, one, separation_given=True)
    assert told["sample"]["separation"] == one.values["sample.separation"]
    # The --set options that reproduce the draw read back as the drawn values (a float like 1e-09 included).
    again = apply_overrides(yaml.safe_load(AIR.read_text()), [parse_override(o) for o in set_options(one, False)])
    for key, value in one.values.items():
        assert get_value(again, key) == value
    assert again["simulate"]["seed"] == one.seed
    assert parse_override(f"x={set_options(type(one)(0, 1, {'k.x': 1e-09}), False)[0].split('=', 1)[1]}")[1] == 1e-09


def test_defaults_follow_what_the_config_declares(tmp_path):
    raw = yaml.safe_load((REPO_ROOT / "configs" / "coverage" / "instrument.yaml").read_text())
    raw.pop("coverage")
    defaults = default_distributions(_config(raw, tmp_path))
    assert set(defaults) == {"simulate.parameters.E_star", "simulate.parameters.hamaker", "sample.separation",
                             "drive.free_amplitude", "simulate.noise.detector_rms", "cantilever.spring_constant",
                             "cantilever.quality_factor", "data.detector.bandwidth",
                             "cantilever.higher_modes.0.resonance_frequency"}
    raw["simulate"]["setpoint"] = 0.9
    defaults = default_distributions(_config(raw, tmp_path))
    assert "simulate.setpoint" in defaults and "sample.separation" not in defaults
    raw["coverage"] = {"vary": {"simulate.setpoint": None}}  # null drops a default
    assert "simulate.setpoint" not in distributions(_config(raw, tmp_path))


def test_draw_number_uses_one_uniform_per_key():
    for dist in (Distribution(uniform=(0, 1)), Distribution(log_uniform=(1, 2)), Distribution(choice=[1, 2, 3])):
        rng = np.random.Generator(np.random.PCG64(5))
        draw_number(dist, rng)
        reference = np.random.Generator(np.random.PCG64(5))
        reference.random()
        assert rng.random() == reference.random()


@pytest.mark.parametrize("vary, key, words", [
    ({"simulate.parameters.E_star": {"uniform": [1, 2], "log_uniform": [1, 2]}}, "coverage.vary", "exactly one"),
    ({"simulate.parameters.E_star": {"log_uniform": [0.0, 2.0]}}, "coverage.vary", "must be > 0"),
    ({"simulate.parameters.E_star": {"uniform": [2.0, 1.0]}}, "coverage.vary", "low <= high"),
    ({"simulate.parameters.E_star": {"uniform": [1, 2], "spread": 3}}, "spread", "spread"),
    ({"E_star": {"uniform": [1, 2]}}, "coverage", "dotted config key"),
    ({"simulate.mode": {"choice": ["steady"]}}, "coverage.vary", "mode: absolute"),
])
def test_a_bad_coverage_section_is_one_line_naming_the_key(tmp_path, vary, key, words):
    raw = _air_raw(vary=vary)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    text = info.value.format()
    assert "\n" not in text and str(path) in text and key in text and words in text, text


def test_a_scale_without_a_value_to_scale_names_the_key(tmp_path):
    raw = _air_raw(defaults=False, vary={"data.detector.bandwidth": {"log_uniform": [3.0, 30.0]}})
    with pytest.raises(ConfigError) as info:
        _draws(_config(raw, tmp_path), [0])
    assert info.value.key == "coverage.vary.data.detector.bandwidth" and "mode: absolute" in info.value.message


@pytest.mark.parametrize("name", sorted(p.name for p in (REPO_ROOT / "configs" / "coverage").glob("*.yaml")))
def test_shipped_distributions_validate_and_their_draws_build(name):
    from afmid.coverage.run import prepare_draws

    config = load_config(REPO_ROOT / "configs" / "coverage" / name)
    assert config.coverage is not None and config.fit.bootstrap > 0
    tasks = prepare_draws(config, [0, 1])  # the first draw's simulation and fit configs are validated
    assert [t["index"] for t in tasks] == [0, 1] and tasks[0]["seed"] != tasks[1]["seed"]
    assert tasks[0]["fit"]["sample"]["separation"] is None  # every shipped distribution estimates d


@pytest.mark.parametrize("key, ok", [("cantilever.quality_facter", False), ("simulate.noise.detector_rms", True),
                                     ("sample.separation.x", False), ("cantilever.higher_modes.0.quality_factor",
                                                                      False),
                                     ("simulate.parameters.debye_length", True), ("data.detector.bandwidth", True)])
def test_a_varied_key_must_be_a_key_of_the_config(tmp_path, key, ok):
    from afmid.coverage.draws import check_keys

    config = _config(_air_raw(vary={key: {"uniform": [1.0, 2.0], "mode": "absolute"}}), tmp_path)
    raw = yaml.safe_load(dump_config(config))
    if ok:
        check_keys(config, raw)
        return
    with pytest.raises(ConfigError) as info:
        check_keys(config, raw)
    assert info.value.key == f"coverage.vary.{key}" and "not a key of the run config" in info.value.message
