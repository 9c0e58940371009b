"""The run's own library's columns, evaluated once per parameter set for all the diagnosis's candidates.

Every candidate refit of a diagnosis searches the rest separation and its shape parameters on the full library
(the run's effects plus the candidate's), and at every trial value the run's own terms were evaluated again:
on a 5e5-sample record those columns were most of each of the ~270 library evaluations of a candidate, and the
same separations (the coarse grid of the search span, then its zooms wherever two candidates' valleys agree)
were visited by every candidate. :class:`BaseColumns` keeps the run's own terms' weak-form columns and
thermal-bias rows per parameter set (the separation and the parameters those terms use), so a trial evaluates
only the added effect's columns and factors the whitened system. Columns are kept in the full library's order,
so the system is the one :func:`afmid.fit.system.build_system` builds from the full library.

The shortcut is checked once per added-effect library against the full evaluation (:data:`AGREEMENT`): a gated
term switching inside a fine-grid cell makes the full library average every column over that cell, the
composed system only the columns of the library (run's or added) whose term switches; where that moves the
BIC by more than a hundredth of a unit, the full library is evaluated.

An added effect whose terms are zero until the tip reaches the surface (role ``contact_only``: a dashpot,
Kelvin-Voigt, the relaxing solid; or a gate switched on at contact: capillary's meniscus) has columns that are
exactly zero at a separation where the trajectory never gets there: they are not evaluated
(:meth:`BaseColumns.out_of_reach`). On the Bruker HSDC record (the run's separation 4 nm above first contact) most
of such a candidate's shape and separation trials are there, and the relaxing solid's stateful columns cost
~0.15 s each on its 5e5 samples.
Lengths in m.
"""

from __future__ import annotations

import logging
from collections import OrderedDict

import numpy as np

log = logging.getLogger(__name__)

#: Bytes of kept columns (and bias rows) before the least recently used are dropped. A 5e5-sample record's
#: [dmt] columns are ~1 MB per separation; a diagnosis visits a few hundred.
KEPT_BYTES = 512 << 20
#: The composed system's residual must agree with the full library's within this many BIC units (the BIC is
#: n ln(rss / n) + ...: a residual off by delta moves it by n delta / rss; 1 is the evidence scale's resolution).
#: They differ where the run's gated terms switch inside a fine-grid cell: the full library averages every column
#: over such a cell (:func:`afmid.fit.system.average_switching_cells`), an added term evaluated alone only where
#: it switches itself. Measured on a 20-period clean DMT trace, [dmt] + electrostatic: 0.0023 in a residual of
#: 2443 over 2299 rows, 0.002 BIC units.
AGREEMENT = 0.01
#: A contact-only term counts as out of reach when the trajectory's deepest point on the fine grid stays this
#: fraction of the drive amplitude short of contact (z = a0). It covers what the library evaluates beyond the
#: grid's samples: the thermal bias's central differences (afmid.fit.thermal_bias.DERIVATIVE_STEP, 1e-4 of the
#: amplitude) and the cubic sub-samples of a cell where another term's gate switches (a few 1e-6 of the amplitude
#: at 2048 points per period).
REACH_MARGIN = 0.01


