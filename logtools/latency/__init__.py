"""Latency (and clock drift) of the slave unit behind the master, from angular rate (and velocity).

``estimate(master, slave, config=LatencyConfig())`` returns a :class:`~logtools.results.LatencyResult`
whose ``latency_s`` follows DESIGN.md: positive when the slave's stamps are late. Model (both units on
the master's relative clock)::

    w_slave(t + d(t)) = R w_master(t) + b + noise,    d(t) = L + drift * (t - t_mid)

R the unknown relative mounting (any rotation), b the gyro bias difference, L the latency at the middle
``t_mid`` of the analysed window, ``drift`` the relative clock rate (``drift_ppm`` = drift * 1e6).

Map: the stages in the order they run, each a function from frozen inputs to a frozen result
(``estimator.tapost`` calls them in this order; nothing is mutated in place, warnings are returned)

====================  ====================================================================================
module                open it to change
====================  ====================================================================================
``config``            any tuning number or switch (``LatencyConfig``, one section per stage below);
                      ``Stages``: replace a refinement function (ablations, tests)
``methods``           the method names (``Method``, ``METHODS``) and the seeds' methods' dispatch
``inputs``            how a unit's angular rate is obtained (gyro, attitude + earth/transport rate), its
                      noise level and motion band, the motion check's figures
``prepare``           grids, the common low-pass cutoff, stamp statistics, which sources are used (``Ctx``)
``spikes``            one unit's isolated IMU samples that the other unit does not show at the coarse lag
                      (corrupt values), replaced for the fit and said (``estimator.despiked``)
``coarse``            the integer-lag search: |w| cross-correlation ("xcorr-norm"), the rotation-solved
                      full-vector cost, periodic alternatives, a window's own search
``fit``               the delay problem (``Fit``, Jacobian, residuals) and the first Gauss-Newton fit
``system``            the whitened fits' joint system, accelerometer rows (``Accel``)
``gls``               residual spectra, whitening, HAC; ``gls_covariance``: every fit's covariance
``refine``            refinement stages: the spectral GLS and the accelerometer-aided passes
``kalman``            the Kalman flexure-model refinement and the one "is this flexure?" criterion
                      (``flexure_like``)
``flexure``           the flexure state-space model, its Kalman whitening kernel (numba) and likelihood
``windows``           drift windows, their line, the joint (L, drift) fit, the windows' check of a sigma
``candidates``        the refinement candidates over the whole overlap (spectral GLS, aided, Kalman) and
                      the choice between them (``fit_all``)
``velocity_pair``     the units' velocities for matching, grids, frame rotation
``velocity``          the velocity-matched (L, drift) fit
``fusion``            velocity and rate fits fused; periodic alternatives tried on the velocities
``uncertainty``       every term of ``sigma_s`` (``SigmaBudget``: report.json ``latency.quality.sigma_budget``)
``quality``           the ``quality`` record and the cost curve for the plots
``steps``             the clock-step check: one line against one line with an offset step
                      (``quality["clock_step"]``)
``estimator``         the order of the stages, the widened search, ``estimate``
====================  ====================================================================================

tapost's method: (0) each unit's rate on its own uniform grid, zero-phase low-passed at 3x the motion's
band (at least 4 Hz for the flexure fit, at most a fifth of the common rate); (0b) a sample of one unit far
off its neighbours with nothing alike in the other unit at the coarse lag replaced; (1) normalised
cross-correlation of |w| (candidates); (2) the rotation- and bias-solved vector cost at every integer lag
from 18 FFT correlations and a batched Wahba solution; (3) Gauss-Newton on the continuous delay (cubic
B-spline of the slave), R and b re-solved at each step, the delay's curvature from the cleaner unit's
derivative (``gls.delay_normal``); (3b) GLS: steps on the residual whitened by its estimated spectrum
(flexure is a coloured disturbance); (3c) accelerometer-aided GLS with a 6x6 cross-spectrum and a model
check of the accelerometers' own delay; (3d) Kalman whitening with seed 000's flexure model (restricted
maximum likelihood), the delay on the profile of the whitened cost; (4) drift windows along the overlap,
a weighted line, outliers rejected, the joint (L, drift) fit; (5) sigma: the fit's covariance with a HAC
floor, inflated by the windows' scatter, with the stamp grid, stamp jitter, drift prior, periodic
ambiguity and model floors (``uncertainty``); (5b) velocity matching (``velocity``), fused when it
agrees; (6) quality flags. Method details: docs/latency.md. The seeds' methods live in
``logtools.latency_seeds``.
"""
from __future__ import annotations

from logtools.latency.config import LatencyConfig, Stages
from logtools.latency.methods import METHODS, Method

__all__ = ["estimate", "METHODS", "Method", "LatencyConfig", "Stages", "rate_from_attitude"]

#: loaded on first use: the method table and the configuration alone stay light (the CLI's choices)
_LAZY = {"estimate": "logtools.latency.estimator", "rate_from_attitude": "logtools.latency.inputs"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'logtools.latency' has no attribute {name!r}")
