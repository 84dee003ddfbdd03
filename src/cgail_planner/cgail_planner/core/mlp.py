"""A small feed-forward network as a flat register program, evaluated by numba.

The planner's deterministic policy is a multi-layer perceptron with the observation normaliser
baked in (:mod:`cgail_learning.export`: ``Sub``, ``Div``, ``Clip``, ``Gemm``, ``Sigmoid``,
``Mul``...). A batch-1 call through onnxruntime costs ~10-20 us of fixed overhead per step of a
1000-step rollout; the same network as a straight-line program of vector instructions runs in a
few microseconds from Python and can be called from inside a numba kernel
(:mod:`cgail_planner.core.rollout_kernel`), so a whole rollout is one native call.

A program is built with :class:`MlpBuilder` (``cgail_planner.core.onnx_policy`` translates an
ONNX graph into it) and frozen into an :class:`MlpProgram`. Register 0 holds the input; every
instruction writes one new register from earlier ones and from constants. All arithmetic is in
float64 (the float32 weights are exact in it); :meth:`MlpProgram.__call__` returns float32 like
the ONNX model does.

Instruction row (int64): ``[op, dst, a, b, c_off, c_len, n_out, n_in]``; ``c_off``/``c_len``
address the flat constant array (a ``GEMM`` stores ``W`` transposed, (n_in, n_out) row-major,
followed by the bias (n_out,); a ``CLIP`` stores ``[low, high]``; a constant operand stores 1 or
``width`` values, one value being broadcast).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from numba import njit
import numpy as np
from numpy.typing import NDArray

__all__ = ["BINARY_OPS", "UNARY_OPS", "MlpBuilder", "MlpProgram", "mlp_forward"]

# opcodes (the ``op`` column of an instruction)
OP_GEMM = 0
"""``dst = W a + bias``."""
OP_BINARY_REG = 1
"""``dst = a (op) b`` for two registers; ``b`` column is the register, ``n_in`` the binary op."""
OP_BINARY_CONST = 2
"""``dst = a (op) c`` with a constant ``c``; ``n_in`` the binary op (+ 8 when ``c (op) a``)."""
OP_UNARY = 3
"""``dst = f(a)``; ``n_in`` the unary function."""
OP_CLIP = 4
"""``dst = min(max(a, low), high)``."""

BINARY_OPS = {"add": 0, "sub": 1, "mul": 2, "div": 3}
"""Binary operations of :data:`OP_BINARY_REG` / :data:`OP_BINARY_CONST`."""
UNARY_OPS = {"identity": 0, "sigmoid": 1, "tanh": 2, "relu": 3, "neg": 4}
"""Unary functions of :data:`OP_UNARY`."""
_CONST_FIRST = 8
_N_COLS = 8

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


# error_model="numpy": a division by zero gives inf/NaN as in ONNX, not ZeroDivisionError
@njit(cache=True, inline="always", error_model="numpy")
def _binary(code, x, y):
    if code == 0:
        return x + y
    if code == 1:
        return x - y
    if code == 2:
        return x * y
    return x / y


@njit(cache=True, inline="always", error_model="numpy")
def _unary(code, x):
    if code == 1:
        # the logistic function without overflow warnings for large |x|
        if x >= 0.0:
            return 1.0 / (1.0 + math.exp(-x))
        e = math.exp(x)
        return e / (1.0 + e)
    if code == 2:
        return math.tanh(x)
    if code == 3:
        return x if x > 0.0 else 0.0
    if code == 4:
        return -x
    return x


@njit(cache=True)
def _gemm(consts, c0, n_in, n_out, x, y):
    # W is stored transposed, (n_in, n_out): the inner loop runs over independent outputs
    # (SIMD), each one summed in input order, bias first
    # (views indexed by loop counters: provably non-negative indices let LLVM vectorise)
    w = consts[c0:c0 + n_in * n_out].reshape((n_in, n_out))
    bias = consts[c0 + n_in * n_out:c0 + n_in * n_out + n_out]
    for o in range(n_out):
        y[o] = bias[o]
    for i in range(n_in):
        xi = x[i]
        for o in range(n_out):
            y[o] += w[i, o] * xi


@njit(cache=True, error_model="numpy")
def mlp_forward(ops, consts, widths, regs, x):
    """Run the program on one input vector ``x``; the registers are left in ``regs``.

    Args:
        ops: (I, 8) int64 instructions (module docstring).
        consts: flat float64 constants.
        widths: (n_regs,) int64 width of every register.
        regs: (n_regs, max width) float64 scratch; register 0 receives ``x``.
        x: (widths[0],) input.
    """
    for i in range(widths[0]):
        regs[0, i] = x[i]
    for k in range(ops.shape[0]):
        op = ops[k, 0]
        dst = ops[k, 1]
        a = ops[k, 2]
        b = ops[k, 3]
        c0 = ops[k, 4]
        n_out = ops[k, 6]
        sub = ops[k, 7]
        if op == OP_GEMM:
            _gemm(consts, c0, sub, n_out, regs[a], regs[dst])
        elif op == OP_BINARY_REG:
            sa = 1 if widths[a] > 1 else 0
            sb = 1 if widths[b] > 1 else 0
            for o in range(n_out):
                regs[dst, o] = _binary(sub, regs[a, o * sa], regs[b, o * sb])
        elif op == OP_BINARY_CONST:
            sa = 1 if widths[a] > 1 else 0
            sc = 1 if ops[k, 5] > 1 else 0
            code = sub % _CONST_FIRST
            if sub >= _CONST_FIRST:
                for o in range(n_out):
                    regs[dst, o] = _binary(code, consts[c0 + o * sc], regs[a, o * sa])
            else:
                for o in range(n_out):
                    regs[dst, o] = _binary(code, regs[a, o * sa], consts[c0 + o * sc])
        elif op == OP_UNARY:
            for o in range(n_out):
                regs[dst, o] = _unary(sub, regs[a, o])
        else:  # OP_CLIP
            lo = consts[c0]
            hi = consts[c0 + 1]
            for o in range(n_out):
                v = regs[a, o]
                if v < lo:
                    v = lo
                if v > hi:
                    v = hi
                regs[dst, o] = v


@njit(cache=True, error_model="numpy")
def _forward_batch(ops, consts, widths, regs, out_reg, x, out):
    for n in range(x.shape[0]):
        mlp_forward(ops, consts, widths, regs, x[n])
        for o in range(out.shape[1]):
            out[n, o] = regs[out_reg, o]


@dataclass(frozen=True, eq=False)
class MlpProgram:
    """A validated register program (build it with :class:`MlpBuilder`).

    Raises:
        ValueError: an instruction that would read or write outside its registers or
            constants, or an input/output size that does not match the registers.
    """

    ops: IntArray
    """(I, 8) int64 instructions ``[op, dst, a, b, c_off, c_len, n_out, n_in]``."""
    consts: FloatArray
    """Flat float64 constants (weights, biases, operands, clip bounds)."""
    widths: IntArray
    """(n_regs,) int64 width of every register; register 0 is the input."""
    out_reg: int
    """Register holding the output after the last instruction."""

    def __post_init__(self) -> None:
        ops = np.ascontiguousarray(self.ops, dtype=np.int64)
        consts = np.ascontiguousarray(self.consts, dtype=np.float64)
        widths = np.ascontiguousarray(self.widths, dtype=np.int64)
        object.__setattr__(self, "ops", ops)
        object.__setattr__(self, "consts", consts)
        object.__setattr__(self, "widths", widths)
        if ops.ndim != 2 or ops.shape[1] != _N_COLS:
            raise ValueError(f"ops must have shape (I, {_N_COLS}), found {ops.shape}")
        if widths.ndim != 1 or len(widths) < 1 or (widths < 1).any():
            raise ValueError(f"widths must be a non-empty vector of sizes >= 1, found "
                             f"{widths.tolist()}")
        if consts.ndim != 1 or not np.isfinite(consts).all():
            raise ValueError("consts must be a finite 1-D array, found "
                             f"shape {consts.shape} or NaN/inf")
        n_regs = len(widths)
        if isinstance(self.out_reg, bool) or not 0 <= int(self.out_reg) < n_regs:
            raise ValueError(f"out_reg must be a register in [0, {n_regs - 1}], found "
                             f"{self.out_reg!r}")
        written = {0}
        for k, (op, dst, a, b, c_off, c_len, n_out, sub) in enumerate(ops.tolist()):
            where = f"instruction {k} ({ops[k].tolist()})"
            if dst in written or not 0 < dst < n_regs:
                raise ValueError(f"{where}: dst must be a new register in [1, {n_regs - 1}]")
            if a not in written:
                raise ValueError(f"{where}: operand a must be a register written before")
            if n_out != widths[dst]:
                raise ValueError(f"{where}: n_out must equal the width {widths[dst]} of dst")
            if c_off < 0 or c_len < 0 or c_off + c_len > len(consts):
                raise ValueError(f"{where}: constants [{c_off}, {c_off + c_len}) must lie in "
                                 f"[0, {len(consts)})")
            if op == OP_GEMM:
                ok = sub == widths[a] and c_len == n_out * (sub + 1)
            elif op == OP_BINARY_REG:
                ok = (b in written and sub in BINARY_OPS.values()
                      and widths[a] in (1, n_out) and widths[b] in (1, n_out))
            elif op == OP_BINARY_CONST:
                ok = (sub % _CONST_FIRST in BINARY_OPS.values() and sub < 2 * _CONST_FIRST
                      and widths[a] in (1, n_out) and c_len in (1, n_out))
            elif op == OP_UNARY:
                ok = sub in UNARY_OPS.values() and widths[a] == n_out
            elif op == OP_CLIP:
                ok = widths[a] == n_out and c_len == 2
            else:
                ok = False
            if not ok:
                raise ValueError(f"{where}: operands, sizes or constants do not fit the op")
            written.add(dst)
        if int(self.out_reg) not in written:
            raise ValueError(f"out_reg must be a written register, found {self.out_reg}")
        object.__setattr__(self, "out_reg", int(self.out_reg))

    def scratch(self) -> FloatArray:
        """New (n_regs, max width) registers for :func:`mlp_forward` (one per caller: a
        program holds no mutable state, so it may be shared between threads)."""
        return np.zeros((len(self.widths), int(self.widths.max())))

    @property
    def in_dim(self) -> int:
        """Input size (the observation size)."""
        return int(self.widths[0])

    @property
    def out_dim(self) -> int:
        """Output size (the action size)."""
        return int(self.widths[self.out_reg])

    def forward64(self, x: NDArray[np.floating]) -> FloatArray:
        """(B, in_dim) -> (B, out_dim) float64 outputs.

        Raises:
            ValueError: ``x`` not of shape (B, in_dim).
        """
        xs = np.ascontiguousarray(x, dtype=np.float64)
        if xs.ndim != 2 or xs.shape[1] != self.in_dim:
            raise ValueError(f"input must have shape (B, {self.in_dim}), found {xs.shape}")
        out = np.empty((xs.shape[0], self.out_dim))
        _forward_batch(self.ops, self.consts, self.widths, self.scratch(), self.out_reg, xs,
                       out)
        return out

    def __call__(self, obs: NDArray[np.floating]) -> NDArray[np.float32]:
        """Output(s) as float32 for one (in_dim,) or a batch (B, in_dim) of inputs."""
        x = np.asarray(obs)
        single = x.ndim == 1
        out = self.forward64(x.reshape(1, -1) if single else x).astype(np.float32)
        return out[0] if single else out


class MlpBuilder:
    """Appends instructions and constants; :meth:`build` freezes them into an MlpProgram.

    Args:
        in_dim: input size (register 0).

    Every method returns the new register. Shape mismatches raise ``ValueError``.
    """

    def __init__(self, in_dim: int) -> None:
        if isinstance(in_dim, bool) or not isinstance(in_dim, int) or in_dim < 1:
            raise ValueError(f"in_dim must be an int >= 1, found {in_dim!r}")
        self._ops: list[list[int]] = []
        self._consts: list[FloatArray] = []
        self._n_consts = 0
        self.widths: list[int] = [in_dim]

    def _const(self, values: FloatArray) -> tuple[int, int]:
        v = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        if not np.isfinite(v).all():
            raise ValueError("constants must be finite, found NaN or inf")
        off = self._n_consts
        self._consts.append(v)
        self._n_consts += len(v)
        return off, len(v)

    def _emit(self, op: int, a: int, b: int, const: tuple[int, int], width: int,
              sub: int) -> int:
        if not 0 <= a < len(self.widths) or not 0 <= b < len(self.widths):
            raise ValueError(f"operands must be registers in [0, {len(self.widths) - 1}], "
                             f"found {a} and {b}")
        dst = len(self.widths)
        self.widths.append(width)
        self._ops.append([op, dst, a, b, const[0], const[1], width, sub])
        return dst

    def _check_reg(self, a: int) -> int:
        if not 0 <= a < len(self.widths):
            raise ValueError(f"register must be in [0, {len(self.widths) - 1}], found {a}")
        return self.widths[a]

    def gemm(self, a: int, weight: NDArray[np.floating], bias: NDArray[np.floating] | None
             ) -> int:
        """``W a + bias`` with ``weight`` (n_out, width of a) and ``bias`` (n_out,) or None."""
        w = np.asarray(weight, dtype=np.float64)
        n_in = self._check_reg(a)
        if w.ndim != 2 or w.shape[1] != n_in:
            raise ValueError(f"weight must have shape (n_out, {n_in}), found {w.shape}")
        bvec = np.zeros(w.shape[0]) if bias is None else np.asarray(bias, dtype=np.float64)
        if bvec.size == 1:
            bvec = np.full(w.shape[0], float(bvec.reshape(-1)[0]))
        if bvec.shape != (w.shape[0],):
            raise ValueError(f"bias must have shape ({w.shape[0]},), found {bvec.shape}")
        const = self._const(np.concatenate([w.T.reshape(-1), bvec]))
        return self._emit(OP_GEMM, a, 0, const, w.shape[0], n_in)

    def binary(self, name: str, a: int, b: int) -> int:
        """``a (name) b`` for registers (a width-1 register broadcasts)."""
        if name not in BINARY_OPS:
            raise ValueError(f"binary op must be one of {sorted(BINARY_OPS)}, found {name!r}")
        wa, wb = self._check_reg(a), self._check_reg(b)
        if wa != wb and 1 not in (wa, wb):
            raise ValueError(f"operand widths must match or be 1, found {wa} and {wb}")
        return self._emit(OP_BINARY_REG, a, b, (0, 0), max(wa, wb), BINARY_OPS[name])

    def binary_const(self, name: str, a: int, const: NDArray[np.floating],
                     const_first: bool = False) -> int:
        """``a (name) const`` (or ``const (name) a``); ``const`` has 1 or width values."""
        if name not in BINARY_OPS:
            raise ValueError(f"binary op must be one of {sorted(BINARY_OPS)}, found {name!r}")
        wa = self._check_reg(a)
        c = np.asarray(const, dtype=np.float64).reshape(-1)
        if c.size != 1 and wa not in (1, c.size):
            raise ValueError(f"constant must have 1 or {wa} values, found {c.size}")
        width = max(wa, c.size)
        sub = BINARY_OPS[name] + (_CONST_FIRST if const_first else 0)
        return self._emit(OP_BINARY_CONST, a, 0, self._const(c), width, sub)

    def unary(self, name: str, a: int) -> int:
        """``f(a)`` elementwise, ``f`` one of :data:`UNARY_OPS`."""
        if name not in UNARY_OPS:
            raise ValueError(f"unary op must be one of {sorted(UNARY_OPS)}, found {name!r}")
        return self._emit(OP_UNARY, a, 0, (0, 0), self._check_reg(a), UNARY_OPS[name])

    def clip(self, a: int, low: float, high: float) -> int:
        """``min(max(a, low), high)`` elementwise (infinite bounds allowed)."""
        lo = max(float(low), -np.finfo(np.float64).max)
        hi = min(float(high), np.finfo(np.float64).max)
        if math.isnan(lo) or math.isnan(hi) or lo > hi:
            raise ValueError(f"clip bounds must satisfy low <= high, found {low}, {high}")
        return self._emit(OP_CLIP, a, 0, self._const(np.array([lo, hi])), self._check_reg(a), 0)

    def build(self, out_reg: int) -> MlpProgram:
        """Freeze the program with ``out_reg`` as its output."""
        ops = np.array(self._ops, dtype=np.int64).reshape(-1, _N_COLS)
        consts = np.concatenate(self._consts) if self._consts else np.zeros(0)
        return MlpProgram(ops=ops, consts=consts, widths=np.array(self.widths, dtype=np.int64),
                          out_reg=out_reg)
