"""A fleet's prior in a point fit (`jaxcal.fleet`): its rows over the fit's vector, and what it gave
the fit and how far the data alone lie from it (`PriorUse`)."""

import jax
import numpy as np

from .. import _distributions as distributions
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


#: The chance that a unit of the fleet has a parameter called contradicting the fleet's prior.
PRIOR_FALSE_ALARM = 0.01


def prior_row(prior: PriorUse):
    """The verdict's check of a fleet's prior the data contradict, `(name, value, limit, reason)`
    (None without one): the data alone farther from the fleet's mean, over the parameters they
    estimate together (`PriorUse.chi2`), than a unit of that fleet lies with chance
    `PRIOR_FALSE_ALARM`: the unit is not of that fleet, or the prior is not its model's or claims
    more than the fleet knows (a reason: the result leans on a wrong prior). The parameter named is
    the one farthest on its own (`PriorUse.z`)."""
    if not prior.dof:
        return None
    z = np.abs(np.nan_to_num(np.asarray(prior.z, np.float64), nan=0.0))
    limit = float(distributions.chi2_ppf(1.0 - PRIOR_FALSE_ALARM, prior.dof))
    worst = int(np.argmax(z))
    return (
        "point_fit.prior_chi2",
        float(prior.chi2),
        limit,
        f"the data contradict the fleet's prior ({prior.file}): over the {prior.dof} parameters the data alone "
        f"estimate, they lie chi2 = {prior.chi2:.1f} from the fleet's mean (at most {limit:.1f} for a unit of "
        f"that fleet, {100 * PRIOR_FALSE_ALARM:g} % false alarms), farthest {prior.names[worst]} at "
        f"{z[worst]:.1f} standard deviations; the unit is not like the fleet's, or the prior is another "
        "model's or claims too much: calibrate it without --prior",
    )
