"""Tests for the force-term expression language (afmid.terms.expr) and its numba VM (afmid.kernels.vm)."""

import re
import subprocess
import sys

import numpy as np
import pytest

from afmid.terms.expr import (
    STACK_SIZE,
    VARIABLES,
    BinOp,
    Call,
    Compare,
    ExpressionError,
    Gate,
    Name,
    Neg,
    Num,
    Program,
    ProgramSet,
    StateRef,
    compile_expression,
    evaluate_numpy,
    expression_units,
    free_names,
    parse,
    switching_programs,
    unparse,
)
from afmid.kernels.vm import evaluate_numba
from afmid.terms.units import parse_unit

pytestmark = pytest.mark.numerics  # floating-point results compared (blas_sensitive ones: make test-kernels runs them again)

PARAMS = {"a0": 0.3, "R": 2.0, "lam": 0.7, "n": 1.5, "c0": 0.0}
PARAM_UNITS = {"a0": "m", "R": "m", "lam": "m", "n": "1", "c0": "m"}
STATES = ("meniscus", "jkr")
N_VARS = len(VARIABLES) + len(STATES)


def constant(text: str) -> float:
    """Value of an expression without variables, by both evaluators."""
    variables = np.zeros((N_VARS, 1))
    value = evaluate_numpy(text, variables, PARAMS, STATES)[0]
    assert evaluate_numba(text, variables, PARAMS, STATES)[0] == value
    return value


def random_variables(rng, n: int) -> np.ndarray:
    """Variables of order 1 with exact zeros, negatives and state values 0/1 mixed in."""
    v = rng.normal(size=(N_VARS, n))
    v[:, rng.random(n) < 0.05] = 0.0
    v[0] = np.where(rng.random(n) < 0.1, PARAMS["a0"], v[0])  # z exactly at a0 sometimes
    v[len(VARIABLES):] = rng.integers(0, 2, size=(len(STATES), n))
    return v


def assert_same(vm: np.ndarray, ref: np.ndarray, rtol: float = 1e-12):
    """Equal to rtol, with nan and inf in the same places."""
    np.testing.assert_array_equal(np.isnan(vm), np.isnan(ref))
    np.testing.assert_allclose(vm, ref, rtol=rtol, atol=0)


# ---------------------------------------------------------------------------
# Parsing
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, tree",
    [
        ("-z^2", Neg(BinOp("^", Name("z"), Num(2)))),
        ("z**-2", BinOp("^", Name("z"), Neg(Num(2)))),
        ("2^3^2", BinOp("^", Num(2), BinOp("^", Num(3), Num(2)))),
        ("z - x - t", BinOp("-", BinOp("-", Name("z"), Name("x")), Name("t"))),
        ("z / x / t", BinOp("/", BinOp("/", Name("z"), Name("x")), Name("t"))),
        ("z + x * t", BinOp("+", Name("z"), BinOp("*", Name("x"), Name("t")))),
        ("(z + x) * t", BinOp("*", BinOp("+", Name("z"), Name("x")), Name("t"))),
        ("+z", Name("z")),
        ("x*-z", BinOp("*", Name("x"), Neg(Name("z")))),
        ("1.5e-9 * 2E3 * .5", BinOp("*", BinOp("*", Num(1.5e-9), Num(2e3)), Num(0.5))),
        ("3. + 1e+2", BinOp("+", Num(3.0), Num(100.0))),
        ("max(z, a0)", Call("max", (Name("z"), Name("a0")))),
        ("[z > a0] * z", BinOp("*", Gate(Compare(">", Name("z"), Name("a0"))), Name("z"))),
        ("[meniscus]", Gate(StateRef("meniscus"))),
    ],
)
def test_parse_tree(text, tree):
    assert parse(text) == tree


