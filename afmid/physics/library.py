"""The library of candidate force terms.

A :class:`Library` is an ordered list of :class:`LibraryTerm` (expressions in the
term language of :mod:`afmid.terms.expr`), built from the effect catalog
(``model.effects``), from a preset (the seed's tables I-IV in :mod:`afmid.physics.presets`, ``model.library``),
and from custom terms in the config (``model.terms``). Each term knows its SI
units and, where it comes from an effect, which effect coefficient it is, so
fitted coefficients can be read out as physical quantities.

Columns are evaluated by the numba VM over the measured trajectory; history
gates (meniscus, JKR neck) are scanned along the trajectory first.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

import afmid.terms.expr as expr
from afmid.errors import ConfigError
from afmid.terms.kinematics import contact_kinematics, next_gate_state, next_relaxation_state
from afmid.physics.effect_tags import SELECTION_RULES, Role
from afmid.physics.effect_types import RelaxingState, State, state_expressions
from afmid.physics.effects import CONTEXT_UNITS, EFFECTS, coefficient_unit, effect_parameter_names, term_unit
from afmid.physics.presets import PRESETS
from afmid.physics.tips import SPHERE, SPHERE_POWER, TipGeometry, shaped_effect
from afmid.registry import unknown_name_message
from afmid.terms.units import parse_unit

NEWTON = parse_unit("N")


@dataclass(frozen=True)
class LibraryTerm:
    name: str  # display name
    expression: str
    unit: str  # SI units of the term
    coefficient_unit: str  # SI units of its coefficient (N / unit)
    effect: str | None = None  # effect whose coefficient this is (for the read-out)
    label: str | None = None  # term label within that effect
    doc: str = ""
    roles: tuple[Role, ...] = ()  # what the term is to the selection rules (afmid.physics.effect_tags)


@dataclass
class Library:
    """Candidate terms plus what evaluating them needs (states, nonlinear parameters)."""

    terms: list[LibraryTerm]
    states: tuple[State, ...] = ()  # gates and relaxing states, scanned along the trajectory
    effects: tuple[str, ...] = ()  # effects whose read-out applies
    nonlinear: dict[str, float] = field(default_factory=dict)  # default values, SI
    source: str = ""
    tip: TipGeometry = SPHERE  # the elastic terms follow its contact law; so does the read-out of E*

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.terms]

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.states)

    def __len__(self) -> int:
        return len(self.terms)

    def __getstate__(self) -> dict:
        # Generated kernels (modules) do not pickle; a process that receives the library generates its own.
        state = dict(self.__dict__)
        state.pop("_term_kernels", None)
        return state

    def selection_rules(self, n_extra: int = 0) -> list[tuple[list[np.ndarray], np.ndarray]]:
        """afmid.physics.effect_tags.SELECTION_RULES as column masks, padded with ``n_extra`` unconstrained columns:
        (one mask per role of ``if_all``, the mask of ``then_any``). A rule is left out when the library
        has no term of some ``if_all`` role (it cannot apply) or none of ``then_any`` (it could not be met)."""
        def having(roles) -> np.ndarray:
            return np.array([bool(set(t.roles) & set(roles)) for t in self.terms] + [False] * n_extra)

        rules = []
        for rule in SELECTION_RULES:
            conditions = [having((role,)) for role in rule.if_all]
            then = having(rule.then_any)
            if all(c.any() for c in conditions) and then.any():
                rules.append((conditions, then))
        return rules

    def compile(self, params: Mapping[str, float]):
        """A :class:`afmid.terms.expr.ProgramSet` of the terms and the state-gate conditions (cached per parameter set:
        the fit evaluates the same library at the same parameters many times)."""
        # Keyed by the parameters the programs use (not the separation d, say, a variable's offset passed to the
        # kernels at run time): a search over d compiles once, not at every trial value.
        expressions = tuple(t.expression for t in self.terms)
        used = self.__dict__.get("_used_names")
        if used is None or used[0] != (expressions, tuple(self.states)):
            names = set().union(*(expr.free_names(e) for e in expressions),
                                *(expr.free_names(state_expressions(g)) for g in self.states))
            used = self.__dict__["_used_names"] = ((expressions, tuple(self.states)), names)
        key = (expressions, tuple(sorted((k, v) for k, v in params.items() if k in used[1])))
        cache = self.__dict__.setdefault("_compiled", {})
        if key not in cache:
            if len(cache) > 64:
                cache.clear()
            cache[key] = self._compile(params)
        return cache[key]

    def _compile(self, params: Mapping[str, float]):
        states = self.state_names
        programs = [expr.compile_expression(t.expression, dict(params), states) for t in self.terms]
        gates = []
        for gate in self.states:
            if isinstance(gate, RelaxingState):  # (its source, its time constant in s)
                gates.append((expr.compile_expression(gate.source, dict(params), states), float(params[gate.time])))
                continue
            gates.append((
                expr.compile_expression(f"[{gate.on}]", dict(params), states),
                expr.compile_expression(f"[{gate.off}]", dict(params), states),
            ))
        return expr.ProgramSet(programs), gates

    def evaluate(self, x: np.ndarray, xdot: np.ndarray, t: np.ndarray, params: Mapping[str, float],
                 state_values: np.ndarray | None = None) -> np.ndarray:
        """Library columns (N, p) along a trajectory (x m, xdot m/s, t s; columns in the terms' units, coefficient
        x column = N). ``params`` holds d (separation), a0, R and nonlinear ones.

        The state gates (hysteresis) are scanned along the trajectory, unless
        ``state_values`` (n_states, N) gives them (for points that are not one
        time series, e.g. sub-samples of many short intervals). The columns come from the VM kernel
        (afmid.kernels.vm); the tests compare it with a plain-NumPy twin (tests/support/library_twin.py).
        """
        from afmid.kernels.vm import eval_set

        variables = trajectory_variables(x, xdot, t, params["d"], params["a0"], len(self.states))
        program_set, gates = self.compile(params)
        if self.states:
            if state_values is not None:
                variables[len(expr.VARIABLES):] = state_values
            else:
                _fill_states(variables, gates)
        out = np.empty((x.size, len(self.terms)))
        eval_set(program_set.code, program_set.code_offsets, program_set.consts, program_set.const_offsets,
                 variables, out)
        return out


    def evaluate_into(self, x: np.ndarray, xdot: np.ndarray, t: np.ndarray, params: Mapping[str, float],
                      out: np.ndarray) -> tuple[bool, bool]:
        """Library columns along trajectory rows (x, xdot, t: (rows, n), m, m/s, s) into ``out`` (rows, n, p), of
        any strides (the weak form's layout, say), for a library without state gates; the same values as
        :meth:`evaluate`, bit for bit, without its (7, N) array of variables. Returns (all finite, any value
        exactly zero)."""
        if self.states:
            raise ValueError("evaluate_into: a library with state gates is evaluated by evaluate()")
        program_set, _ = self.compile(params)
        kernel = self.term_kernel(params)
        if kernel is not None:
            return kernel.eval_rows(x, xdot, t, float(params["d"]), float(params["a0"]), out)
        from afmid.kernels.trajectory_eval import eval_rows

        finite, any_zero = eval_rows(program_set.code, program_set.code_offsets, program_set.consts,
                                     program_set.const_offsets, x, xdot, t, float(params["d"]),
                                     float(params["a0"]), out)
        return bool(finite), bool(any_zero)

    def term_kernel(self, params: Mapping[str, float]):
        """The kernel generated for this library's terms (:func:`afmid.kernels.termgen.term_kernel`: straight-line
        code, ~4x faster than the VM, the same bits) with the constants of ``params``; None for a library with
        state gates or where it cannot be generated (the VM evaluates it then). Kept per compiled parameter set:
        call it (or :meth:`compile`) once before threads share the library."""
        if self.states:
            return None
        program_set, _ = self.compile(params)
        kernels = self.__dict__.setdefault("_term_kernels", {})
        entry = kernels.get(id(program_set))
        if entry is None or entry[0] is not program_set:  # the program set is kept with it: ids are reused
            from afmid.kernels.lawgen import GenerationError
            from afmid.kernels.termgen import term_kernel

            try:
                kernel = term_kernel(program_set.programs)
            except GenerationError:
                kernel = None
            if len(kernels) > 64:
                kernels.clear()
            entry = kernels[id(program_set)] = (program_set, kernel)
        return entry[1]

    def reads_velocity(self) -> bool:
        """Whether a term or state reads a velocity (zdot, deltadot, xdot): if not, the columns do not depend on
        the velocity passed with the trajectory (only on x and t)."""
        from afmid.terms.term_parser import walk

        velocities = {"zdot", "deltadot", "xdot"}
        texts = [t.expression for t in self.terms] + [state_expressions(gate) for gate in self.states]
        return any(isinstance(node, expr.Name) and node.name in velocities
                   for text in texts for node in walk(expr.parse(text)))

    def evaluate_rows(self, x: np.ndarray, xdot: np.ndarray, t: np.ndarray, params: Mapping[str, float]
                      ) -> np.ndarray:
        """Library columns (x.size, p) along a trajectory given as rows (x, xdot, t of one shape, m, m/s, s; 1-D is
        one row): :meth:`evaluate` of the raveled arrays, bit for bit (state gates scanned along them as one series).
        Without state gates through :meth:`evaluate_into`: no (7, N) array of variables and no temporaries, which
        is what lets threads evaluate pieces of one trace at once (page faults of fresh temporaries serialise
        them: two threads evaluating the variables array took longer than one)."""
        if self.states:
            return self.evaluate(x.ravel(), xdot.ravel(), t.ravel(), params)
        def as_rows(a: np.ndarray) -> np.ndarray:
            return a[None] if a.ndim == 1 else a.reshape(-1, a.shape[-1])

        rows = as_rows(x)
        out = np.empty(rows.shape + (len(self.terms),))
        self.evaluate_into(rows, as_rows(xdot), as_rows(t), params, out)
        return out.reshape(x.size, -1)

    def states_along(self, x: np.ndarray, xdot: np.ndarray, t: np.ndarray, params: Mapping[str, float],
                     initial: np.ndarray | None = None) -> np.ndarray:
        """The states (n_states, N) scanned along a trajectory: gates 0 or 1, relaxing states their values.
        ``initial`` (n_states,): the relaxing states' values at the first sample where known (NaN or None:
        relaxed there, state = source); gates always start from their conditions at the first sample."""
        variables = trajectory_variables(x, xdot, t, params["d"], params["a0"], len(self.states))
        if self.states:
            _fill_states(variables, self.compile(params)[1], initial)
        return variables[len(expr.VARIABLES):]

    def states_from(self, initial: np.ndarray, x: np.ndarray, xdot: np.ndarray, t: np.ndarray,
                    params: Mapping[str, float]) -> np.ndarray:
        """State gates (n_states, m * S) along m short trajectories (m, S) in time order, each from its ``initial`` state
        (n_states, m). Vectorised over the trajectories: for sub-samples of many short intervals."""
        m, S = x.shape
        variables = trajectory_variables(x.ravel(), xdot.ravel(), t.ravel(), params["d"], params["a0"], len(self.states))
        out = np.empty((len(self.states), m, S))
        for k, (first, second) in enumerate(self.compile(params)[1]):
            if isinstance(self.states[k], RelaxingState):
                # ``initial`` (the value at the sample before each short trajectory) is taken as the value at its
                # first sub-sample, then stepped exactly: an O(h) error in the two cells a contact switches in.
                source = expr.evaluate_numpy(first, variables).reshape(m, S)
                tt = t.reshape(m, S)
                state = initial[k].astype(float)
                out[k, :, 0] = state
                for j in range(1, S):
                    state = next_relaxation_state(state, source[:, j - 1], source[:, j], tt[:, j] - tt[:, j - 1],
                                                  second)
                    out[k, :, j] = state
                continue
            on = expr.evaluate_numpy(first, variables).reshape(m, S) != 0
            off = expr.evaluate_numpy(second, variables).reshape(m, S) != 0
            state = initial[k].astype(float)
            for j in range(S):
                state = next_gate_state(state, on[:, j], off[:, j])
                out[k, :, j] = state
        return out.reshape(len(self.states), -1)


def trajectory_variables(x, xdot, t, d: float, a0: float, n_states: int = 0) -> np.ndarray:
    """The term-language variables (z, zdot, delta, deltadot, x, xdot, t, states...) along a trajectory."""
    n = x.size
    v = np.zeros((len(expr.VARIABLES) + n_states, n))
    v[0], v[1], v[2], v[3] = contact_kinematics(x, xdot, d, a0)
    v[4] = x
    v[5] = xdot
    v[6] = t
    return v


def _fill_states(variables: np.ndarray, gates, initial: np.ndarray | None = None) -> None:
    """The state rows of ``variables`` scanned along the trajectory by the kernels (afmid.kernels.hysteresis)."""
    from afmid.kernels.hysteresis import scan_hysteresis, scan_relaxation

    base = len(expr.VARIABLES)
    for k, (on_prog, off_prog) in enumerate(gates):
        if not isinstance(off_prog, expr.Program):  # a relaxing state: (source, time constant in s)
            source = expr.evaluate_numpy(on_prog, variables)
            start = source[0] if initial is None or not np.isfinite(initial[k]) else float(initial[k])
            out = np.empty_like(source)
            scan_relaxation(source, variables[6], off_prog, start, out)
            variables[base + k] = out
            continue
        on = expr.evaluate_numpy(on_prog, variables)
        off = expr.evaluate_numpy(off_prog, variables)
        out = np.empty_like(on)
        scan_hysteresis(on, off, float(on[0] != 0), out)
        variables[base + k] = out


def _units_context(extra_units: Mapping[str, str]) -> dict:
    units = {k: parse_unit(v) for k, v in CONTEXT_UNITS.items()}
    units["w"] = parse_unit("1/s")
    units.update({k: parse_unit(v) for k, v in extra_units.items()})
    return units


def _check_custom_term_names(texts, param_units: Mapping[str, str], nonlinear: Mapping[str, float], states,
                             source) -> None:
    """A custom term may name only values known when it is evaluated: the context (R, a0, w), the nonlinear
    parameters and the state gates. An effect's linear parameter (E_star, hamaker, ...) is what the fit
    determines from the coefficients; inside a term it has no value (and would make the term's scale unknown)."""
    known = set(CONTEXT_UNITS) | {"w"} | set(nonlinear) | {s.name for s in states}
    for i, text in enumerate(texts):
        unknown = sorted(expr.free_names(text) - known)
        if not unknown:
            continue
        name = unknown[0]
        what = ("a parameter the fit determines from the coefficients, with no value inside a term"
                if name in param_units else "not a value a term can use")
        allowed = ", ".join(sorted(known)) or "none"
        raise ConfigError(f"{name!r} is {what}; a custom term may use the variables and {allowed} "
                          f"(in term {text!r})", file=source, key=f"model.terms[{i}]")


def build_library(model_config, source=None, tip: TipGeometry = SPHERE) -> Library:
    """The library a run config asks for (``model.library`` preset or ``model.effects``, plus ``model.terms``),
    its elastic contact terms following the ``tip``'s contact law (``cantilever.tip_shape``)."""

    terms: list[LibraryTerm] = []
    states: list[State] = []
    nonlinear: dict[str, float] = {}
    param_units: dict[str, str] = {}
    if model_config.library is not None:
        if model_config.library not in PRESETS:
            raise ConfigError(unknown_name_message("library preset", model_config.library, PRESETS.names()),
                              file=source, key="model.library")
        preset = PRESETS.get(model_config.library)
        effects = preset.effects
    else:
        preset = None
        effects = tuple(model_config.effects)
    for name in effects:
        eff = EFFECTS.get(name)
        states.extend(s for s in eff.states if s not in states)
        for p in eff.parameters:
            param_units[p.name] = p.unit
            if p.nonlinear:
                nonlinear[p.name] = p.default
    if preset is not None:
        units = _units_context(param_units)
        power = tip.declaration.power_text
        for term in preset.terms:
            name, expression = term.name, term.expression
            if Role.ELASTIC_CONTACT in term.roles and power != SPHERE_POWER:  # the seed tables' Hertz column
                name, expression = name.replace(SPHERE_POWER, power), expression.replace(SPHERE_POWER, power)
            unit = expr.expression_units(expression, units, tuple(s.name for s in states))
            terms.append(LibraryTerm(name, expression, str(unit), str(NEWTON / unit), term.effect,
                                     term.label, roles=term.roles))
    else:
        for name in effects:
            eff = shaped_effect(EFFECTS.get(name), tip)
            for term in eff.terms:
                terms.append(LibraryTerm(
                    f"{name}.{term.label}", term.expression, str(term_unit(eff, term)),
                    str(coefficient_unit(eff, term)), name, term.label, term.doc, term.roles,
                ))
    units = _units_context(param_units)
    for i, text in enumerate(model_config.terms):
        key = f"model.terms[{i}]"
        try:
            unit = expr.expression_units(text, units, tuple(s.name for s in states))
        except expr.ExpressionError as exc:
            where = f" at column {exc.pos + 1}" if exc.pos is not None else ""
            raise ConfigError(f"{exc.reason}{where} in term {text!r}", file=source, key=key) from None
        except ValueError as exc:
            raise ConfigError(f"{exc}", file=source, key=key) from None
        terms.append(LibraryTerm(text, text, str(unit), str(NEWTON / unit)))
    # One column per distinct expression: effects may share a term.
    seen: dict[str, LibraryTerm] = {}
    for term in terms:
        seen.setdefault(" ".join(term.expression.split()), term)
    # Only nonlinear parameters that some term or state gate actually uses are searched.
    used = set()
    for term in terms:
        used |= expr.free_names(term.expression)
    for gate in states:
        used |= expr.free_names(state_expressions(gate))
    states = [g for g in states if any(g.name in expr.free_names(t.expression) for t in terms)]
    used = set()
    for term in terms:
        used |= expr.free_names(term.expression)
    for gate in states:
        used |= expr.free_names(state_expressions(gate))
    nonlinear = {k: v for k, v in nonlinear.items() if k in used}
    for name, value in model_config.parameters.items():
        if name not in nonlinear:
            allowed = ", ".join(sorted(nonlinear)) or "none for these effects"
            raise ConfigError(f"{name!r} is not a nonlinear parameter of the library; allowed: {allowed}",
                              file=source, key=f"model.parameters.{name}")
        declared = effect_parameter_names(effects)[name]  # a fixed value must be one the physics allows
        if not declared.low <= value <= declared.high:
            raise ConfigError(f"must be in [{declared.low:g}, {declared.high:g}] {declared.unit} ({declared.doc}), "
                              f"got {value:g}", file=source, key=f"model.parameters.{name}")
        nonlinear[name] = value
    _check_custom_term_names(model_config.terms, param_units, nonlinear, states, source)
    return Library(list(seen.values()), tuple(states), tuple(effects), nonlinear,
                   model_config.library or "effects", tip)
