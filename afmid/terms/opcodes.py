"""The bytecode of the term language's stack VM: its opcodes and stack size, declared once.

The compiler (:mod:`afmid.terms.term_compile`) emits them; the numba VM (:mod:`afmid.kernels.vm`) and the
generated kernels (:mod:`afmid.kernels.lawgen`) read them as ``opcodes.NAME``: the terms layer is below the
kernels (docs/architecture.md, Layers), so the compiler stays free of numba.
"""

# ---------------------------------------------------------------------------
# Code is a flat int64 array: each opcode is followed by its inline operand, if
# any. Booleans are 0.0/1.0 on the stack; a value counts as true when nonzero.
# A gated product [c] * e compiles to
#     c  JUMP_IF_FALSE_PUSH0 end  e  GATE_END  end:
# ---------------------------------------------------------------------------
PUSH_VAR = 1  # operand: variable slot
PUSH_CONST = 2  # operand: index into the program's consts
# operand: jump target, relative to the program's first code word. If the
# condition on top of the stack is false (on every sample of the block the VM
# runs), it becomes the result 0.0 and control jumps over the gated body;
# otherwise the condition stays below the body for GATE_END.
JUMP_IF_FALSE_PUSH0 = 3
# Pops the body value e and the condition c below it; pushes e where c is
# true, else 0.0 (so samples where c is false get 0.0 even if e is nan there).
GATE_END = 4
# operand k: replaces the top x by x ** (k/2) for |k| <= MAX_POW_HALVES, using
# multiplications and a sqrt, since a general pow costs ~10x more.
POW_HALVES = 5
MAX_POW_HALVES = 16
# Binary opcodes (pop b, pop a, push a op b) are 10..29.
ADD = 10
SUB = 11
MUL = 12
DIV = 13
POW = 14
MAX = 15
MIN = 16
LT = 17
LE = 18
GT = 19
GE = 20
AND = 21
OR = 22
# Unary opcodes (pop a, push f(a)) are 30 and up.
NEG = 30
EXP = 31
LOG = 32
SQRT = 33
ABS = 34
SIN = 35
COS = 36
POS = 37
NOT = 38

# Stack slots of the VM. The compiler rejects deeper expressions, so the kernel
# needs no overflow check.
STACK_SIZE = 32