@pytest.mark.parametrize(
    "text, value",
    [
        ("-2^2", -4.0),
        ("2^3^2", 512.0),
        ("2*3+4", 10.0),
        ("2+3*4", 14.0),
        ("(2+3)*4", 20.0),
        ("2^-1", 0.5),
        ("8/4/2", 1.0),
        ("2**3", 8.0),
        ("max(1, 2) + min(1, 2)", 3.0),
        ("pos(-3) + pos(2)", 2.0),
        ("abs(-2) * sqrt(16)", 8.0),
        ("exp(0) + log(1) + cos(0) + sin(0)", 2.0),
        ("[1 < 2] + [2 < 1] + [1 <= 1] + [1 >= 2] + [2 > 1]", 3.0),
        ("[1 < 2 and 2 < 1] + [1 < 2 or 2 < 1] + [not 2 < 1]", 2.0),
        ("[not (1 < 2 and 2 < 1)]", 1.0),
        ("[(1 - 2) < 0]", 1.0),
        ("a0 * 10", 3.0),
    ],
)
def test_evaluation_follows_precedence(text, value):
    assert constant(text) == pytest.approx(value, rel=1e-15)


@pytest.mark.parametrize(
    "text",
    [
        "-z^2",
        "(-z)^2",
        "z^(x^2)",
        "(z^x)^2",
        "z - (x - t)",
        "z / (x * t)",
        "-(z * x)",
        "z^-1.5",
        "1e-10 * z + 2.5e+300",
        "[z > a0 and (meniscus or not jkr)] * exp(-z/lam)",
        "[(z < a0 or meniscus) and x <= 0] * max(z, 0)",
        "[z - a0 < 0]",
    ],
)
def test_unparse_round_trips(text):
    tree = parse(text)
    assert parse(unparse(tree)) == tree


def test_free_names():
    text = "[z > a0 and meniscus] * exp(-z/lam) + R"
    assert free_names(text) == {"a0", "meniscus", "lam", "R"}
    assert free_names(parse(text)) == free_names(text)
    assert free_names("z * zdot + t") == set()


# ---------------------------------------------------------------------------
# Error messages
# ---------------------------------------------------------------------------


def error_of(fn, *args) -> ExpressionError:
    with pytest.raises(ExpressionError) as info:
        fn(*args)
    return info.value


def test_unknown_name_suggests_the_closest_and_lists_allowed():
    err = error_of(compile_expression, "exp(-z/lamda)", PARAMS, STATES)
    message = str(err)
    assert "unknown name 'lamda'" in message
    assert "did you mean 'lam'?" in message
    assert "allowed: z, zdot, delta, deltadot, x, xdot, t, meniscus, jkr, a0, R, lam, n, c0" in message
    assert err.pos == 7
    assert message.endswith("    exp(-z/lamda)\n           ^")


def test_syntax_error_shows_position():
    err = error_of(parse, "z * (x + ")
    assert err.pos == 9
    assert "column 10" in str(err)
    assert str(err).splitlines()[1:] == ["    z * (x + ", "             ^"]


def test_error_in_a_multiline_expression_shows_its_line():
    err = error_of(parse, "z +\n  * x")
    assert str(err).splitlines()[1:] == ["      * x", "      ^"]


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty expression"),
        ("2z", "missing operator before 'z'"),
        ("z $ x", "unexpected character '$'"),
        ("z > a0", "only allowed inside a gate"),
        ("z and x", "'and' is only allowed inside a gate"),
        ("(z + x", "expected ')' to close the '(' at column 1"),
        ("[z > a0 * z", "expected ']' to close the '['"),
        ("foo(z)", "unknown function 'foo'"),
        ("mx(z, x)", "did you mean 'max'?"),
        ("exp z", "'exp' is a function"),
        ("max(z)", "max() takes 2 arguments, got 1"),
        ("sqrt(z, x)", "sqrt() takes 1 argument, got 2"),
        ("[z < a0 < x]", "chained comparisons are not supported"),
        ("[z == a0]", "'==' is not supported"),
        ("[z + 1]", "expected a comparison"),
        ("z *", "expected a number, name, '(' or '['"),
        ("1e999", "too large"),
    ],
)
def test_syntax_errors(text, message):
    assert message in str(error_of(parse, text))


