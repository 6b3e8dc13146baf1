"""Degenerate and nearly degenerate mechanisms: directions the data do not determine, held by priors.

The gauge rules of :mod:`dcc_fg.calibrate` remove the directions that are unobservable for *every*
mechanism. Some mechanisms leave more: a gimbal whose three axes intersect in one point (a
spherical wrist, the usual yaw-roll-pitch camera gimbal) reproduces any set of rotations with any
axes, so only the wrist centre (in s and in d) and the per-snapshot ``T_ds`` are determined, not
the axes, twists or link offsets; two intersecting axes leave one more direction. Such data are
calibrated, not refused: every direction of the kinematics that the data leave (numerically)
undetermined is held by a weak prior at its starting value (or at the nominal geometry the user
gave, ``--nominal``), and reported as held by prior.

Test. ``S`` is the information matrix of the free kinematic entries with the per-snapshot
variables (joint angles, target poses) eliminated (:func:`dcc_fg.covariance.information_schur`),
plus the nominal priors. In Jacobi-scaled coordinates (each parameter divided by its own data
1-sigma, so metres and radians compare) the gauge directions of the held joint-angle offsets
(``offset_directions``) are removed, and every eigenvector with an eigenvalue below
``REL_TOL`` times the largest is a held direction.

Prior. Along each held direction ``v`` (unit, scaled coordinates) the prior adds the information
``PRIOR_REL * w_max`` = the detection threshold: a direction the data determine better than that
is left to them, one they determine worse is held (its sigma is ~1/sqrt(PRIOR_REL) = 6000 times a
parameter's data-alone 1-sigma); the parameters it moves are reported as not determined by the data.
The marginals of such a system are too ill-conditioned for GTSAM's Cholesky;
:func:`dcc_fg.covariance.dense_covariances` takes over.
The held directions leave every snapshot's ``T_ds(theta_i)`` unchanged to first order (the joint
angles follow them), so the per-snapshot result and its covariance do not depend on the prior;
the kinematic parameters involved and the joint angles do, and are reported as such.

Nominal geometries (``--nominal``; the DH convention of :mod:`factors.chain`, links l < L, since
the last link's d, a, alpha are gauge-fixed):

* ``intersecting``: consecutive axes intersect: ``a_l = 0`` (l < L) and ``d_l = 0`` (2 <= l < L)
  with a 1-sigma of ``NOMINAL_OFFSET_SIGMA``;
* ``exactly-intersecting``: the same offsets held at zero with a 1-sigma of ``EXACT_OFFSET_SIGMA``
  (1 micrometre: the intersecting model itself, e.g. a spherical wrist; :mod:`dcc_fg.model_selection`
  tries it automatically);
* ``orthogonal``: consecutive axes are perpendicular: ``|alpha_l| = 90 deg`` (sign of the start)
  with a 1-sigma of ``NOMINAL_TWIST_SIGMA``;
* ``yaw-roll-pitch`` / ``pan-tilt-roll`` / ``pan-tilt``: both (the usual camera gimbals).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors import chain
from factors.calibration import linear_prior_factor

FloatArray = NDArray[np.float64]
# Relative eigenvalue of the scaled information below which a direction is held. At the truth, exactly
# undetermined directions sit at round-off (<= 2e-16 on spherical wrists); at a start the pose-level fit
# has moved along them they rise to 6e-10..5e-7 (no gap); the weakest direction the data determine in
# the pinned L = 3 scene (links offset by 5-12 cm) is at 7e-8. The prior along a held direction has the
# same information as the threshold, so it never dominates a direction the data determine better than
# that (a prior of 1e-4 on the pinned scene's 7e-8 direction pulled its twists to the start, past the
# joint-angle bound).
REL_TOL = 3e-8
PRIOR_REL = REL_TOL
INVOLVED = 0.2  # |component| of a held direction (unit, scaled) for a parameter to be named
NOMINAL_OFFSET_SIGMA = 0.005  # m
NOMINAL_TWIST_SIGMA = np.deg2rad(2.0)  # rad
EXACT_OFFSET_SIGMA = 1e-6  # m, the offsets of ``exactly-intersecting`` (a constraint, not a preference)
EXACT = "exactly-intersecting"  # the nominal of the intersecting model itself (dcc_fg.model_selection keeps it)
NOMINALS = ("intersecting", EXACT, "orthogonal", "yaw-roll-pitch", "pan-tilt-roll", "pan-tilt")


@dataclass
class HeldDirections:
    """Directions of the free kinematic entries held by the weak prior.

    Attributes:
        W: (k, n_free) whitened prior rows (residual ``W (x - x0)``), empty when k = 0.
        x0: (n_free,) the values the directions are held at.
        directions: (k, n_free) unit directions in Jacobi-scaled coordinates.
        scale: (n_free,) the Jacobi scale (data 1-sigma of each free entry alone is 1/scale).
        names: names of the free entries.
        nominal: (index into the free entries, value, sigma) of the nominal-geometry priors.
    """

    W: FloatArray
    x0: FloatArray
    directions: FloatArray
    scale: FloatArray
    names: list[str]
    nominal: list[tuple[int, float, float]] = field(default_factory=list)

    @property
    def count(self) -> int:
        return int(self.W.shape[0])

    def involved(self) -> NDArray[np.bool_]:
        """Per free entry: moved by some held direction."""
        if self.count == 0:
            return np.zeros(len(self.names), dtype=bool)
        return np.max(np.abs(self.directions), axis=0) > INVOLVED

    def factors(self, key: int, weakening: float = 1.0) -> list[gtsam.CustomFactor]:
        """The weak prior on the held directions (its 1-sigma times ``weakening``) and the nominal
        priors, on the free-kinematics key."""
        out = [linear_prior_factor(key, self.W / weakening, self.x0)] if self.count else []
        return out + self.nominal_factors(key)

    def nominal_factors(self, key: int) -> list[gtsam.CustomFactor]:
        """The nominal-geometry priors alone (none without ``--nominal``), on the free-kinematics key."""
        if not self.nominal:
            return []
        rows = np.zeros((len(self.nominal), len(self.names)))
        target = self.x0.copy()
        for r, (i, value, sigma) in enumerate(self.nominal):
            rows[r, i] = 1.0 / sigma
            target[i] = value
        return [linear_prior_factor(key, rows, target)]

    def report(self) -> list[dict[str, Any]]:
        """Plain-data description of each held direction (for ``calibration.yaml``): the parameters
        it moves (largest first), its unit direction in scaled coordinates, the values it is held at,
        and the prior's 1-sigma along it expressed in each parameter's unit (rad or m)."""
        out = []
        for v, w in zip(self.directions, self.W, strict=True):
            order = [int(i) for i in np.argsort(-np.abs(v)) if abs(v[i]) > INVOLVED]
            weight = float(np.linalg.norm(w / self.scale[None, :])) if np.any(w) else 0.0  # sqrt(prior information)
            sigma_scaled = 1.0 / weight if weight > 0 else float("inf")
            out.append(
                {
                    "parameters": [self.names[i] for i in order],
                    "direction": {self.names[i]: round(float(v[i]), 4) for i in order},
                    "held_at": {self.names[i]: float(self.x0[i]) for i in order},
                    "prior_sigma": {self.names[i]: float(sigma_scaled * abs(v[i]) / self.scale[i]) for i in order},
                }
            )
        return out

    def plain_words(self) -> str:
        """One sentence per held direction for the user."""
        if self.count == 0:
            return ""
        names = sorted({n for d in self.report() for n in d["parameters"]}, key=self.names.index)
        return (
            f"the data do not determine {self.count} combination(s) of the kinematic parameters "
            f"({', '.join(names)}): they are held by a weak prior at their starting values (see held_by_prior in "
            "calibration.yaml). Every snapshot's T_ds is still determined by the images; these parameters and "
            "the joint angles depend on the prior. A mechanism whose axes (nearly) intersect behaves like this; "
            "give --nominal (e.g. yaw-roll-pitch) to hold them at the nominal geometry instead"
        )


def offset_directions(kin: FloatArray, n_joints: int, offsets: list[int]) -> FloatArray:
    """(n_kin, len(offsets)) kinematic directions that absorb a constant offset of the held joints.

    Only the last joint's offset is held in encoderless mode: ``theta_L + e`` is absorbed by the
    end mount, ``T_de' = T_de inv(M_L) Rz(e) M_L`` with ``A_L = Rz(theta_L) M_L``
    (:mod:`factors.chain`), so the direction is d tau_d / d e (central difference)."""
    out = np.zeros((chain.n_kin(n_joints), len(offsets)))
    for c, j in enumerate(offsets):
        if j != n_joints - 1:
            continue
        d, a, alpha = np.asarray(kin, float)[12 + 3 * j : 15 + 3 * j]
        M = _tz(d) @ _tx(a) @ _rx4(alpha)
        M_inv = chain.inv_se3(M)
        T_de = chain.se3_from_tau(kin[6:12])
        h = 1e-6
        plus = chain.tau_from_se3(T_de @ M_inv @ _rz4(h) @ M)
        minus = chain.tau_from_se3(T_de @ M_inv @ _rz4(-h) @ M)
        out[6:12, c] = (plus - minus) / (2.0 * h)
    return out


def offset_entries(n_joints: int) -> list[int]:
    """Indices into the kinematic vector of the link offsets that intersecting axes zero:
    ``a_l`` (l < L) and ``d_l`` (2 <= l < L), ascending."""
    out = []
    for link in range(n_joints - 1):  # l < L (0-based link < L - 1)
        base = 12 + 3 * link
        if link >= 1:
            out.append(base)  # d_l
        out.append(base + 1)  # a_l
    return out


def nominal_priors(
    nominal: str | None, kin: FloatArray, n_joints: int, free: NDArray[np.bool_]
) -> list[tuple[int, float, float]]:
    """(index into the free entries, value, sigma) of the nominal-geometry priors (module docstring)."""
    if nominal is None:
        return []
    if nominal not in NOMINALS:
        raise ValueError(f"--nominal must be one of {', '.join(NOMINALS)}, got '{nominal}'")
    free_index = {int(k): i for i, k in enumerate(np.flatnonzero(free))}
    entries: list[tuple[int, float, float]] = []
    if nominal != "orthogonal":
        sigma = EXACT_OFFSET_SIGMA if nominal == EXACT else NOMINAL_OFFSET_SIGMA
        entries += [(k, 0.0, sigma) for k in offset_entries(n_joints)]
    if nominal not in ("intersecting", EXACT):
        for link in range(n_joints - 1):  # l < L (0-based link < L - 1)
            alpha = 12 + 3 * link + 2
            sign = 1.0 if np.sin(kin[alpha]) >= 0 else -1.0
            entries.append((alpha, sign * np.pi / 2.0, NOMINAL_TWIST_SIGMA))
    return [(free_index[k], v, s) for k, v, s in entries if k in free_index]


def held_directions(
    S_full: FloatArray,
    kin: FloatArray,
    n_joints: int,
    fixed: NDArray[np.bool_],
    offsets: list[int],
    nominal: str | None = None,
    scale: FloatArray | None = None,
) -> HeldDirections:
    """The directions of the free kinematic entries that the data (information ``S_full`` of the
    full kinematic vector, per-snapshot variables eliminated) and the nominal priors leave
    undetermined, beyond the gauge; see the module docstring. ``scale``: the square root of the
    diagonal of the information before the elimination (the Jacobi scale; without it the diagonal of
    ``S_full``, which vanishes along the eliminated directions)."""
    free = ~np.asarray(fixed, dtype=bool)
    names = [n for n, f in zip(chain.kin_names(n_joints), free, strict=True) if f]
    x0 = np.asarray(kin, float)[free].copy()
    nominal_entries = nominal_priors(nominal, kin, n_joints, free)
    S = S_full[np.ix_(free, free)].copy()
    for i, _, sigma in nominal_entries:
        S[i, i] += 1.0 / sigma**2
    S = 0.5 * (S + S.T)
    if scale is not None:  # the information before elimination (dcc_fg.covariance.information_schur)
        d = np.sqrt(np.asarray(scale, float)[free] ** 2 + np.diag(S) - np.diag(S_full)[free])
    else:
        d = np.sqrt(np.maximum(np.diag(S), 0.0))
    d = np.where(d > 1e-150, d, 1.0)
    Sn = S / np.outer(d, d)
    w_max = float(np.max(np.linalg.eigvalsh(Sn)))
    G = offset_directions(kin, n_joints, offsets)[free] * d[:, None]
    for c in range(G.shape[1]):
        norm = np.linalg.norm(G[:, c])
        if norm > 0:
            g = G[:, c] / norm
            Sn = Sn + w_max * np.outer(g, g)
    w, V = np.linalg.eigh(Sn)
    held = V[:, w < REL_TOL * w_max].T  # (k, n_free)
    weight = np.sqrt(PRIOR_REL * w_max)
    W = weight * held * d[None, :]
    return HeldDirections(W, x0, held, d, names, nominal_entries)


def _tz(d: float) -> FloatArray:
    T = np.eye(4)
    T[2, 3] = d
    return T


def _tx(a: float) -> FloatArray:
    T = np.eye(4)
    T[0, 3] = a
    return T


def _rx4(alpha: float) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = chain.rot_x(alpha)
    return T


def _rz4(angle: float) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = chain.rot_z(angle)
    return T
