"""Integration kernels specialised to a force law: its programs translated to straight-line numba code.

The generic kernel (:mod:`afmid.kernels.integrate`) evaluates the force law by
interpreting its VM programs (:mod:`afmid.kernels.vm`) at every RK4 stage: one
interpreter call per program and point costs ~50-150 ns, most of an RK4 step.
This module translates the same programs -- the force law's terms, switching
functions and gate conditions, compiled from the effect registry by
:func:`afmid.simulate.driver.compile_force_law` -- opcode by opcode into Python source
for the four ``law_*`` functions of the integration algorithm, appends them to a
verbatim copy of the algorithm section of :mod:`afmid.kernels.integrate`, and
lets numba compile the result. Nothing about the physics is written here: the
translation follows the VM's semantics opcode for opcode (the same float64
operations in the same order, gates that short-circuit to +0.0, NaN-propagating
max/min, POW_HALVES by multiplications and a sqrt), so a generated kernel gives
the VM kernel's numbers; the tests compare them point by point and along
trajectories.

(Why generate a module rather than pass compiled law functions to one kernel:
numba specialises a kernel on each function passed to it, but cannot cache such
a specialisation on disk, so every process would compile again.)

Only the *structure* of the programs is baked into the code; their constants
(parameter values) and the term coefficients are passed at run time in the
``law`` tuple ``(consts, coef)``. A kernel therefore serves every parameter
value of a force law, and is compiled once per structure (a few seconds) and
then loaded from numba's on-disk cache.

Generated modules are plain files named by the hash of their text, in
``$AFMID_KERNEL_DIR``, else ``$NUMBA_CACHE_DIR/afmid_kernels``, else
``$XDG_CACHE_HOME/afmid/kernels`` (``~/.cache/afmid/kernels``), or if that cannot
be written, a folder in the temporary directory; numba keeps its cache next to
them (or in NUMBA_CACHE_DIR). A file is written once (atomically)
and never rewritten, so numba's cache of it stays valid; any change of the
algorithm or of the generator changes the text and hence the file name.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import afmid.terms.expr as expr
from afmid.terms import opcodes

#: Bump when the translation changes in a way the generated text would not show.
GENERATOR_VERSION = 1
_ALGORITHM_BEGIN = "# >>> algorithm"
_ALGORITHM_END = "# <<< algorithm"
#: The program variable slots (afmid.terms.expr.VARIABLES) as locals of the generated functions
#: (xdot is the parameter v), computed as afmid.kernels.integrate.fill_variables does.
_SLOT_NAMES = ("z", "zdot", "delta", "deltadot", "x", "v", "t")
if expr.VARIABLES != ("z", "zdot", "delta", "deltadot", "x", "xdot", "t"):  # pragma: no cover
    raise ImportError("afmid.terms.expr.VARIABLES changed: update afmid.kernels.lawgen._variables and fill_variables")

_lock = threading.Lock()
_loaded: dict[str, object] = {}  # text hash -> module
_by_structure: dict[tuple, object] = {}  # program structure -> module (skips regenerating the text)


class GenerationError(RuntimeError):
    """A force law could not be turned into a kernel (the caller falls back to the VM kernel)."""


@dataclass(frozen=True)
class LawKernel:
    """A generated kernel module and the run-time data of one force law for it."""

    module: object  # has integrate, evaluate_law, OK, NOT_FINITE like afmid.kernels.integrate
    law: tuple  # (consts, coef): the ``law`` argument of module.integrate
    path: Path  # the generated source file


# =========================================================================== translation
class SourceWriter:
    """Lines of generated Python source, with fresh temporary names (``_t1``, ``_t2``, ...)."""

    def __init__(self):
        self.lines: list[str] = []
        self._n = 0

    def temp(self) -> str:
        self._n += 1
        return f"_t{self._n}"

    def emit(self, indent: int, text: str) -> None:
        self.lines.append("    " * indent + text)


def _operand_names(n_gates: int) -> list[str]:
    return [*_SLOT_NAMES, *(f"gates[{g}]" for g in range(n_gates))]


def translate_program(program: expr.Program, offset: int, w: SourceWriter, indent: int, n_gates: int) -> str:
    """Emit statements computing ``program`` (constants at consts[offset:]); return the name of its value.

    The program's variable slots are the locals z, zdot, delta, deltadot, x, v, t (and ``gates[g]``), which the
    surrounding generated code defines (afmid.kernels.termgen uses it too)."""
    code = [int(c) for c in program.code]
    names = _operand_names(n_gates)

    def block(pc: int, end: int, level: int) -> str:
        stack: list[str] = []

        def assign(value: str) -> None:
            name = w.temp()
            w.emit(level, f"{name} = {value}")
            stack.append(name)

        while pc < end:
            op = code[pc]
            if op == opcodes.PUSH_VAR:
                slot = code[pc + 1]
                if slot >= len(names):
                    raise GenerationError(f"{program.text!r} reads variable slot {slot}, beyond the gates")
                stack.append(names[slot])
                pc += 2
            elif op == opcodes.PUSH_CONST:
                stack.append(f"K[{offset + code[pc + 1]}]")
                pc += 2
            elif op == opcodes.JUMP_IF_FALSE_PUSH0:
                target = code[pc + 1]
                if not (pc + 2 < target <= end) or code[target - 1] != opcodes.GATE_END:
                    raise GenerationError(f"{program.text!r}: unexpected gate layout at {pc}")
                cond = stack.pop()
                result = w.temp()
                w.emit(level, f"if {cond} != 0.0:")
                body = block(pc + 2, target - 1, level + 1)
                w.emit(level + 1, f"{result} = {body}")
                w.emit(level, "else:")
                w.emit(level + 1, f"{result} = 0.0")
                stack.append(result)
                pc = target
            elif op == opcodes.GATE_END:
                raise GenerationError(f"{program.text!r}: GATE_END without its jump at {pc}")
            elif op == opcodes.POW_HALVES:
                stack.append(_pow_halves(stack.pop(), code[pc + 1], w, level))
                pc += 2
            elif opcodes.ADD <= op < opcodes.NEG:
                b = stack.pop()
                a = stack.pop()
                assign(_binary(op, a, b))
                pc += 1
            else:
                assign(_unary(op, stack.pop()))
                pc += 1
        if len(stack) != 1:
            raise GenerationError(f"{program.text!r}: the program leaves {len(stack)} values")
        return stack[0]

    return block(0, len(code), indent)


def _binary(op: int, a: str, b: str) -> str:
    simple = {opcodes.ADD: "+", opcodes.SUB: "-", opcodes.MUL: "*", opcodes.DIV: "/", opcodes.POW: "**"}
    if op in simple:
        return f"{a} {simple[op]} {b}"
    if op == opcodes.MAX:  # NaN-propagating, like the VM and np.maximum
        return f"{a} if ({a} > {b} or {a} != {a}) else {b}"
    if op == opcodes.MIN:
        return f"{a} if ({a} < {b} or {a} != {a}) else {b}"
    compare = {opcodes.LT: "<", opcodes.LE: "<=", opcodes.GT: ">", opcodes.GE: ">="}
    if op in compare:
        return f"1.0 if {a} {compare[op]} {b} else 0.0"
    if op == opcodes.AND:
        return f"1.0 if ({a} != 0.0 and {b} != 0.0) else 0.0"
    if op == opcodes.OR:
        return f"1.0 if ({a} != 0.0 or {b} != 0.0) else 0.0"
    raise GenerationError(f"unknown binary opcode {op}")


def _unary(op: int, a: str) -> str:
    functions = {opcodes.EXP: "math.exp", opcodes.LOG: "math.log", opcodes.SQRT: "math.sqrt", opcodes.ABS: "abs",
                 opcodes.SIN: "math.sin", opcodes.COS: "math.cos"}
    if op == opcodes.NEG:
        return f"-{a}"
    if op in functions:
        return f"{functions[op]}({a})"
    if op == opcodes.POS:
        return f"{a} if ({a} > 0.0 or {a} != {a}) else 0.0"
    if op == opcodes.NOT:
        return f"1.0 if {a} == 0.0 else 0.0"
    raise GenerationError(f"unknown unary opcode {op}")


def _pow_halves(a: str, k: int, w: SourceWriter, level: int) -> str:
    """a ** (k/2) exactly as the VM's _pow_halves: repeated multiplication from 1.0, times sqrt, inverted."""
    m = abs(k)
    result = w.temp()
    if m % 2 == 1:
        w.emit(level, f"if {a} == -math.inf:")
        w.emit(level + 1, f"{result} = {a} ** {0.5 * k!r}")  # sqrt(-inf) is nan, but (-inf) ** 1.5 is inf
        w.emit(level, "else:")
        level += 1
        base = w.temp()
        w.emit(level, f"{base} = {a} + 0.0")  # -0.0 becomes +0.0
    else:
        base = a
    product = "1.0"
    for _ in range(m // 2):  # r = 1.0; r *= a (m // 2 times); 1.0 * a == a exactly
        product = base if product == "1.0" else f"({product}) * {base}"
    if m % 2 == 1:
        product = f"({product}) * math.sqrt({base})" if product != "1.0" else f"1.0 * math.sqrt({base})"
    w.emit(level, f"{result} = 1.0 / ({product})" if k < 0 else f"{result} = {product}")
    return result


def variables_read(programs) -> set[int]:
    """The variable slots (afmid.kernels.integrate.fill_variables' order) that the programs' code reads."""
    used = set()
    for p in programs:
        code = [int(c) for c in p.code]
        pc = 0
        while pc < len(code):
            op = code[pc]
            if op == opcodes.PUSH_VAR:
                used.add(code[pc + 1])
            pc += 2 if op in (opcodes.PUSH_VAR, opcodes.PUSH_CONST, opcodes.JUMP_IF_FALSE_PUSH0, opcodes.POW_HALVES) else 1
    return used


def _variables(w: SourceWriter, programs: list[expr.Program]) -> None:
    """Emit the variable locals the programs read (as afmid.kernels.integrate.fill_variables computes them)."""
    if variables_read(programs) & {0, 1, 2, 3}:  # contact_kinematics_at is in the algorithm section copied into the kernel
        w.emit(1, "z, zdot, delta, deltadot = contact_kinematics_at(x, v, dyn[5], dyn[6])")


def _offsets(programs: list[expr.Program]) -> list[int]:
    offsets, total = [], 0
    for p in programs:
        offsets.append(total)
        total += len(p.consts)
    return offsets


def law_source(terms, switching, conditions, n_gates: int) -> str:
    """Source of law_work, law_force, law_full and law_conditions for these programs.

    Constants are read from ``K = law[0]``, the programs' consts concatenated
    in the order terms, switching, conditions; coefficients from ``C = law[1]``.
    """
    terms, switching, conditions = list(terms), list(switching), list(conditions)
    if len(conditions) != 2 * n_gates:
        raise GenerationError(f"{len(conditions)} gate conditions for {n_gates} gates")
    offsets = _offsets(terms + switching + conditions)
    t_off = offsets[:len(terms)]
    s_off = offsets[len(terms):len(terms) + len(switching)]
    c_off = offsets[len(terms) + len(switching):]
    out = [
        "",
        "",
        "# " + "=" * 75 + " the force law (generated)",
        "@_inline",
        "def law_work(law, n_gates):",
        '    """No work arrays: the generated code keeps everything in registers."""',
        "    return law[0]",
    ]

    def function(name: str, signature: str, doc: str, body) -> None:
        w = SourceWriter()
        w.emit(0, "")
        w.emit(0, "")
        # Compiled as functions of their own: LLVM inlines them into the algorithm anyway, and numba
        # compiles them once instead of once per call site (inline="always" doubled the compile time).
        w.emit(0, "@_jit")
        w.emit(0, f"def {name}({signature}):")
        w.emit(1, f'"""{doc}"""')
        w.emit(1, "K = law[0]")
        w.emit(1, "C = law[1]")
        body(w)
        out.extend(w.lines)

    def term_sum(w: SourceWriter) -> None:
        values = []
        for j, (p, off) in enumerate(zip(terms, t_off)):
            w.emit(1, f"# term {j}: {p.text}")
            values.append(translate_program(p, off, w, 1, n_gates))
        w.emit(1, "total = 0.0")
        for j, value in enumerate(values):
            w.emit(1, f"total += C[{j}] * {value}")

    def force_body(w: SourceWriter) -> None:
        _variables(w, terms)
        term_sum(w)
        w.emit(1, "return total")

    def full_body(w: SourceWriter) -> None:
        _variables(w, terms + switching)
        term_sum(w)
        for j, (p, off) in enumerate(zip(switching, s_off)):
            w.emit(1, f"# switching function {j}: {p.text}")
            w.emit(1, f"s_out[{j}] = {translate_program(p, off, w, 1, n_gates)}")
        w.emit(1, "return total")

    def conditions_body(w: SourceWriter) -> None:
        _variables(w, conditions)
        for j, (p, off) in enumerate(zip(conditions, c_off)):
            w.emit(1, f"# gate {j // 2} {'off' if j % 2 else 'on'}: {p.text}")
            w.emit(1, f"cond_out[{j}] = {translate_program(p, off, w, 1, n_gates)}")

    function("law_force", "x, v, t, dyn, gates, law, work", "F_ts (N) at (x, v, t) with the current gates.",
             force_body)
    function("law_full", "x, v, t, dyn, gates, law, work, s_out",
             "F_ts (N) at (x, v, t), and the switching functions' values into s_out.", full_body)
    function("law_conditions", "x, v, t, dyn, gates, law, work, cond_out",
             "The gates' on and off conditions (interleaved, 1.0 where they hold) into cond_out.", conditions_body)
    return "\n".join(out) + "\n"


def law_constants(terms, switching, conditions) -> np.ndarray:
    """The ``K`` array of the generated code: the programs' consts in the order of :func:`law_source`."""
    return np.concatenate([np.zeros(0), *(p.consts for p in (*terms, *switching, *conditions))]).astype(np.float64)


@functools.lru_cache(maxsize=1)
def algorithm_source() -> str:
    """The algorithm section of afmid/kernels/integrate.py, verbatim."""
    text = Path(__file__).with_name("integrate.py").read_text(encoding="utf-8")
    start, end = text.find(_ALGORITHM_BEGIN), text.find(_ALGORITHM_END)
    if start < 0 or end < start:
        raise GenerationError("afmid/kernels/integrate.py has no algorithm section markers")
    return text[start:end]


def module_source(terms, switching, conditions, n_gates: int) -> str:
    """The text of a generated kernel module."""
    header = (
        '"""Integration kernel for one force-law structure, generated by afmid.kernels.lawgen. Do not edit.\n\n'
        "Terms:\n" + "".join(f"    {p.text}\n" for p in terms)
        + "Switching functions:\n" + "".join(f"    {p.text}\n" for p in switching)
        + "Gate conditions (on, off per gate):\n" + "".join(f"    {p.text}\n" for p in conditions)
        + f'"""\n# generator version {GENERATOR_VERSION}\n\n'
        "import math\n\nimport numpy as np\nfrom numba import njit\n\n"
    )
    # A law without gates: the algorithm's gate handling pruned at compile time (see HAS_GATES in the section)
    gates = ("" if n_gates else
             "\n# no gates in this law: the algorithm's gate handling is not compiled\nHAS_GATES = False\n\n")
    return header + algorithm_source() + gates + law_source(terms, switching, conditions, n_gates)


# =========================================================================== files and import
def kernel_directory() -> Path:
    """Where generated kernel modules are written (see the module docstring)."""
    if os.environ.get("AFMID_KERNEL_DIR"):
        return Path(os.environ["AFMID_KERNEL_DIR"])
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"]) / "afmid_kernels"
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "afmid" / "kernels"


def _user() -> str:
    try:
        return str(os.getuid())
    except AttributeError:  # pragma: no cover (Windows)
        return os.environ.get("USERNAME", "user")


def _write_once(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically unless it is there already (an existing file keeps its mtime)."""
    if path.exists():
        try:
            if path.read_text(encoding="utf-8") == text:
                return
        except OSError:
            pass
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.stem + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def load_module(text: str):
    """Write (once) and import the generated module with this text; memoized per process."""
    key = hashlib.sha256(text.encode("utf-8")).hexdigest()[:20]
    with _lock:
        if key in _loaded:
            return _loaded[key]
        name = f"afmid_law_{key}"
        errors = []
        for folder in (kernel_directory(), Path(tempfile.gettempdir()) / f"afmid-kernels-{_user()}"):
            path = folder / f"{name}.py"
            try:
                _write_once(path, text)
                break
            except OSError as exc:
                errors.append(f"{path}: {exc}")
        else:
            raise GenerationError(f"cannot write the generated kernel ({'; '.join(errors)})")
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        try:
            spec.loader.exec_module(module)
        except Exception:
            sys.modules.pop(name, None)
            raise
        module.SOURCE_PATH = path
        _loaded[key] = module
        return module


def law_kernel(terms, switching, conditions, coefficients, n_gates: int) -> LawKernel:
    """The generated kernel for these programs (written and imported on first use) and its ``law`` tuple.

    Raises GenerationError if the programs cannot be translated or the file cannot be written.
    """
    terms, switching, conditions = tuple(terms), tuple(switching), tuple(conditions)
    structure = (n_gates, *((p.code.tobytes(), len(p.consts), p.n_vars) for p in (*terms, *switching, *conditions)),
                 len(terms), len(switching))
    module = _by_structure.get(structure)
    if module is None:
        module = load_module(module_source(terms, switching, conditions, n_gates))
        _by_structure[structure] = module
    consts = law_constants(terms, switching, conditions)
    coef = np.ascontiguousarray(coefficients, dtype=np.float64)
    return LawKernel(module, (consts, coef), module.SOURCE_PATH)