@pytest.mark.parametrize(
    "text, message",
    [
        ("[z]", "'z' is a variable, not a state"),
        ("[a0]", "'a0' is a parameter, not a state"),
        ("[menisk]", "unknown state 'menisk' (did you mean 'meniscus'?)"),
        ("z / [z > a0]", "a gate [...] cannot be a divisor"),
        ("z / (2 * [z > a0])", "a gate [...] cannot be a divisor"),
        # A constant part that is not a number would be taken as a gate that is always true (or a column of inf).
        ("[1/0 > 0] * z", "the constant 1/0 is not finite (inf)"),
        ("z * (1/(2 - 2))", "the constant 1/(2 - 2) is not finite (inf)"),
        ("[z > log(0)] * z", "the constant log(0) is not finite (-inf)"),
        ("z * 0^(-1)", "the constant 0^-1 is not finite (inf)"),
    ],
)
def test_semantic_errors(text, message):
    assert message in str(error_of(compile_expression, text, PARAMS, STATES))


def test_finite_constants_are_accepted():
    """Constant parts that are numbers stay terms as before: the check refuses only a non-finite constant."""
    for text in ("z / 2", "[z > 1/2 * a0] * z", "z * log(2)", "z * 0^2", "z * (2 - 2 + 1)"):
        compile_expression(text, PARAMS, STATES)


@pytest.mark.parametrize(
    "params, states, message",
    [
        ({"z": 1.0}, (), "parameter name 'z' is a variable"),
        ({"exp": 1.0}, (), "parameter name 'exp' is a function"),
        ({"a": 1.0}, ("a",), "parameter name 'a' is a state"),
        ({"a b": 1.0}, (), "parameter name 'a b' is not a valid name"),
        ({}, ("s", "s"), "contain a duplicate"),
        ({"a0": float("nan")}, (), "parameter 'a0' = nan is not a finite number"),
        ({"a0": "big"}, (), "parameter 'a0' = 'big' is not a finite number"),
    ],
)
def test_declaration_errors(params, states, message):
    assert message in str(error_of(compile_expression, "z * a0", params, states))


def test_too_deep_for_the_stack():
    deep = "z" + "".join(f" + (z * {i}" for i in range(STACK_SIZE)) + ")" * STACK_SIZE
    assert "nested too deeply for the VM" in str(error_of(compile_expression, deep, {}))
    compile_expression("z" + " + z" * 150, {})  # a long sum needs a stack of 2 only
    assert "nested too deeply (more than 200 levels)" in str(error_of(parse, "z" + " + z" * 300))
    assert "nested too deeply" in str(error_of(parse, "(" * 1000 + "z" + ")" * 1000))


# ---------------------------------------------------------------------------
# Units
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, unit",
    [
        ("[z <= a0] * delta^1.5", "m^1.5"),
        ("delta^0.5*deltadot", "m^1.5/s"),
        ("exp(-z/lam)*zdot", "m/s"),
        ("[z > a0] * z^-2", "m^-2"),
        ("[z > a0] * R / z^2", "m^-1"),
        ("sqrt(R * delta) * delta", "m^2"),
        ("[meniscus] * x", "m"),
        ("[meniscus]", "1"),
        ("meniscus * x", "m"),
        ("pos(a0 - z) + abs(x)", "m"),
        ("max(z, 0) - min(0, x)", "m"),  # a literal 0 fits any unit
        ("[z - a0 > 0] * zdot", "m/s"),
        ("(z / a0)^n", "1"),  # a dimensionless base may take a parameter exponent
        ("z^(3/2)", "m^1.5"),
        ("z^-(1/3) * z^(1/3)", "1"),
        ("t * zdot", "m"),
        ("x / t", "m/s"),
        ("log(z / R) + sin(t / t) + cos(1)", "1"),
    ],
)
def test_expression_units(text, unit):
    assert expression_units(text, PARAM_UNITS, STATES) == parse_unit(unit)


