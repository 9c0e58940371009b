"""The run's own columns kept for all candidates (afmid.diagnosis.base_columns.BaseColumns).

The composed system (the run's [dmt] columns from the store, the added effect's evaluated) must give the residual
the full library's system gives, within base_columns.AGREEMENT (0.01 BIC units, n |delta rss| / rss):
the same columns in the same order except on the fine-grid cells where a [dmt] gate switches, which the full
library averages for every column and the composed system for the gated columns only (an O(h^2) difference on a
few cells per period: measured 0.0023 of 2443 with electrostatic added). A separation visited again, by the same
or another candidate, evaluates the run's columns once.
"""

from __future__ import annotations

import pytest

from afmid.config import read_yaml
from repo_paths import REPO_ROOT

pytestmark = [pytest.mark.numerics]


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """(config, prepared trace, first contact in m) of hidden_clean.yaml simulated for 20 periods."""
    from afmid.config import build_config
    from afmid.fit.pipeline import first_contact
    from afmid.fit.prepare import prepare
    from afmid.simulate.driver import simulate

    source = REPO_ROOT / "tests" / "configs" / "hidden_clean.yaml"
    raw = read_yaml(source)
    raw["simulate"]["periods"] = 20
    config = build_config(raw, source=source, base_dir=tmp_path_factory.mktemp("clean"))
    prepared = prepare(simulate(config), config.fit)
    return config, prepared, first_contact(prepared, config.sample.a0)


def _library(config, effects):
    from afmid.physics.library import build_library
    from afmid.physics.tips import tip_geometry

    model = config.model.model_copy(update={"effects": effects})
    return build_library(model, config.source, tip_geometry(config.cantilever))


@pytest.mark.parametrize("added", ["electrostatic", "exponential_damping", "hydration", "viscoelastic"])
def test_composed_residual_is_the_full_librarys(clean, added):
    from afmid.diagnosis.base_columns import AGREEMENT, BaseColumns
    from afmid.fit.pipeline import library_parameters
    from afmid.fit.system import build_system, residual_sum_squares

    config, prepared, touch = clean
    base = _library(config, ["dmt"])
    library = _library(config, ["dmt", added])
    shared = BaseColumns(prepared, base)
    params = library_parameters(prepared, config, library)
    for d in (touch - 0.3e-9, touch + 0.2e-9, touch - 0.3e-9):
        trial = dict(params, d=d)
        system = build_system(prepared, library, trial)
        full = residual_sum_squares(system)
        # within AGREEMENT BIC units: n |delta| / rss
        assert shared.residual(library, trial) == pytest.approx(full, abs=AGREEMENT * full / system.n_rows)
    # the first visit is checked against the full library; the third (the first separation again) is the first's
    # residual from the memo, nothing evaluated again
    assert shared.repeated == 1
    assert shared.evaluations == 3


def test_a_separation_is_evaluated_once_for_all_candidates(clean):
    from afmid.diagnosis.base_columns import BaseColumns
    from afmid.fit.pipeline import library_parameters

    config, prepared, touch = clean
    shared = BaseColumns(prepared, _library(config, ["dmt"]))
    grid = [touch + k * 0.25e-9 for k in range(-2, 3)]
    for added in ("electrostatic", "hydration"):
        library = _library(config, ["dmt", added])
        params = library_parameters(prepared, config, library)
        for d in grid:
            shared.residual(library, dict(params, d=d))
    # 10 evaluations, 5 separations: the run's columns made 5 times, reused 5 times
    assert (shared.evaluations, shared.reused) == (10, 5)


def test_a_shape_parameter_of_the_added_effect_does_not_evaluate_the_run_columns_again(clean):
    from afmid.diagnosis.base_columns import BaseColumns
    from afmid.fit.pipeline import library_parameters

    config, prepared, touch = clean
    shared = BaseColumns(prepared, _library(config, ["dmt"]))
    library = _library(config, ["dmt", "hydration"])
    params = dict(library_parameters(prepared, config, library), d=touch)
    name = "hydration_length"
    assert name in library.nonlinear and name not in _library(config, ["dmt"]).nonlinear
    for scale in (0.5, 1.0, 2.0):
        shared.residual(library, dict(params, **{name: params[name] * scale}))
    assert shared.reused == 2


