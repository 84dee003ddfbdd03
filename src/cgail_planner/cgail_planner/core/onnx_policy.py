"""Run an exported policy without torch: used by the planner node.

>>> policy = OnnxPolicy('policy.onnx')
>>> action = policy(obs)            # (obs_dim,) -> (3,), or (B, obs_dim) -> (B, 3)

Two backends give the same actions (max abs difference <= 1e-5, checked at load):

* ``mlp`` (default when possible): the graph is translated into a
  :class:`cgail_planner.core.mlp.MlpProgram` (numba, float64) when it only uses the operators of
  a small feed-forward network - ``Gemm``, ``MatMul``, ``Add``, ``Sub``, ``Mul``, ``Div``,
  ``Sigmoid``, ``Tanh``, ``Relu``, ``Neg``, ``Clip``, ``Identity``, ``Constant`` - on the one
  ``obs`` input, as :mod:`cgail_learning.export` writes it. A batch-1 call costs a few
  microseconds instead of onnxruntime's fixed ~10-20 us, and the planner runs the program inside
  its numba rollout (:mod:`cgail_planner.core.rollout_kernel`).
* ``onnxruntime``: any other graph (logged with the reason), or ``backend='onnxruntime'``.

The ONNX file is always opened by onnxruntime too (validation, metadata, the load-time parity
check); the translation reads the initializers with the ``onnx`` package.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from cgail_planner.core.errors import PolicyLoadError
from cgail_planner.core.mlp import MlpBuilder, MlpProgram
from cgail_sim.ftl_model import CONTRACT_KEY, PolicyContract

logger = logging.getLogger(__name__)

BACKENDS = ('auto', 'mlp', 'onnxruntime')
#: Largest difference to onnxruntime accepted by the load-time check of the ``mlp`` backend.
PARITY_TOLERANCE = 1e-5


class UnsupportedGraphError(PolicyLoadError):
    """The ONNX graph uses something the ``mlp`` backend does not evaluate."""


class OnnxPolicy:
    """Deterministic policy from an ONNX file written by ``export_onnx``.

    Args:
        path: the ``.onnx`` file.
        expected_obs_dim: if given, the model's observation size must equal it.
        backend: ``auto`` (the ``mlp`` program when the graph allows it, else onnxruntime),
            ``mlp`` (required: an unsupported graph raises) or ``onnxruntime``.

    Attributes:
        mlp: the :class:`MlpProgram` of the graph, or None when onnxruntime evaluates it.
        backend: ``mlp`` or ``onnxruntime``: the backend in use.
        contract: the catheter model and observation the policy was trained with
            (:class:`~cgail_sim.ftl_model.PolicyContract`, metadata key
            ``catheter_contract``), or None for a file written without one.

    Raises:
        PolicyLoadError: missing or corrupt file, an observation size mismatch (with the
            caller's ``expected_obs_dim`` or with the contract's), a contract that cannot be
            read, a bad ``backend``, or ``backend='mlp'`` with a graph it cannot evaluate.
    """

    def __init__(self, path: str | Path, expected_obs_dim: int | None = None,
                 backend: str = 'auto') -> None:
        self.path = Path(path)
        if backend not in BACKENDS:
            raise PolicyLoadError(f'backend must be one of {BACKENDS}, found {backend!r}')
        if not self.path.is_file():
            raise PolicyLoadError(f'ONNX policy not found: expected a file at {self.path}')
        try:
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1
            self._session = ort.InferenceSession(str(self.path), sess_options=opts,
                                                 providers=['CPUExecutionProvider'])
        except Exception as exc:  # onnxruntime raises its own untyped Fail/InvalidGraph errors
            raise PolicyLoadError(f'{self.path}: not a loadable ONNX model ({exc})') from None
        inputs = self._session.get_inputs()
        if len(inputs) != 1 or inputs[0].name != 'obs':
            raise PolicyLoadError(f'{self.path}: expected one input named obs, found '
                                  f'{[i.name for i in inputs]}')
        shape = inputs[0].shape
        if len(shape) != 2 or not isinstance(shape[1], int):
            raise PolicyLoadError(f'{self.path}: expected input shape (batch, obs_dim), found '
                                  f'{shape}')
        self.obs_dim: int = shape[1]
        meta = self._session.get_modelmeta().custom_metadata_map
        self.metadata: dict[str, Any] = {}
        for key, value in meta.items():
            try:
                self.metadata[key] = json.loads(value)
            except json.JSONDecodeError:
                self.metadata[key] = value
        if expected_obs_dim is not None and expected_obs_dim != self.obs_dim:
            raise PolicyLoadError(f'{self.path}: observation size mismatch: expected '
                                  f'{expected_obs_dim}, found {self.obs_dim} in the model')
        self.contract: PolicyContract | None = None
        if CONTRACT_KEY in self.metadata:
            try:
                self.contract = PolicyContract.from_dict(self.metadata[CONTRACT_KEY])
            except ValueError as exc:
                raise PolicyLoadError(f'{self.path}: {exc}') from None
            if self.contract.observation.dim != self.obs_dim:
                raise PolicyLoadError(f'{self.path}: contract observation size: expected the '
                                      f"model's {self.obs_dim}, found "
                                      f'{self.contract.observation.dim}')
        self.mlp: MlpProgram | None = None
        if backend != 'onnxruntime':
            try:
                self.mlp = self._checked_program()
            except UnsupportedGraphError as exc:
                if backend == 'mlp':
                    raise
                logger.warning('%s: evaluated with onnxruntime (the mlp backend cannot: %s)',
                               self.path, exc)
        self.backend = 'mlp' if self.mlp is not None else 'onnxruntime'

    def _checked_program(self) -> MlpProgram:
        """The graph as an MlpProgram that agrees with onnxruntime on probe observations."""
        program = mlp_from_onnx(self.path)
        if program.in_dim != self.obs_dim:
            raise UnsupportedGraphError(f'program input size {program.in_dim} != {self.obs_dim}')
        rng = np.random.default_rng(0)
        probe = np.vstack([np.zeros((1, self.obs_dim)), rng.normal(0.0, 1.0, (8, self.obs_dim)),
                           rng.uniform(-5.0, 5.0, (8, self.obs_dim))]).astype(np.float32)
        ref = np.asarray(self._session.run(['action'], {'obs': probe})[0], dtype=np.float64)
        got = program.forward64(probe)
        if got.shape != ref.shape:
            raise UnsupportedGraphError(f'program output shape {got.shape} != onnxruntime '
                                        f'{ref.shape}')
        diff = float(np.max(np.abs(got - ref)))
        if not diff <= PARITY_TOLERANCE:
            raise UnsupportedGraphError(f'program differs from onnxruntime by {diff:.3g} '
                                        f'(tolerance {PARITY_TOLERANCE})')
        return program

    def run_onnxruntime(self, obs: np.ndarray) -> np.ndarray:
        """(B, obs_dim) -> (B, act) float32 through onnxruntime, whatever the backend."""
        x = np.asarray(obs, dtype=np.float32)
        return np.asarray(self._session.run(['action'], {'obs': x})[0], dtype=np.float32)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Action(s) in [-1, 1] for one (obs_dim,) or a batch (B, obs_dim) of observations."""
        x = np.asarray(obs, dtype=np.float32)
        single = x.ndim == 1
        x2 = x.reshape(1, -1) if single else x
        if x2.ndim != 2 or x2.shape[1] != self.obs_dim:
            raise PolicyLoadError(f'observation size mismatch: expected (B, {self.obs_dim}), '
                                  f'found {x.shape}')
        if self.mlp is not None:
            out = self.mlp.forward64(x2).astype(np.float32)
        else:
            out = self.run_onnxruntime(x2)
        return out[0] if single else out


