"""The error of a diverged run: :class:`NotFinite`, raised when the loss, weights or descriptors become NaN or inf."""
from __future__ import annotations


class NotFinite(ValueError):
    """Training diverged: ``what`` (the loss, the weights, the descriptors) became NaN or inf. Raised by the
    sources and :func:`train_epoch`, which names the step and the learning rate."""

    def __init__(self, what: str, value: str = "NaN or inf"):
        super().__init__(f"the {what} became {value}")
        self.what, self.value = what, value
