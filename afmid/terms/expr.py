"""A small, safe expression language for force-library terms.

A term is an arithmetic expression in the tip-sample variables (see
:data:`VARIABLES`), named scalar parameters and boolean history states, e.g.::

    [z <= a0] * delta^1.5          Hertz-type contact term
    [z > a0] * z^-2                van der Waals-type term, zero in contact
    exp(-z/lambda) * zdot          distance-dependent damping
    [meniscus and z > a0] * z      a term that only acts while a state is set

Grammar (usual precedence, lowest first)::

    expr   := term (('+' | '-') term)*
    term   := unary (('*' | '/') unary)*
    unary  := ('-' | '+') unary | power
    power  := atom (('^' | '**') unary)?           right-associative; -z^2 = -(z^2)
    atom   := number | name | func '(' expr (',' expr)* ')' | '(' expr ')' | '[' cond ']'
    cond   := and_c ('or' and_c)*
    and_c  := not_c ('and' not_c)*
    not_c  := 'not' not_c | expr ('<' | '<=' | '>' | '>=') expr | state | '(' cond ')'

A gate ``[cond]`` is worth 1 where ``cond`` holds and 0 elsewhere. A gate that
multiplies something short-circuits: ``[z > a0] * z^-2`` is exactly 0 where the
gate is false, even where ``z^-2`` is inf or nan.

Text is parsed by a hand-written tokenizer and recursive-descent parser (user
text is never given to eval, exec, compile or ast.parse). :func:`compile_expression`
turns an expression into a :class:`Program` for the numba stack VM in
:mod:`afmid.kernels.vm`; :func:`evaluate_numpy` is its plain-NumPy twin, used to
test the VM. This module does not import numba (nor any kernel: the VM reads
its opcodes from :mod:`afmid.terms.opcodes`; :func:`afmid.kernels.vm.evaluate_numba`
evaluates one expression with it).

Layout: the term language lives in four modules, re-exported here (the public
facade; callers import from :mod:`afmid.terms.expr`):

- :mod:`afmid.terms.term_parser` -- variables, tokenizer, parser, AST, unparse, name checks;
- :mod:`afmid.terms.term_units` -- :func:`expression_units`, the dimensional check;
- :mod:`afmid.terms.term_lowering` -- names to slots and values, gates pulled out of
  products, constant folding, NumPy operations with the VM's float64 semantics;
- :mod:`afmid.terms.opcodes` -- the VM's opcodes and stack size;
- :mod:`afmid.terms.term_compile` -- :class:`Program`, :func:`compile_expression`,
  :func:`switching_programs`, :class:`ProgramSet`, :func:`evaluate_numpy`.
"""

from __future__ import annotations

from afmid.terms.opcodes import MAX_POW_HALVES, STACK_SIZE  # noqa: F401 (re-exported)
from afmid.terms.term_compile import (  # noqa: F401 (re-exported)
    Program,
    ProgramSet,
    check_variables,
    compile_expression,
    evaluate_numpy,
    switching_programs,
)
from afmid.terms.term_parser import (  # noqa: F401 (re-exported)
    COMPARISONS,
    FUNCTIONS,
    KEYWORDS,
    MAX_TREE_DEPTH,
    VARIABLES,
    VARIABLE_UNITS,
    BinOp,
    BoolOp,
    Call,
    Compare,
    Cond,
    ExpressionError,
    Gate,
    Name,
    Neg,
    Node,
    Not,
    Num,
    StateRef,
    free_names,
    parse,
    unparse,
)
from afmid.terms.term_units import expression_units  # noqa: F401 (re-exported)
