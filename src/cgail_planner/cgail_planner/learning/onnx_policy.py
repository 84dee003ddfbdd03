"""Run an exported policy with onnxruntime only (no torch): used by the planner node.

>>> policy = OnnxPolicy('policy.onnx')
>>> action = policy(obs)            # (obs_dim,) -> (3,), or (B, obs_dim) -> (B, 3)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from cgail_planner.learning.errors import PolicyLoadError


class OnnxPolicy:
    """Deterministic policy from an ONNX file written by ``export_onnx``.

    Args:
        path: the ``.onnx`` file.
        expected_obs_dim: if given, the model's observation size must equal it.

    Raises:
        PolicyLoadError: missing or corrupt file, or an observation size mismatch.
    """

    def __init__(self, path: str | Path, expected_obs_dim: int | None = None) -> None:
        self.path = Path(path)
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

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Action(s) in [-1, 1] for one (obs_dim,) or a batch (B, obs_dim) of observations."""
        x = np.asarray(obs, dtype=np.float32)
        single = x.ndim == 1
        x2 = x.reshape(1, -1) if single else x
        if x2.ndim != 2 or x2.shape[1] != self.obs_dim:
            raise PolicyLoadError(f'observation size mismatch: expected (B, {self.obs_dim}), '
                                  f'found {x.shape}')
        out = self._session.run(['action'], {'obs': x2})[0]
        return np.asarray(out[0] if single else out, dtype=np.float32)