def test_units_accept_unit_objects():
    units = {name: parse_unit(u) for name, u in PARAM_UNITS.items()}
    assert expression_units("a0 * R", units) == parse_unit("m^2")


@pytest.mark.parametrize(
    "text, message",
    [
        ("z + zdot", "'+' needs equal units, got m and m/s in 'z + zdot'"),
        ("z - 1", "'-' needs equal units, got m and 1"),
        ("max(z, zdot)", "max() needs equal units, got m and m/s"),
        ("[z > t] * x", "comparison '>' needs equal units, got m and s"),
        ("exp(z)", "the argument of exp() must be dimensionless, got m"),
        ("log(t)", "the argument of log() must be dimensionless, got s"),
        ("z^t", "an exponent must be dimensionless, got s"),
        ("(z/a0)^(x/a0)", "an exponent must be a constant"),
        ("z^n", "the exponent of a quantity in m must be a number, not 'n'"),
    ],
)
def test_unit_errors(text, message):
    err = error_of(expression_units, text, PARAM_UNITS, STATES)
    assert message in str(err)
    assert err.pos is not None


def test_unit_error_points_at_the_operator():
    err = error_of(expression_units, "a0 * z + zdot", PARAM_UNITS)
    assert err.pos == 7


def test_bad_parameter_unit():
    assert "parameter 'a0' has an invalid unit" in str(error_of(expression_units, "z", {"a0": "furlong"}))


# ---------------------------------------------------------------------------
# Compilation
# ---------------------------------------------------------------------------


def test_parameters_and_constants_are_folded():
    program = compile_expression("2 * 3 * a0 * z", PARAMS)
    assert isinstance(program, Program)
    assert program.code.dtype == np.int64 and program.consts.dtype == np.float64
    assert program.consts.tolist() == [6 * PARAMS["a0"]]
    assert program.n_vars == len(VARIABLES)
    assert program.params == (("a0", 0.3),)
    assert program.text == "2 * 3 * a0 * z"
    other = compile_expression("2 * 3 * a0 * z", {**PARAMS, "a0": 1.0})
    assert np.array_equal(other.code, program.code) and other.consts.tolist() == [6.0]


def test_constant_gates_are_folded():
    assert compile_expression("[a0 < 0] * z^-2", PARAMS).consts.tolist() == [0.0]
    assert len(compile_expression("[a0 > 0] * z", PARAMS).code) == 2  # just PUSH_VAR z


def test_program_arrays_are_read_only():
    program = compile_expression("z * a0", PARAMS)
    with pytest.raises(ValueError):
        program.code[0] = 0
    with pytest.raises(ValueError):
        program.consts[0] = 0.0


def test_states_follow_the_variables():
    program = compile_expression("[jkr] * x", {}, STATES)
    assert program.n_vars == N_VARS
    variables = np.zeros((N_VARS, 2))
    variables[4] = 3.0  # x
    variables[len(VARIABLES) + 1] = [0.0, 1.0]  # jkr
    assert evaluate_numba(program, variables).tolist() == [0.0, 3.0]
    assert evaluate_numpy(program, variables).tolist() == [0.0, 3.0]


def test_variables_shape_is_checked():
    with pytest.raises(ValueError, match="shape"):
        evaluate_numpy("z", np.zeros((3, 4)))
    with pytest.raises(ValueError, match="shape"):
        evaluate_numba("[meniscus] * z", np.zeros((len(VARIABLES), 4)), {}, STATES)


def test_program_set_layout():
    programs = [compile_expression(t, PARAMS, STATES) for t in ("z", "[z > a0] * z^-2", "a0 * x + R")]
    pset = ProgramSet(programs)
    assert pset.n_programs == 3 and pset.n_vars == N_VARS
    assert pset.code_offsets.tolist() == np.cumsum([0] + [len(p.code) for p in programs]).tolist()
    assert pset.const_offsets.tolist() == np.cumsum([0] + [len(p.consts) for p in programs]).tolist()
    assert pset.code_offsets.dtype == pset.const_offsets.dtype == np.int64
    for j, p in enumerate(programs):
        assert np.array_equal(pset.code[pset.code_offsets[j]:pset.code_offsets[j + 1]], p.code)
        assert np.array_equal(pset.consts[pset.const_offsets[j]:pset.const_offsets[j + 1]], p.consts)
    empty = ProgramSet([])
    assert empty.n_programs == 0 and empty.code_offsets.tolist() == [0]


