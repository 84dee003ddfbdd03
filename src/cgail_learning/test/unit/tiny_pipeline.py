"""The shared start of the smoke-scale pipeline tests: demonstrations, then a short training."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import yaml

from cgail_learning import demos_cli, train


def demos_and_training(root: Path, demos_args: Sequence[str], preset: dict[str, Any],
                       train_args: Sequence[str] = ()) -> Path:
    """``make_demos DEMOS_ARGS --out ROOT/demos``, then ``train`` of ``preset`` (written to
    ``ROOT/tiny.yaml``) on them into ``ROOT/run``; returns ``root``."""
    torch.set_num_threads(1)
    assert demos_cli.main([*demos_args, '--out', str(root / 'demos')]) == 0
    path = root / 'tiny.yaml'
    path.write_text(yaml.safe_dump(preset))
    assert train.main(['--preset', str(path), '--demos', str(root / 'demos'),
                       '--out', str(root / 'run'), '--no-progress', *train_args]) == 0
    return root
