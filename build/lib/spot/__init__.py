"""spot: offline preference-based RL with attention-guided subgoals (SPOT) and its baselines.

Importing ``spot`` (or any of its modules) changes nothing in the process: the XLA flag and the
``MUJOCO_GL`` default that spot needs are set by an explicit :func:`spot.runtime.configure` call,
which the ``spot`` command, sweep trials and the tests make first.
"""

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