# ---------------------------------------------------------------------------
# Gates short-circuit
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text",
    [
        "[z > a0] * z^-2",
        "z^-2 * [z > a0]",
        "-[z > a0] * z^-2",
        "[z > a0] * log(z - a0) / (z - a0)",
        "2 * ([z > a0] * x) / (z - a0)",
        "[z > a0] * [meniscus] * (z - a0)^-1.5",
        "[z > a0] * [meniscus] * 1 / (0 * z)",
        "[z > a0] * z^-2 + [z <= a0] * (a0 - z)^1.5",
        "[z > a0]",
    ],
)
def test_gates_short_circuit(text):
    """Where the gate is false the term is exactly 0, though the gated factor is inf or nan."""
    z = np.array([-1.0, 0.0, 0.1, 0.3, 0.31, 2.0] * 50)  # 300 samples: mixed and uniform blocks
    variables = np.zeros((N_VARS, z.size))
    variables[0] = z
    variables[4] = 1.0
    variables[len(VARIABLES)] = 1.0  # meniscus
    ref = evaluate_numpy(text, variables, PARAMS, STATES)
    vm = evaluate_numba(text, variables, PARAMS, STATES)
    assert not np.isnan(ref).any() and not np.isnan(vm).any()
    assert_same(vm, ref)
    off = z <= PARAMS["a0"]
    if "<=" not in text:
        assert np.all(vm[off] == 0.0)


def test_gate_false_on_whole_blocks_and_alone():
    z = np.full(1000, -1.0)  # gate false everywhere: the body is skipped
    z[500] = 1.0
    variables = np.zeros((len(VARIABLES), z.size))
    variables[0] = z
    vm = evaluate_numba("[z > 0] * log(z)", variables)
    assert vm[500] == 0.0 and np.count_nonzero(vm) == 0 and not np.isnan(vm).any()
    assert evaluate_numba("[z > 0]", variables).sum() == 1.0


# ---------------------------------------------------------------------------
# Switching functions
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, switches",
    [
        ("[z <= a0] * delta^1.5", ["z - a0"]),
        ("[z > a0] * z^-2 + [z <= a0] * delta^1.5", ["z - a0"]),  # identical ones merged
        ("[a0 < z] * z^-2", ["a0 - z"]),
        ("max(z, a0) + min(x, 2 * a0)", ["z - a0", "x - 2*a0"]),
        ("pos(a0 - z) * abs(x)", ["a0 - z", "x"]),
        ("[meniscus and z > a0 or x < 0] * z", ["z - a0", "x - 0"]),
        ("[meniscus] * x", []),
        ("[a0 > 0] * z + max(R, a0)", []),  # constant after folding
        ("exp(-z/lam) * zdot", []),
    ],
)
def test_switching_programs(text, switches):
    programs = switching_programs(text, PARAMS, STATES)
    assert [p.text for p in programs] == switches


def test_switching_program_values():
    (program,) = switching_programs("[z <= a0] * delta^1.5", PARAMS)
    variables = np.zeros((len(VARIABLES), 3))
    variables[0] = [0.0, 0.3, 1.0]
    np.testing.assert_allclose(evaluate_numba(program, variables), [-0.3, 0.0, 0.7])
    np.testing.assert_allclose(evaluate_numpy(program, variables), [-0.3, 0.0, 0.7])


# ---------------------------------------------------------------------------
# VM against the NumPy twin
# ---------------------------------------------------------------------------

