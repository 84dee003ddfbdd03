"""OnnxPolicy's mlp backend: ONNX graph -> numba program, parity with onnxruntime, fallback."""

import logging
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper, TensorProto
import pytest

from cgail_learning.errors import PolicyLoadError
from cgail_planner.core.mlp import MlpBuilder, MlpProgram
from cgail_planner.core.onnx_policy import mlp_from_onnx, OnnxPolicy, UnsupportedGraphError

MODELS = Path(__file__).resolve().parents[3] / 'cgail_planner' / 'cgail_planner' / 'models'
FIXTURES = Path(__file__).resolve().parents[3] / 'cgail_planner' / 'test' / 'fixtures'


def random_obs(n: int, dim: int = 41, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.vstack([rng.normal(0.0, 1.0, (n, dim)), rng.uniform(-20, 20, (n, dim)),
                      np.zeros((1, dim))]).astype(np.float32)


@pytest.mark.parametrize('path', [MODELS / 'cgail_default_static.onnx',
                                  FIXTURES / 'straight_policy.onnx',
                                  FIXTURES / 'untrained_policy.onnx',
                                  FIXTURES / 'bc_demo_policy.onnx'])
def test_exported_policies_run_on_the_mlp_backend_as_onnxruntime_does(path) -> None:
    policy = OnnxPolicy(path, expected_obs_dim=41)
    assert policy.backend == 'mlp' and isinstance(policy.mlp, MlpProgram)
    obs = random_obs(500)
    ref = policy.run_onnxruntime(obs)
    got = policy(obs)
    assert got.dtype == np.float32 and got.shape == (len(obs), 3)
    assert np.abs(got - ref).max() <= 1e-5
    single = policy(obs[3])
    assert single.shape == (3,) and np.abs(single - ref[3]).max() <= 1e-5


def write_model(path: Path, nodes, initializers, in_dim: int, out_dim: int,
                out_name: str = 'action') -> Path:
    graph = helper.make_graph(
        nodes, 'g', [helper.make_tensor_value_info('obs', TensorProto.FLOAT, ['batch', in_dim])],
        [helper.make_tensor_value_info(out_name, TensorProto.FLOAT, ['batch', out_dim])],
        [numpy_helper.from_array(np.asarray(v, dtype=np.float32), k)
         for k, v in initializers.items()])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid('', 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def test_every_supported_operator_matches_onnxruntime(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    init = {'w1': rng.normal(0, 0.3, (6, 8)), 'b1': rng.normal(0, 0.1, 8),
            'w2': rng.normal(0, 0.3, (5, 8)), 'b2': rng.normal(0, 0.1, 5),
            'w3': rng.normal(0, 0.3, (5, 4)), 'shift': rng.normal(0, 1, 6),
            'scale': rng.uniform(0.5, 2.0, (1, 6)), 'two': np.array(2.0), 'lo': np.array(-0.8)}
    n = helper.make_node
    nodes = [
        n('Constant', [], ['hi'], value=numpy_helper.from_array(np.array(0.9, np.float32))),
        n('Sub', ['shift', 'obs'], ['x0']),                  # const - x
        n('Div', ['x0', 'scale'], ['x1']),                   # x / (1, n) const
        n('Identity', ['x1'], ['x2']),
        n('MatMul', ['x2', 'w1'], ['m1']),
        n('Add', ['m1', 'b1'], ['h1']),
        n('Tanh', ['h1'], ['t1']),
        n('Relu', ['h1'], ['r1']),
        n('Mul', ['t1', 'r1'], ['p1']),                      # register * register
        n('Sub', ['p1', 'h1'], ['q1']),
        n('Gemm', ['q1', 'w2', 'b2'], ['g2'], transB=1, alpha=0.5, beta=2.0),
        n('Sigmoid', ['g2'], ['s2']),
        n('Neg', ['s2'], ['n2']),
        n('Add', ['s2', 'two'], ['e2']),
        n('Div', ['two', 'e2'], ['d2']),                     # scalar const / x
        n('Add', ['n2', 'd2'], ['a2']),
        n('Gemm', ['a2', 'w3'], ['g3']),                     # no bias, B not transposed
        n('Mul', ['g3', 'two'], ['g4']),
        n('Clip', ['g4', 'lo', 'hi'], ['action']),
    ]
    path = write_model(tmp_path / 'ops.onnx', nodes, init, 6, 4)
    policy = OnnxPolicy(path, backend='mlp')
    obs = random_obs(300, dim=6)
    ref = policy.run_onnxruntime(obs)
    assert np.abs(policy(obs) - ref).max() <= 1e-5
    clipped = (ref == np.float32(-0.8)) | (ref == np.float32(0.9))
    assert 0.01 < clipped.mean() < 0.99  # the clip is active on some outputs, not all


def test_unsupported_graph_falls_back_to_onnxruntime_with_a_logged_reason(tmp_path: Path,
                                                                          caplog) -> None:
    rng = np.random.default_rng(0)
    nodes = [helper.make_node('Gemm', ['obs', 'w', 'b'], ['h'], transB=1),
             helper.make_node('Softplus', ['h'], ['action'])]
    path = write_model(tmp_path / 'softplus.onnx', nodes,
                       {'w': rng.normal(size=(3, 5)), 'b': np.zeros(3)}, 5, 3)
    with caplog.at_level(logging.WARNING, logger='cgail_planner.core.onnx_policy'):
        policy = OnnxPolicy(path)
    assert policy.backend == 'onnxruntime' and policy.mlp is None
    assert 'evaluated with onnxruntime' in caplog.text and 'operator Softplus' in caplog.text
    obs = random_obs(10, dim=5)
    h = obs.astype(np.float64) @ np.asarray(onnx.numpy_helper.to_array(
        onnx.load(str(path)).graph.initializer[0]), dtype=np.float64).T
    np.testing.assert_allclose(policy(obs), np.log1p(np.exp(h)), rtol=1e-5, atol=1e-5)
    with pytest.raises(UnsupportedGraphError, match='operator Softplus'):
        OnnxPolicy(path, backend='mlp')


@pytest.mark.parametrize(('nodes', 'init', 'match'), [
    ([helper.make_node('MatMul', ['obs', 'obs'], ['action'])], {},
     "operand 'obs' must be a constant"),
    ([helper.make_node('MatMul', ['w', 'obs'], ['action'])], {'w': np.ones((3, 3))},
     "operand 'w' must be computed from the input"),
    ([helper.make_node('Add', ['obs', 'c'], ['action'])], {'c': np.ones((2, 3))},
     r'constant of shape \(2, 3\)'),
    ([helper.make_node('Gemm', ['obs', 'w'], ['action'], transA=1)], {'w': np.ones((3, 3))},
     'transA'),
])
def test_graphs_the_program_cannot_express_are_refused(tmp_path, nodes, init, match) -> None:
    path = tmp_path / 'm.onnx'
    graph = helper.make_graph(
        nodes, 'g', [helper.make_tensor_value_info('obs', TensorProto.FLOAT, ['batch', 3])],
        [helper.make_tensor_value_info('action', TensorProto.FLOAT, None)],
        [numpy_helper.from_array(np.asarray(v, dtype=np.float32), k) for k, v in init.items()])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid('', 17)]), str(path))
    with pytest.raises(UnsupportedGraphError, match=match):
        mlp_from_onnx(path)


