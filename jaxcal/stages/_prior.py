"""A fleet's prior in a point fit (`jaxcal.fleet`): its rows over the fit's vector, and what it gave
the fit and how far the data alone lie from it (`PriorUse`)."""

import jax
import numpy as np

from .._kinematics import KinematicModel
from .._pointfit import PointFitResult, PointLayout, PointProblem
from ..fleet_prior import model_digest, prior_rows
from ..records import PriorUse
from ._setup import Options


def prior_rows_of(options: Options, layout: PointLayout, nominal: KinematicModel, frame_free: bool):
    """The fleet's prior (`options.prior`) over `layout`'s vector (`jaxcal.fleet.prior_rows`), or None."""
    if options.prior is None:
        return None
    return prior_rows(options.prior, layout.names(), nominal.joint_names, model_digest(nominal), frame_free)


def prior_use(options: Options, problem: PointProblem, fit: PointFitResult, names, alone) -> PriorUse | None:
    """How much the fleet's prior gave each parameter it covers (the diagonal of the posterior
    covariance times the prior's precision, said in a line), and how far the data alone (`alone()`:
    the same fit without the prior) lie from it; None without a prior.

    The data's distance is taken where the data alone estimate a parameter: `(x - m)^T (S + D)^-1 (x - m)`,
    chi-square under a unit of the fleet (`x`, `D`: the data-alone fit and its covariance; `m`, `S`:
    the prior's mean and covariance). The posterior's own distance, in `S - C` (`C` the posterior's
    covariance), is the same number only for a linear model fitted exactly: where the data barely add
    to the prior, `S - C` is nearly singular, and the fit's round-off and curvature read as a conflict
    the data alone do not have."""
    prior = options.prior
    if prior is None:
        return None
    U = np.asarray(problem.prior.root) * np.asarray(fit.free)[None, :]
    idx = [names.index(n) for n in prior.names]
    share = np.diag(np.asarray(fit.cov) @ (U.T @ U))[idx]
    data = jax.device_get(alone())
    seen = np.asarray(data.free)[idx]
    d = np.asarray(data.x)[idx][seen] - prior.mean[seen]
    V = prior.covariance[np.ix_(seen, seen)] + np.asarray(data.cov)[np.ix_(idx, idx)][np.ix_(seen, seen)]
    z = np.full(len(idx), np.nan)
    z[seen] = d / np.sqrt(np.diag(V))
    options.say(
        f"point fit: the fleet's prior ({prior.units} units) gave {np.mean(share):.0%} of its "
        f"{len(share)} parameters' information on average"
    )
    return PriorUse(
        file=prior.file,
        units=prior.units,
        names=tuple(prior.names),
        share=tuple(float(v) for v in share),
        mean=np.asarray(prior.mean),
        covariance=np.asarray(prior.covariance),
        z=tuple(float(v) for v in z),
        chi2=float(d @ np.linalg.solve(V, d)) if d.size else 0.0,
        dof=int(d.size),
    )
