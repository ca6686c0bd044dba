"""spot: offline preference-based RL with attention-guided subgoals (SPOT) and its baselines.

Importing ``spot`` sets one XLA flag before jax is imported (if jax is not imported yet): jaxlib
0.10.2 on CPU crashes in transformer training at batch 256 with ``YNNPACK operation failed`` unless
the YNN reduce fusion is turned off (see docs/install.md). Nothing else happens at import.
"""

import os as _os

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type=-LIBRARY_FUSION_TYPE_REDUCE"
if _YNN_FLAG not in _os.environ.get("XLA_FLAGS", ""):
    _os.environ["XLA_FLAGS"] = (_os.environ.get("XLA_FLAGS", "") + " " + _YNN_FLAG).strip()

__version__ = "0.1.0"


class SpotError(Exception):
    """A user error (bad file, key, value). The CLI prints the message and exits with code 2."""


class NonFiniteError(RuntimeError):
    """A training loss became NaN or inf. The run stops and is marked failed with step and loss name."""

    def __init__(self, step: int, loss_name: str, value: float = float("nan")) -> None:
        super().__init__(f"non-finite loss '{loss_name}' = {value} at step {step}")
        self.step = step
        self.loss_name = loss_name
        self.value = value