def test_backend_choice_and_errors(tmp_path: Path) -> None:
    path = MODELS / 'cgail_default_static.onnx'
    ort_only = OnnxPolicy(path, backend='onnxruntime')
    assert ort_only.backend == 'onnxruntime' and ort_only.mlp is None
    obs = random_obs(20)
    assert np.abs(ort_only(obs) - OnnxPolicy(path)(obs)).max() <= 1e-5
    with pytest.raises(PolicyLoadError, match="backend must be one of"):
        OnnxPolicy(path, backend='torch')
    with pytest.raises(PolicyLoadError, match=r'expected \(B, 41\), found \(40,\)'):
        OnnxPolicy(path)(np.zeros(40))
    bad = tmp_path / 'bad.onnx'
    bad.write_bytes(b'\x00garbage')
    with pytest.raises(PolicyLoadError, match='not a loadable ONNX model'):
        OnnxPolicy(bad)


def test_program_validation_rejects_out_of_range_instructions() -> None:
    b = MlpBuilder(4)
    h = b.gemm(0, np.ones((3, 4)), np.zeros(3))
    out = b.unary('sigmoid', h)
    prog = b.build(out)
    assert prog(np.zeros(4)) == pytest.approx([0.5, 0.5, 0.5])
    ops = prog.ops.copy()
    ops[1, 2] = 5  # reads a register never written
    with pytest.raises(ValueError, match='operand a must be a register written before'):
        MlpProgram(ops=ops, consts=prog.consts, widths=prog.widths, out_reg=out)
    ops = prog.ops.copy()
    ops[0, 4] = len(prog.consts)  # constants past the end
    with pytest.raises(ValueError, match=r'constants \[\d+, \d+\) must lie in'):
        MlpProgram(ops=ops, consts=prog.consts, widths=prog.widths, out_reg=out)
    with pytest.raises(ValueError, match='out_reg must be a register in'):
        MlpProgram(ops=prog.ops, consts=prog.consts, widths=prog.widths, out_reg=7)
    with pytest.raises(ValueError, match=r'weight must have shape \(n_out, 4\)'):
        MlpBuilder(4).gemm(0, np.ones((3, 5)), None)
    with pytest.raises(ValueError, match='operand widths must match or be 1'):
        b.binary('add', 0, h)
    with pytest.raises(ValueError, match='input must have shape'):
        prog(np.zeros(5))


def test_no_torch_in_the_node_side_modules() -> None:
    root = Path(__file__).resolve().parents[3] / 'cgail_planner' / 'cgail_planner'
    for rel in ('core/onnx_policy.py', 'core/mlp.py', 'core/rollout_kernel.py',
                'core/planner.py'):
        text = (root / rel).read_text()
        assert 'import torch' not in text and 'from torch' not in text, rel