_LEAVES = [*VARIABLES, "a0", "R", "lam", "n", "c0", "0", "1", "2", "0.5", "3.25", "1e-3"]
_EXPONENTS = ["2", "3", "-2", "-1", "0.5", "1.5", "-1.5", "0", "0.3", "n", "-n", "(x)", "17", "2.5"]


def random_expression(rng, depth: int) -> str:
    """A random expression text exercising every construct of the language."""
    if depth == 0 or rng.random() < 0.2:
        return str(rng.choice(_LEAVES))
    def sub() -> str:
        return random_expression(rng, depth - 1)

    kind = rng.integers(9)
    if kind <= 2:
        return f"({sub()} {rng.choice(['+', '-', '*', '/'])} {sub()})"
    if kind == 3:
        return f"({sub()})^{rng.choice(_EXPONENTS)}"
    if kind == 4:
        return f"{rng.choice(['exp', 'log', 'sqrt', 'abs', 'sin', 'cos', 'pos'])}({sub()})"
    if kind == 5:
        return f"{rng.choice(['max', 'min'])}({sub()}, {sub()})"
    if kind == 6:
        return f"-{sub()}"
    gate = f"[{random_condition(rng, depth - 1)}]"
    if kind == 7:
        return f"({gate} * {sub()})" if rng.random() < 0.5 else f"({sub()} * {gate})"
    return gate


def random_condition(rng, depth: int) -> str:
    kind = rng.integers(5)
    if kind == 0 and depth > 0:
        left, right = random_condition(rng, depth - 1), random_condition(rng, depth - 1)
        return f"({left} {rng.choice(['and', 'or'])} {right})"
    if kind == 1 and depth > 0:
        return f"not {random_condition(rng, depth - 1)}"
    if kind == 2:
        return str(rng.choice(STATES))
    op = rng.choice(["<", "<=", ">", ">="])
    return f"{random_expression(rng, max(depth - 1, 0))} {op} {random_expression(rng, max(depth - 1, 0))}"


HAND_WRITTEN = [
    "[z <= a0] * delta^1.5",
    "[z > a0] * z^-2",
    "exp(-z/lam) * zdot",
    "[z <= a0] * delta^0.5 * deltadot",
    "[meniscus and z > a0] * (z - a0)",
    "max(z, x) * min(zdot, xdot) + pos(t - 1)",
    "z^x + (-z)^n + z^-n",
    "log(abs(z)) * sin(x) / cos(t)",
]


def random_programs(rng, count: int, depth: int) -> tuple[list[str], list[Program]]:
    """HAND_WRITTEN and ``count`` random expressions, compiled (those dividing by a gate or with a constant part
    that is not finite, such as 3.25/0, are rejected)."""
    texts, programs = [], []
    for text in HAND_WRITTEN + [random_expression(rng, depth) for _ in range(count)]:
        try:
            programs.append(compile_expression(text, PARAMS, STATES))
        except ExpressionError as exc:
            assert "cannot be a divisor" in str(exc) or "is not finite" in str(exc)
            continue
        texts.append(text)
    assert len(texts) > 0.8 * count
    return texts, programs


