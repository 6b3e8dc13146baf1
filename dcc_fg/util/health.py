"""Result health checks: every estimator judges its own result before anything is written.

A :class:`HealthCheck` is one test of a result against the noise model or a physical limit (for
example "calibration residual RMS against the corner noise floor": a chi-square test). A
:class:`HealthReport` gathers the checks of one run. A command that gets an unhealthy report raises
:class:`UnhealthyResultError` (the command line exits with :data:`EXIT_UNHEALTHY` and prints every
failed check with what to try) unless the user passed ``--accept-unhealthy``; then the outputs are
written and ``summary.json`` carries ``health: {healthy: false, failures: [...]}``.

Thresholds are derived from the noise model (chi-square quantiles at a small false-alarm
probability, physical ranges of the sensors), never tuned to examples; every check records the
value it measured and the threshold it compared against, so a user can see how close a run was.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from dcc_fg.util.errors import EstimatorError

#: Exit code of a command whose result failed a health check (bad input / numerical failure: 2;
#: interrupted by Ctrl-C: 130).
EXIT_UNHEALTHY = 3

#: False-alarm probability of the chi-square tests of a correct run (per test).
FALSE_ALARM_PROBABILITY = 1e-6


@dataclass(frozen=True)
class HealthCheck:
    """One test of a result.

    Attributes:
        name: short identifier, e.g. ``residuals.dynamic`` or ``convergence``.
        passed: whether the result passed.
        message: what was measured, in words with units (shown when the check fails).
        hint: what to try when it failed (empty when passed).
        value: the measured statistic (None when not numeric).
        threshold: the limit it was compared against (None when not numeric).
        severity: ``error`` (a failure makes the result unhealthy) or ``warning`` (a failure is
            reported and recorded but the result stays usable, e.g. a few outlier snapshots).
    """

    name: str
    passed: bool
    message: str
    hint: str = ""
    value: float | None = None
    threshold: float | None = None
    severity: str = "error"

    def __post_init__(self) -> None:
        if self.severity not in ("error", "warning"):
            raise ValueError(f"health check severity must be error or warning, got {self.severity!r}")

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "passed": bool(self.passed), "message": self.message}
        if self.severity != "error":
            out["severity"] = self.severity
        if self.hint:
            out["hint"] = self.hint
        if self.value is not None:
            out["value"] = float(self.value)
        if self.threshold is not None:
            out["threshold"] = float(self.threshold)
        return out


@dataclass
class HealthReport:
    """The health checks of one run (``subject``: e.g. ``calibration`` or ``trajectory``)."""

    subject: str
    checks: list[HealthCheck] = field(default_factory=list)

    def add(self, check: HealthCheck) -> HealthCheck:
        self.checks.append(check)
        return check

    def extend(self, checks: Iterable[HealthCheck]) -> None:
        self.checks.extend(checks)

    @property
    def failures(self) -> list[HealthCheck]:
        """Failed checks of severity ``error``: any of them makes the result unhealthy."""
        return [c for c in self.checks if not c.passed and c.severity == "error"]

    @property
    def warnings(self) -> list[HealthCheck]:
        """Failed checks of severity ``warning``: reported, the result stays healthy."""
        return [c for c in self.checks if not c.passed and c.severity == "warning"]

    @property
    def healthy(self) -> bool:
        return not self.failures

    def to_dict(self) -> dict[str, Any]:
        """The ``health`` block of ``summary.json``."""
        return {
            "healthy": self.healthy,
            "failures": [f"{c.name}: {c.message}" for c in self.failures],
            "warnings": [f"{c.name}: {c.message}" for c in self.warnings],
            "checks": [c.to_dict() for c in self.checks],
        }

    def failure_text(self) -> str:
        """Every failed check on one line each: what is wrong, then what to try."""
        lines = []
        for c in self.failures:
            line = f"  - {c.name}: {c.message}"
            if c.hint:
                line += f" (try: {c.hint})"
            lines.append(line)
        return "\n".join(lines)


class UnhealthyResultError(EstimatorError):
    """The run finished but its result failed health checks; nothing was written."""

    def __init__(self, report: HealthReport) -> None:
        self.report = report
        n = len(report.failures)
        message = (
            f"the {report.subject} failed {n} health check{'s' if n != 1 else ''}; nothing was written "
            "(rerun with --accept-unhealthy to write it anyway, marked healthy: false):\n" + report.failure_text()
        )
        super().__init__(f"{report.subject} health check", message)