# --------------------------------------------------------------------------- ONNX -> program
_BINARY = {'Add': 'add', 'Sub': 'sub', 'Mul': 'mul', 'Div': 'div'}
_UNARY = {'Sigmoid': 'sigmoid', 'Tanh': 'tanh', 'Relu': 'relu', 'Neg': 'neg'}


def mlp_from_onnx(path: str | Path) -> MlpProgram:
    """Translate a feed-forward ONNX graph into an :class:`MlpProgram`.

    Raises:
        UnsupportedGraphError: the ``onnx`` package is missing, or the graph has an operator,
            attribute, constant shape or input/output layout the program cannot express.
    """
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError:
        raise UnsupportedGraphError('the onnx package is not installed '
                                    '(pip install onnx)') from None
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # protobuf's DecodeError and friends: no common base class
        raise UnsupportedGraphError(f'onnx cannot parse the file ({exc})') from None
    graph = model.graph
    init_names = {t.name for t in graph.initializer}
    inputs = [i for i in graph.input if i.name not in init_names]
    if len(inputs) != 1 or len(graph.output) != 1:
        raise UnsupportedGraphError(f'expected 1 input and 1 output, found {len(inputs)} and '
                                    f'{len(graph.output)}')
    dims = inputs[0].type.tensor_type.shape.dim
    if inputs[0].type.tensor_type.elem_type != onnx.TensorProto.FLOAT or len(dims) != 2 \
            or not dims[1].HasField('dim_value'):
        raise UnsupportedGraphError('expected a float32 (batch, obs_dim) input')
    builder = MlpBuilder(int(dims[1].dim_value))
    regs: dict[str, int] = {inputs[0].name: 0}
    consts: dict[str, np.ndarray] = {t.name: numpy_helper.to_array(t).astype(np.float64)
                                     for t in graph.initializer}

    def reg(name: str, node: Any) -> int:
        if name not in regs:
            raise UnsupportedGraphError(f'{node.op_type} {node.name!r}: operand {name!r} must '
                                        'be computed from the input')
        return regs[name]

    def const(name: str, node: Any) -> np.ndarray:
        if name not in consts:
            raise UnsupportedGraphError(f'{node.op_type} {node.name!r}: operand {name!r} must '
                                        'be a constant')
        return consts[name]

    def vector(c: np.ndarray, node: Any) -> np.ndarray:
        # a broadcast operand of a (batch, n) tensor: a scalar, (n,), or (1, n)
        if c.size == 1 or (c.ndim >= 1 and c.shape[-1] == c.size and c.ndim <= 2):
            return c.reshape(-1)
        raise UnsupportedGraphError(f'{node.op_type} {node.name!r}: constant of shape {c.shape}')

    for node in graph.node:
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        op = node.op_type
        if node.domain not in ('', 'ai.onnx') or len(node.output) != 1:
            raise UnsupportedGraphError(f'operator {node.domain}:{op} {node.name!r}')
        out = node.output[0]
        try:
            if op == 'Constant':
                if 'value' in attrs:
                    consts[out] = numpy_helper.to_array(attrs['value']).astype(np.float64)
                elif 'value_float' in attrs or 'value_floats' in attrs:
                    consts[out] = np.asarray(attrs.get('value_float', attrs.get('value_floats')),
                                             dtype=np.float64)
                else:
                    raise UnsupportedGraphError(f'Constant {node.name!r} with {sorted(attrs)}')
            elif op == 'Identity':
                if node.input[0] in regs:
                    regs[out] = regs[node.input[0]]
                else:
                    consts[out] = const(node.input[0], node)
            elif op == 'Gemm':
                if attrs.get('transA', 0):
                    raise UnsupportedGraphError(f'Gemm {node.name!r} with transA')
                a = reg(node.input[0], node)
                w = const(node.input[1], node)
                if w.ndim != 2:
                    raise UnsupportedGraphError(f'Gemm {node.name!r}: B of shape {w.shape}')
                w = (w if attrs.get('transB', 0) else w.T) * float(attrs.get('alpha', 1.0))
                bias = None
                if len(node.input) > 2 and node.input[2]:
                    bias = vector(const(node.input[2], node), node) \
                        * float(attrs.get('beta', 1.0))
                regs[out] = builder.gemm(a, w, bias)
            elif op == 'MatMul':
                a = reg(node.input[0], node)
                w = const(node.input[1], node)
                if w.ndim != 2:
                    raise UnsupportedGraphError(f'MatMul {node.name!r}: B of shape {w.shape}')
                regs[out] = builder.gemm(a, w.T, None)
            elif op in _BINARY:
                a, b = node.input[0], node.input[1]
                if a in regs and b in regs:
                    regs[out] = builder.binary(_BINARY[op], regs[a], regs[b])
                elif a in regs:
                    regs[out] = builder.binary_const(_BINARY[op], regs[a],
                                                     vector(const(b, node), node))
                elif b in regs:
                    regs[out] = builder.binary_const(_BINARY[op], regs[b],
                                                     vector(const(a, node), node),
                                                     const_first=True)
                else:
                    ca, cb = const(a, node), const(b, node)
                    with np.errstate(all='ignore'):
                        consts[out] = {'add': np.add, 'sub': np.subtract, 'mul': np.multiply,
                                       'div': np.divide}[_BINARY[op]](ca, cb)
            elif op in _UNARY:
                regs[out] = builder.unary(_UNARY[op], reg(node.input[0], node))
            elif op == 'Clip':
                low, high = float(attrs.get('min', -np.inf)), float(attrs.get('max', np.inf))
                if len(node.input) > 1 and node.input[1]:
                    low = float(vector(const(node.input[1], node), node)[0])
                if len(node.input) > 2 and node.input[2]:
                    high = float(vector(const(node.input[2], node), node)[0])
                regs[out] = builder.clip(reg(node.input[0], node), low, high)
            else:
                raise UnsupportedGraphError(f'operator {op} {node.name!r}')
        except ValueError as exc:
            if isinstance(exc, UnsupportedGraphError):
                raise
            raise UnsupportedGraphError(f'{op} {node.name!r}: {exc}') from None
    out_name = graph.output[0].name
    if out_name not in regs:
        raise UnsupportedGraphError(f'output {out_name!r} is not computed from the input')
    return builder.build(regs[out_name])