def well_conditioned(text: str, variables: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Samples where ``text`` barely moves when the variables move by 1e-13 relative.

    Elsewhere (cancellation, sin of a huge argument, a comparison on a knife's
    edge) the last-bit differences between libm and NumPy's exp, log, sin, cos
    and pow are legitimately amplified, so those samples are not compared.
    """
    nudged = evaluate_numpy(text, variables * (1 + 1e-13), PARAMS, STATES)
    with np.errstate(invalid="ignore"):
        close = np.isclose(nudged, ref, rtol=1e-9, atol=0) | (nudged == ref)
    return close | np.isnan(nudged) & np.isnan(ref)


def test_vm_matches_numpy_twin_on_random_expressions():
    rng = np.random.default_rng(20240611)
    texts, programs = random_programs(rng, 400, 5)
    variables = random_variables(rng, 1000)  # 7 full blocks of 128 and a partial one
    compared = 0
    for i, (text, program) in enumerate(zip(texts, programs)):
        assert parse(unparse(parse(text))) == parse(text)
        ref = evaluate_numpy(text, variables, PARAMS, STATES)
        vm = evaluate_numba(program, variables)
        ok = well_conditioned(text, variables, ref)
        compared += ok.sum()
        # Typical terms agree to 1e-12. Deep random nests can sit at a stationary
        # point (log(sin(u)^3) with sin(u) ~ 1) where a 1-ulp libm difference
        # grows to ~1e-11 without the variables' nudge revealing it.
        rtol = 1e-12 if i < len(HAND_WRITTEN) else 1e-10
        try:
            assert_same(vm[ok], ref[ok], rtol)
        except AssertionError as exc:
            raise AssertionError(f"VM and NumPy differ for {text!r}") from exc
    assert compared > 0.9 * len(texts) * variables.shape[1]

    from afmid.kernels.vm import eval_set

    pset = ProgramSet(programs)
    out = np.empty((variables.shape[1], pset.n_programs))
    eval_set(pset.code, pset.code_offsets, pset.consts, pset.const_offsets, variables, out)
    for j, program in enumerate(programs):
        assert_same(out[:, j], evaluate_numba(program, variables), rtol=0)


def test_point_kernels_match_eval_set():
    from afmid.kernels.vm import eval_point, eval_set, eval_set_point

    rng = np.random.default_rng(7)
    pset = ProgramSet(random_programs(rng, 60, 4)[1])
    variables = random_variables(rng, 300)
    out = np.empty((variables.shape[1], pset.n_programs))
    eval_set(pset.code, pset.code_offsets, pset.consts, pset.const_offsets, variables, out)
    point = np.empty(pset.n_programs)
    stack = np.empty((STACK_SIZE, 1))
    for i in range(0, variables.shape[1], 7):
        column = variables[:, i]  # a strided view
        eval_set_point(pset.code, pset.code_offsets, pset.consts, pset.const_offsets, column, point)
        np.testing.assert_array_equal(point, out[i])
        point[:] = 0.0
        eval_set_point(pset.code, pset.code_offsets, pset.consts, pset.const_offsets, column.copy(), point,
                       stack)
        np.testing.assert_array_equal(point, out[i])
        j = i % pset.n_programs
        c0, c1 = pset.code_offsets[j], pset.code_offsets[j + 1]
        k0, k1 = pset.const_offsets[j], pset.const_offsets[j + 1]
        np.testing.assert_array_equal(eval_point(pset.code, c0, c1, pset.consts, k0, k1, column), out[i, j])


def test_evaluate_numpy_reuses_program_params():
    program = compile_expression("a0 * z", PARAMS)
    variables = np.ones((len(VARIABLES), 2))
    assert evaluate_numpy(program, variables).tolist() == [0.3, 0.3]
    assert evaluate_numpy(program, variables, {"a0": 2.0}).tolist() == [2.0, 2.0]
    assert evaluate_numpy("2", variables).tolist() == [2.0, 2.0]  # constants broadcast


def test_importing_expr_does_not_import_numba():
    code = "import sys, afmid.terms.expr; assert 'numba' not in sys.modules, 'numba was imported'"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_no_eval_of_user_text():
    # The facade and every module of the term language it re-exports.
    import afmid.terms.term_compile  # noqa: F401 (looked up in sys.modules below)
    import afmid.terms.term_lowering  # noqa: F401 (looked up in sys.modules below)
    import afmid.terms.term_parser  # noqa: F401 (looked up in sys.modules below)
    import afmid.terms.term_units  # noqa: F401 (looked up in sys.modules below)

    forbidden = r"(?<![\w.])(eval|exec|compile)\(|^\s*(import|from) ast\b|ast\.parse\("
    for module in ("afmid.terms.expr", "afmid.terms.term_parser", "afmid.terms.term_units", "afmid.terms.term_lowering", "afmid.terms.term_compile"):
        with open(sys.modules[module].__file__) as f:
            source = f.read()
        assert not re.search(forbidden, source, re.M), module