class BaseColumns:
    """The columns of ``base_library`` (the run's own effects' terms) on ``prepared``, per parameter set.

    :meth:`residual` is :func:`afmid.fit.system.residual_sum_squares` of the system of a library made of these
    terms and an added effect's (in any order), with the run's terms' columns reused when their parameters were
    seen before. ``evaluations``: residuals asked for; ``repeated``: those answered from :meth:`residual`'s memo
    (the same library at the same parameters asked before); ``reused``: parameter sets whose run columns came from
    the store.
    """

    def __init__(self, prepared, base_library, kept_bytes: int = KEPT_BYTES):
        self.prepared = prepared  # afmid.fit.prepare.Prepared, shared by every refit of the diagnosis
        self.base_library = base_library
        self.kept_bytes = kept_bytes
        self._kept: OrderedDict[tuple, tuple[np.ndarray, np.ndarray | None]] = OrderedDict()
        self._bytes = 0
        self._agrees: dict[tuple, bool] = {}  # per full library (term names): the shortcut checked
        self._deepest: float | None = None  # m, the trajectory's largest deflection on the fine grid
        # (term names, parameters) -> residual: a few floats per trial, kept for the whole diagnosis
        self._residuals: dict[tuple, float] = {}
        self.evaluations = 0
        self.repeated = 0
        self.reused = 0
        self.out_of_reach_trials = 0  # trials whose added contact-only columns were zeros, not evaluated

    def _key(self, params: dict, others: frozenset) -> tuple:
        # Every parameter but the added effects' own shape parameters (``others``) can move the run's columns.
        return tuple(sorted((k, float(v)) for k, v in params.items() if k not in others))

    def columns(self, params: dict, others: frozenset = frozenset()) -> tuple[np.ndarray, np.ndarray | None]:
        """The run's own terms' columns (W, rows, p_base) and thermal-bias rows (None without a thermal force) at
        ``params`` (SI; ``d`` the rest separation), from the store when seen before; ``others``: names in
        ``params`` the run's terms do not use (an added effect's shape parameters), left out of the store's key.
        Callers do not write into them."""
        from afmid.fit.system import library_columns, library_thermal_bias

        key = self._key(params, others)
        kept = self._kept.get(key)
        if kept is not None:
            self._kept.move_to_end(key)
            self.reused += 1
            return kept
        theta = library_columns(self.prepared, self.base_library, params)
        bias = library_thermal_bias(self.prepared, self.base_library, params)
        kept = (theta, bias)
        self._kept[key] = kept
        self._bytes += theta.nbytes + (0 if bias is None else bias.nbytes)
        while self._bytes > self.kept_bytes and len(self._kept) > 1:
            _, (old_theta, old_bias) = self._kept.popitem(last=False)
            self._bytes -= old_theta.nbytes + (0 if old_bias is None else old_bias.nbytes)
        return kept

    def residual(self, library, params: dict) -> float:
        """The whitened residual sum of squares of ``library``'s full system at ``params`` (dimensionless), the
        run's own terms' columns reused (:meth:`columns`) when ``library`` holds all of them.

        A library asked again at the same parameters gets the value computed the first time, not a new evaluation:
        the searches revisit points (a candidate's two starts often find the same shape and then walk the same
        separation grid: 176 of capillary's 370 trials on the Bruker HSDC record). The value is the one evaluating
        again would give, to the bit: which path (composed or full) a library takes is settled at its first evaluated
        trial."""
        self.evaluations += 1
        key = (tuple(library.names), tuple(sorted((k, float(v)) for k, v in params.items())))
        known = self._residuals.get(key)
        if known is not None:
            self.repeated += 1
            return known
        value = self._evaluated_residual(library, params)
        self._residuals[key] = value
        return value

    def _evaluated_residual(self, library, params: dict) -> float:
        from afmid.fit.system import build_system, residual_sum_squares

        names = library.names
        key = tuple(names)
        base_names = self.base_library.names
        position = {name: i for i, name in enumerate(names)}
        plus_others = not (len(set(names)) != len(names) or any(n not in position for n in base_names)
                           or len(names) == len(base_names))
        if plus_others and self.out_of_reach(self._added_terms(library), params, library.states):
            # zero columns whatever the checks below would decide: exact for a new gate too (it never switches)
            return self._composed_residual(library, params, [position[n] for n in base_names])[0]
        if key not in self._agrees and (not plus_others or self.adds_a_gate(library)):
            self._agrees[key] = False  # not the run's terms plus others (or a new gate): nothing to reuse
        if self._agrees.get(key) is False:
            return residual_sum_squares(build_system(self.prepared, library, params))
        composed, n_rows, evaluated = self._composed_residual(library, params, [position[n] for n in base_names])
        # The check needs a trial whose added columns were evaluated (zeros out of reach agree by construction).
        if key not in self._agrees and evaluated:
            full = residual_sum_squares(build_system(self.prepared, library, params))
            agrees = n_rows * abs(composed - full) <= AGREEMENT * full
            self._agrees[key] = agrees
            if not agrees:
                log.debug("run columns reused disagree with the full library %s (%g vs %g); not reused", names,
                          composed, full)
                return full
        return composed

    def adds_a_gate(self, library) -> bool:
        """Whether ``library`` switches a state gate the run's terms do not (a meniscus that ruptures at its own
        distance). Its switching cells, wherever that distance puts them, are averaged over every column in the
        full library and not in the run's kept columns: one check at the first trial does not cover the others
        (measured: capillary on the hidden-hydration traces a and b, d unknown, ΔBIC 1.3 and 2.3 units off)."""
        from afmid.physics.effect_types import StateGate

        return any(isinstance(state, StateGate) and state not in self.base_library.states for state in library.states)

    def _added_terms(self, library) -> list:
        base = set(self.base_library.names)
        return [term for term in library.terms if term.name not in base]

    def out_of_reach(self, terms, params: dict, states=()) -> bool:
        """Whether every one of ``terms`` is zero until the tip reaches the surface (:func:`starts_at_contact`; a
        gate among ``states``) and the trajectory at ``params['d']`` (m) stays more than :data:`REACH_MARGIN` of the
        amplitude short of it: their columns and thermal-bias rows are then zero."""
        from afmid.fit.prepare import fine_chunks

        if not terms or not all(starts_at_contact(term, states) for term in terms):
            return False
        if self._deepest is None:
            self._deepest = max(float(np.max(x)) for _, x, _, _ in fine_chunks(self.prepared, overlap=1))
        margin = REACH_MARGIN * abs(float(self.prepared.drive.amplitude))
        return self._deepest + margin < float(params["d"]) - float(params["a0"])

    def _composed_residual(self, library, params: dict, base_positions: list[int]) -> tuple[float, int, bool]:
        """(the residual of the system composed of the kept run columns and the added ones, its rows, whether the
        added columns were evaluated: False when they are out of reach, :meth:`out_of_reach`)."""
        from dataclasses import replace

        from afmid.fit.system import build_system, library_columns, library_thermal_bias, residual_sum_squares

        others = frozenset(library.nonlinear) - frozenset(self.base_library.nonlinear)
        base_theta, base_bias = self.columns(params, others)
        taken = set(base_positions)
        added_positions = [i for i in range(len(library)) if i not in taken]
        # The added terms alone, with the full library's states (their gates may be among them).
        added = replace(library, terms=[library.terms[i] for i in added_positions])
        evaluated = not self.out_of_reach(added.terms, params, library.states)
        if not evaluated:
            self.out_of_reach_trials += 1
            added_theta = np.zeros(base_theta.shape[:2] + (len(added_positions),))
            added_bias = None if base_bias is None else np.zeros(base_bias.shape[:2] + (len(added_positions),))
        else:
            added_theta = library_columns(self.prepared, added, params)
            added_bias = library_thermal_bias(self.prepared, added, params)
        theta = np.empty(base_theta.shape[:2] + (len(library),))
        theta[..., base_positions] = base_theta
        theta[..., added_positions] = added_theta
        bias = None
        if base_bias is not None and added_bias is not None:
            bias = np.empty(base_bias.shape[:2] + (len(library),))
            bias[..., base_positions] = base_bias
            bias[..., added_positions] = added_bias
        elif (base_bias is None) != (added_bias is None):  # cannot happen on one preparation; never mixed
            system = build_system(self.prepared, library, params)
            return residual_sum_squares(system), system.n_rows, True
        system = build_system(self.prepared, library, params, theta=theta, thermal_bias=bias)
        return residual_sum_squares(system), system.n_rows, evaluated


def starts_at_contact(term, states=()) -> bool:
    """Whether a library term is zero wherever the tip has not yet reached the surface (z > a0 all along): it acts
    only in contact (role ``contact_only``: adhesion, a dashpot, Kelvin-Voigt, the relaxing solid), or it is a state
    gate of ``states`` declared to form at contact (:attr:`afmid.physics.effect_types.StateGate.forms_at_contact`:
    capillary's meniscus; a gate starts from its condition at the first sample, so off)."""
    from afmid.physics.effect_tags import Role
    from afmid.physics.effect_types import StateGate

    if Role.CONTACT_ONLY in term.roles:
        return True
    text = term.expression.replace(" ", "")
    gates = {state.name: state for state in states if isinstance(state, StateGate)}
    gate = gates.get(text[1:-1]) if text.startswith("[") and text.endswith("]") else None
    return gate is not None and gate.forms_at_contact