def test_the_store_keeps_at_most_its_bytes(clean):
    from afmid.diagnosis.base_columns import BaseColumns
    from afmid.fit.pipeline import library_parameters

    config, prepared, touch = clean
    base = _library(config, ["dmt"])
    one = BaseColumns(prepared, base)
    params = dict(library_parameters(prepared, config, base), d=touch)
    theta, bias = one.columns(params)
    size = theta.nbytes + (0 if bias is None else bias.nbytes)
    shared = BaseColumns(prepared, base, kept_bytes=2 * size)
    for k in range(4):
        shared.columns(dict(params, d=touch + k * 1e-10))
    shared.columns(dict(params, d=touch))  # dropped (least recently used): evaluated again
    assert shared.reused == 0
    shared.columns(dict(params, d=touch + 3e-10))
    assert shared.reused == 1


def test_an_added_state_gate_is_evaluated_in_full(clean):
    """capillary's meniscus gate switches at its own rupture distance: those cells are averaged over every column
    in the full library, so the run's kept columns would differ there at every trial (not only the checked one)."""
    from afmid.diagnosis.base_columns import BaseColumns
    from afmid.fit.pipeline import library_parameters

    config, prepared, touch = clean
    shared = BaseColumns(prepared, _library(config, ["dmt"]))
    library = _library(config, ["dmt", "capillary"])
    params = library_parameters(prepared, config, library)
    for d in (touch, touch, touch + 1e-10):
        shared.residual(library, dict(params, d=d))
    assert (shared.evaluations, shared.reused) == (3, 0)


@pytest.mark.parametrize("added", ["viscoelastic", "contact_damping", "standard_linear_solid", "capillary"])
def test_an_effect_zero_until_contact_out_of_reach_is_not_evaluated_and_gives_the_full_librarys_residual(clean, added):
    """Above first contact (by more than REACH_MARGIN of the amplitude) a contact-only effect's columns (or a meniscus
    formed at contact) are zeros:
    not evaluated, and the residual is the full library's to the last bit's rounding (the same system but for the
    zero columns, which least squares leaves out exactly). Just below contact they are evaluated."""
    from afmid.diagnosis.base_columns import REACH_MARGIN, BaseColumns
    from afmid.fit.pipeline import library_parameters
    from afmid.fit.system import build_system, residual_sum_squares
    from afmid.fit.system import library_columns
    from afmid.physics.effects import EFFECTS

    config, prepared, touch = clean
    library = _library(config, ["dmt", added])
    shared = BaseColumns(prepared, _library(config, ["dmt"]))
    params = library_parameters(prepared, config, library)
    for parameter in EFFECTS.get(added).parameters:  # the relaxing solid's relaxation time: a mid-range value
        if parameter.nonlinear and parameter.name not in params:
            params[parameter.name] = parameter.default
    own = [i for i, term in enumerate(library.terms) if term.effect == added]
    beyond = touch + 2 * REACH_MARGIN * prepared.drive.amplitude + 0.1e-9
    for d in (beyond, beyond + 1e-9):
        trial = dict(params, d=d)
        # the premise: evaluated in full, the effect's columns are exactly zero there
        assert not library_columns(prepared, library, trial)[..., own].any()
        full = residual_sum_squares(build_system(prepared, library, trial))
        assert shared.residual(library, trial) == pytest.approx(full, rel=1e-12)
    assert shared.out_of_reach_trials == 2
    inside = dict(params, d=touch - 0.3e-9)
    shared.residual(library, inside)
    assert shared.out_of_reach_trials == 2  # evaluated in contact


@pytest.mark.parametrize("added", ["hydration", "capillary"])
def test_a_trial_asked_again_is_answered_from_the_memo_to_the_bit(clean, added):
    """The searches revisit trials (a candidate's two starts walk the same separation grid): the same library at the
    same parameters gets the first answer, bit for bit what evaluating again gives, with no columns evaluated; a
    changed shape parameter or another library is a new trial. capillary adds a gate (evaluated in full)."""
    from afmid.diagnosis.base_columns import BaseColumns
    from afmid.fit.pipeline import library_parameters

    config, prepared, touch = clean
    library = _library(config, ["dmt", added])
    params = dict(library_parameters(prepared, config, library), d=touch - 0.2e-9)
    name = next(p for p in library.nonlinear if p not in _library(config, ["dmt"]).nonlinear)
    params.setdefault(name, 1e-9)
    shared = BaseColumns(prepared, _library(config, ["dmt"]))
    first = shared.residual(library, params)
    again = shared.residual(library, dict(params))
    assert again == first and (shared.evaluations, shared.repeated) == (2, 1)
    fresh = BaseColumns(prepared, _library(config, ["dmt"]))
    fresh.residual(library, dict(params, d=touch))  # another trial first: the library's path is settled there
    assert fresh.residual(library, params) == first  # evaluated anew: the same bits
    assert fresh.repeated == 0
    other = shared.residual(library, dict(params, **{name: 2 * params[name]}))
    assert other != first and shared.repeated == 1
