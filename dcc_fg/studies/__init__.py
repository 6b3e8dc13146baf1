"""Studies: the estimators run on simulated data and compared against the simulator's ground truth.

:mod:`dcc_fg.studies.calibration_accuracy`: gauge-invariant errors of a calibration and its Cramer-Rao bound;
:mod:`dcc_fg.studies.vio_study`: the tracks-level dcc / scc / mono VIO comparison on a simulated flight.
This layer sits above the estimators and :mod:`dcc_fg.sim` and below ``report``/``plots`` (docs/architecture.md).
"""
