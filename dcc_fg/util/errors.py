"""Errors that the command line turns into one-line messages.

:class:`EstimatorError` names the stage of a pipeline that failed and a hint for the user. Estimator
code wraps its numerical stages in :func:`stage`, which converts the numerical exceptions of gtsam
(``RuntimeError``, e.g. ``IndeterminantLinearSystemException``) and numpy (``LinAlgError``) into an
``EstimatorError``; every other exception (a programming error) passes through unchanged, so it is
never relabelled as a problem with the user's input.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

NUMERICAL_ERRORS: tuple[type[BaseException], ...] = (RuntimeError, np.linalg.LinAlgError)


class EstimatorError(RuntimeError):
    """A numerical stage of an estimator failed. ``stage`` says which, ``hint`` what to try."""

    def __init__(self, stage: str, message: str, hint: str = "") -> None:
        self.stage = stage
        self.hint = hint
        self.detail = message
        text = f"{stage} failed: {message}"
        if hint:
            text += f" (hint: {hint})"
        super().__init__(text)


@contextmanager
def stage(name: str, hint: str = "") -> Iterator[None]:
    """Run a block as the stage ``name``; gtsam/numpy numerical failures become :class:`EstimatorError`.

    An ``EstimatorError`` raised inside keeps its own (innermost) stage.
    """
    try:
        yield
    except EstimatorError:
        raise
    except NUMERICAL_ERRORS as exc:
        message = " ".join(str(exc).split()) or type(exc).__name__
        raise EstimatorError(name, message, hint) from exc
