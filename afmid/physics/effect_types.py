"""The physics registry's vocabulary: what an effect, a term, a parameter and a model are, and the checks a
declaration passes when it is registered (:data:`EFFECTS`, :data:`MODELS`).

The declarations themselves are in :mod:`afmid.physics.effects` (and the modules it imports, e.g.
:mod:`afmid.physics.contact_effects`); read that module's docstring for the conventions.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import afmid.terms.expr as expr
from afmid.physics.effect_tags import Character, Region, Role, check_member, check_roles
from afmid.errors import DefinitionError
from afmid.registry import Registry
from afmid.terms.units import Unit, parse_unit

EPSILON_0 = 8.8541878128e-12  # F/m, vacuum permittivity
BOLTZMANN = 1.380649e-23  # J/K

#: Context quantities every effect may use (set from the cantilever/sample config): the tip radius, the
#: intermolecular distance and the relative permittivity of the medium (``afmid.physics.medium``).
CONTEXT_UNITS: dict[str, str] = {"R": "m", "a0": "m", "eps_r": "1"}
#: The media a sample can be imaged in (``sample.medium``); an effect declares where it is offered.
MEDIA: tuple[str, ...] = ("air", "liquid")
NEWTON = parse_unit("N")


@dataclass(frozen=True)
class Parameter:
    """A physical parameter of an effect, in SI units."""

    name: str
    unit: str
    default: float
    low: float  # valid range, inclusive
    high: float
    doc: str
    nonlinear: bool = False  # appears inside a term (searched by the fit, not linear in F)
    # Where the fit and the diagnosis search a nonlinear parameter that is not fixed, per medium: (medium, low,
    # high) entries; a medium without one searches the valid range. Narrower than the valid range where a wider
    # search would take the effect for another one of the same shape (in liquid: the double layer's Debye length
    # against the hydration length).
    search: tuple[tuple[str, float, float], ...] = ()

    def search_span(self, medium: str = "air") -> tuple[float, float]:
        """(low, high) searched in ``medium`` (SI)."""
        return next(((low, high) for m, low, high in self.search if m == medium), (self.low, self.high))


@dataclass(frozen=True)
class Term:
    """One force term: ``coefficient(params) * expression``.

    ``label`` names the term within its effect (keys of the readout's input).
    ``coefficient`` maps the effect's parameters (plus context R, a0) to the SI
    coefficient, so that ``coefficient * expression`` is a force in newtons;
    ``coefficient_unit`` states its SI units, and registration checks that they
    times the expression's units are newtons.
    """

    label: str
    expression: str
    coefficient: Callable[[Mapping[str, float]], float]
    doc: str = ""
    roles: tuple[Role, ...] = ()  # what the term is to the selection rules (afmid.physics.effect_tags.SELECTION_RULES)
    coefficient_unit: str = ""  # SI units of the coefficient, e.g. "J*m" for H R / 6 (required: checked at registration)


@dataclass(frozen=True)
class Quantity:
    """A physical quantity the fit reports for an effect.

    ``low``/``high`` (inclusive, SI, in ``unit``) are the values a physical sample
    can have; they also fix the sign (``low >= 0``: a positive number). A quantity
    that is one of its effect's parameters takes the parameter's range and leaves
    them None. Read-outs outside the range are flagged (:mod:`afmid.fit.plausibility`).
    """

    name: str
    unit: str
    doc: str
    low: float | None = None
    high: float | None = None
    #: For a force that grows with the tip (adhesion 4 pi R gamma, a meniscus 4 pi R gamma_w cos theta): its
    #: largest physical value per metre of tip radius, in ``unit`` / m. A read-out above it for the declared
    #: ``cantilever.tip_radius`` is implausible even inside [low, high] (:mod:`afmid.fit.plausibility`).
    high_per_radius: float | None = None


@dataclass(frozen=True)
class StateGate:
    """A history-dependent boolean state used in terms as ``[name]``.

    It switches on when ``on`` becomes true and stays on until ``off`` becomes
    true (conditions in the term language), e.g. a water meniscus that forms at
    contact and ruptures only at a set separation on retraction.

    ``forms_at_contact`` declares that the gate switches on where the tip reaches the sample (``on`` is
    :data:`CONTACT_CONDITION`): its force then steps on at each tap whose lowest separation reaches a0, so a
    residual of the rest separation d jumps wherever d crosses a tap's contact threshold (a0 + that tap's
    largest deflection) and can have valleys narrower than a coarse grid's step. Searches of d try those
    thresholds (:func:`afmid.fit.contact_thresholds.contact_trial_separations`).
    """

    name: str
    on: str
    off: str
    forms_at_contact: bool = False


@dataclass(frozen=True)
class RelaxingState:
    """A continuous history state used in terms by its ``name``: the dimensionless ``source`` (an expression of
    the trajectory) seen through a first-order lag of time constant ``time`` (the name of a parameter, s)::

        d(state)/dt = (source - state) / time

    e.g. the relaxing part of a standard linear solid's contact force. Scanned along a trajectory with the source
    taken linear in time between samples (exact for that; :func:`afmid.terms.kinematics.next_relaxation_state`);
    it starts relaxed (state = source) where no earlier value is known.
    """

    name: str
    source: str
    time: str


#: The ``on`` condition of a gate that forms where the tip reaches contact (:attr:`StateGate.forms_at_contact`).
CONTACT_CONDITION = "z <= a0"


def forms_at_contact(states) -> bool:
    """Whether any of ``states`` (an effect's or a library's) is a gate declared to form at contact."""
    return any(isinstance(s, StateGate) and s.forms_at_contact for s in states)


#: A state an effect carries through the period: a boolean gate or a relaxing (lagging) value.
State = StateGate | RelaxingState


def state_expressions(state: State) -> str:
    """One expression naming everything a state uses (for the names a library must know)."""
    if isinstance(state, RelaxingState):
        return f"({state.source}) * {state.time}"
    return f"[{state.on}] * [{state.off}]"


@dataclass(frozen=True)
class Effect:
    name: str
    title: str
    formula: str  # human-readable force law, repulsive positive
    parameters: tuple[Parameter, ...]
    terms: tuple[Term, ...]
    quantities: tuple[Quantity, ...]
    readout: Callable[[Mapping[str, float], Mapping[str, float]], dict[str, float]]
    references: tuple[str, ...]
    states: tuple[State, ...] = ()
    character: Character = Character.CONSERVATIVE  # guides the diagnosis
    region: Region = Region.CONTACT  # where it acts
    notes: str = ""
    # Terms a library may fit under this effect's name, for its read-out, that the effect itself does not add
    # (neither to the simulated force nor to an effects library): e.g. DMT ties its adhesion to the tail, but
    # the seed tables fit the adhesion as a term of its own. Checked like ``terms``; presets may name them.
    readout_only_terms: tuple[Term, ...] = ()
    # The media (``sample.medium``) the effect exists in: a capillary meniscus only in air, a double layer only
    # in an electrolyte. Elsewhere the diagnosis does not try it and a config that lists it is refused.
    media: tuple[str, ...] = MEDIA

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    def defaults(self) -> dict[str, float]:
        return {p.name: p.default for p in self.parameters}

    @property
    def nonlinear_parameters(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters if p.nonlinear)


@dataclass(frozen=True)
class Model:
    """A named combination of effects used by the simulator (the seed's models)."""

    name: str
    title: str
    effects: tuple[str, ...]
    references: tuple[str, ...]
    equation: str = ""
    defaults: Mapping[str, float] = field(default_factory=dict)
    derived_defaults: Callable[[Mapping[str, float]], dict[str, float]] | None = None


# A realistic default context for checks: a 10 nm tip, a0 = 0.165 nm, water.
CHECK_CONTEXT = {"R": 10e-9, "a0": 0.165e-9, "eps_r": 78.4}


def _param_units(effect: Effect) -> dict[str, Unit]:
    units = {name: parse_unit(u) for name, u in CONTEXT_UNITS.items()}
    units.update({p.name: parse_unit(p.unit) for p in effect.parameters})
    return units


def _validate_term(effect: Effect, term: Term, units: Mapping[str, Unit], values: Mapping[str, float]) -> None:
    """A term's roles are known, its expression names only declared values, its coefficient is finite at the
    defaults and in its declared units, and coefficient x term is a force (N)."""
    state_names = tuple(s.name for s in effect.states)
    check_roles(term.roles, f"term {term.label}")
    undeclared = expr.free_names(term.expression) - set(state_names) - set(units)
    if undeclared:
        raise DefinitionError(f"term {term.label}: undeclared names {sorted(undeclared)}")
    if not math.isfinite(term.coefficient(values)):
        raise DefinitionError(f"term {term.label}: coefficient not finite at defaults")
    if not term.coefficient_unit:
        raise DefinitionError(f"term {term.label}: declare coefficient_unit (SI units of the coefficient)")
    expression_unit = expr.expression_units(term.expression, units, states=state_names)
    force = parse_unit(term.coefficient_unit) * expression_unit
    if force != NEWTON:
        raise DefinitionError(f"term {term.label}: coefficient ({term.coefficient_unit}) x term ({expression_unit}) "
                              f"is {force}, not N; the coefficient should be in {NEWTON / expression_unit}")


def validate_effect(effect: Effect) -> None:
    """Raise DefinitionError (or ValueError) unless a declaration is consistent: the checks run by
    ``EFFECTS.register``, also for an effect derived from a registered one (a tip shape's contact law)."""
    if not effect.terms:
        raise DefinitionError("an effect needs at least one term")
    check_member(Character, effect.character, "character")
    check_member(Region, effect.region, "region")
    labels = [t.label for t in effect.terms + effect.readout_only_terms]
    if len(set(labels)) != len(labels):
        raise DefinitionError(f"term labels repeat: {labels}")
    if not effect.media or set(effect.media) - set(MEDIA):
        raise DefinitionError(f"media {effect.media} must be some of {MEDIA}")
    for p in effect.parameters:
        if not (p.low <= p.default <= p.high):
            raise DefinitionError(f"default of {p.name} ({p.default}) outside [{p.low}, {p.high}]")
        for medium, low, high in p.search:
            if medium not in MEDIA or not (p.nonlinear and p.low <= low < high <= p.high):
                raise DefinitionError(f"search range of {p.name} in {medium} [{low}, {high}] must lie in "
                                      f"[{p.low}, {p.high}], a medium of {MEDIA}, nonlinear parameters only")
        parse_unit(p.unit)
    state_names = tuple(s.name for s in effect.states)
    units = _param_units(effect)
    values = {**CHECK_CONTEXT, **effect.defaults()}
    for term in effect.terms + effect.readout_only_terms:
        _validate_term(effect, term, units, values)
    for gate in effect.states:
        if isinstance(gate, RelaxingState):
            _validate_relaxing_state(effect, gate, units, state_names)
            continue
        for cond in (gate.on, gate.off):
            expr.expression_units(f"[{cond}]", units, states=state_names)
        if gate.forms_at_contact and gate.on.split() != CONTACT_CONDITION.split():
            raise DefinitionError(f"state {gate.name}: declared to form at contact, but it switches on at "
                                  f"{gate.on!r}, not {CONTACT_CONDITION!r}")
    # The readout must invert the coefficients at the defaults.
    coefficients = {t.label: t.coefficient(values) for t in effect.terms}
    recovered = effect.readout(coefficients, values)
    for q in effect.quantities:
        _validate_quantity_range(effect, q)
        if q.name not in recovered:
            raise DefinitionError(f"readout does not give quantity {q.name}")
        if q.name in values and values[q.name] != 0:
            rel = abs(recovered[q.name] - values[q.name]) / abs(values[q.name])
            if rel > 1e-9:
                raise DefinitionError(f"readout of {q.name} does not invert its coefficient ({rel:.1e})")
    # A read-out-only term stands for part of the effect's force: fitted at the value the effect implies,
    # it must not change what the readout reports.
    if effect.readout_only_terms:
        with_extra = effect.readout({**coefficients, **{t.label: t.coefficient(values)
                                                         for t in effect.readout_only_terms}}, values)
        for name, value in recovered.items():
            if not math.isclose(with_extra.get(name, math.nan), value, rel_tol=1e-9):
                raise DefinitionError(f"readout of {name} changes with the read-out-only terms at the defaults "
                                      f"({value!r} -> {with_extra.get(name)!r})")


def _validate_relaxing_state(effect: Effect, state: RelaxingState, units: Mapping[str, Unit],
                             state_names: tuple[str, ...]) -> None:
    """A relaxing state's source is dimensionless, free of states, and its time a nonlinear parameter in s."""
    source_unit = expr.expression_units(state.source, units, states=())
    if source_unit != parse_unit("1"):
        raise DefinitionError(f"state {state.name}: source {state.source!r} is in {source_unit}, not dimensionless")
    try:
        time = effect.parameter(state.time)
    except KeyError:
        raise DefinitionError(f"state {state.name}: time {state.time!r} is not a parameter of {effect.name}") from None
    if parse_unit(time.unit) != parse_unit("s") or not time.nonlinear or time.low <= 0:
        raise DefinitionError(f"state {state.name}: time {state.time!r} must be a nonlinear parameter in s, > 0")


def quantity_range(effect: Effect, quantity: Quantity) -> tuple[float, float]:
    """The plausible range [low, high] (SI, inclusive) of a quantity: its own, or its parameter's."""
    if quantity.low is not None and quantity.high is not None:
        return quantity.low, quantity.high
    parameter = effect.parameter(quantity.name)
    return parameter.low, parameter.high


def _validate_quantity_range(effect: Effect, q: Quantity) -> None:
    """Every reported quantity has a plausible range, in known units, one per name across the catalog."""
    unit = parse_unit(q.unit)
    is_parameter = q.name in {p.name for p in effect.parameters}
    if is_parameter:
        if q.low is not None or q.high is not None:
            raise DefinitionError(f"quantity {q.name} is a parameter: it takes the parameter's range, declare none")
        if parse_unit(effect.parameter(q.name).unit) != unit:
            raise DefinitionError(f"quantity {q.name} is in {q.unit}, its parameter in {effect.parameter(q.name).unit}")
    elif q.low is None or q.high is None:
        raise DefinitionError(f"quantity {q.name} needs a plausible range (low, high)")
    low, high = quantity_range(effect, q)
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise DefinitionError(f"quantity {q.name}: plausible range [{low}, {high}] needs finite low < high")
    if q.high_per_radius is not None and not (math.isfinite(q.high_per_radius) and q.high_per_radius > 0):
        raise DefinitionError(f"quantity {q.name}: high_per_radius {q.high_per_radius} must be finite and > 0")
    for other in EFFECTS:  # one name, one meaning: the same unit and range wherever it is reported
        for o in other.quantities:
            if o.name == q.name and (parse_unit(o.unit) != unit or quantity_range(other, o) != (low, high)
                                     or o.high_per_radius != q.high_per_radius):
                raise DefinitionError(f"quantity {q.name}: unit or range differs from effect {other.name}'s "
                                      f"({o.unit} [{quantity_range(other, o)}])")


def _validate_model(model: Model) -> None:
    for name in model.effects:
        if name not in EFFECTS:
            raise DefinitionError(f"unknown effect {name!r}")


EFFECTS: Registry[Effect] = Registry("effect", validate_effect)
MODELS: Registry[Model] = Registry("model", _validate_model)


def term_unit(effect: Effect, term: Term) -> Unit:
    """SI units of a term's expression."""
    return expr.expression_units(term.expression, _param_units(effect), states=tuple(s.name for s in effect.states))


def coefficient_unit(effect: Effect, term: Term) -> Unit:
    """SI units of a term's coefficient (newtons divided by the term's units)."""
    return NEWTON / term_unit(effect, term)
