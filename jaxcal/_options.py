"""The fits' options as objects, and the one mapping of the keywords they replaced.

Every public fit takes the solver's settings as `options: LMOptions`
(`jaxcal._lsq.LMOptions`: `rtol`, `atol`, `max_steps`) and, where it can
down-weight outliers, the loss as `robust: RobustOptions | None` (`None`: plain
least squares). Each fit's signature shows its own defaults (a fit on whitened
residuals stops at a coarser `atol` than one in metres).

The keywords these replaced (`rtol=`, `atol=`, `max_steps=`; `loss=`, `c=`,
`reject=`, `rounds=`) still work for one release: `fit_options` maps them onto
the objects and warns with a `DeprecationWarning` naming the replacement, as
`calibrate(clock=...)` did for `estimate_clock` and `trust_clock`.
"""

import dataclasses
import warnings

import equinox as eqx

from ._lsq import LMOptions
from ._robust import check_loss

#: The keywords of `LMOptions` and of `RobustOptions` that fits used to take one by one.
LM_KEYWORDS = ("rtol", "atol", "max_steps")
ROBUST_KEYWORDS = ("loss", "c", "reject", "rounds")


class RobustOptions(eqx.Module):
    """Iteratively reweighted least squares with a robust loss, then an inlier solve.

    `rounds` solves, each reweighting the samples by `loss` (`"cauchy"` or
    `"huber"`) of their residuals in robust standard deviations with constant `c`;
    then, with `reject` (a radius in robust sigmas; `None`: none), one solve on
    the samples within `reject` (weight 1, the others 0), whose Jacobian gives
    honest standard deviations. `reject = 3.7` drops a clean sample with
    probability $e^{-3.7^2/2} \\approx 10^{-3}$ (see `jaxcal._robust`).
    """

    loss: str = eqx.field(static=True, default="cauchy")
    c: float = 3.0
    reject: float | None = 3.7
    rounds: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        if self.loss is None:
            raise ValueError(
                "RobustOptions: loss must be 'cauchy' or 'huber' (plain least squares: robust=None)"
            )
        check_loss(self.loss)
        if self.rounds < 1:
            raise ValueError(f"RobustOptions: rounds must be at least 1, got {self.rounds}")


def robust_terms(robust: RobustOptions | None) -> tuple:
    """`(loss, c, reject, rounds)` of `robust`; `None`: one plain least-squares round."""
    if robust is None:
        return None, 3.0, None, 1
    return robust.loss, robust.c, robust.reject, robust.rounds


def fit_options(
    fit: str,
    options: LMOptions,
    robust: RobustOptions | None,
    old: dict,
    *,
    robust_fit: bool = True,
) -> tuple[LMOptions, RobustOptions | None]:
    """`options` and `robust` with the deprecated keywords `old` of `fit` applied.

    `rtol`, `atol`, `max_steps` replace those fields of `options`; `loss`, `c`,
    `reject`, `rounds` (for a fit with a robust loss, `robust_fit`) those of
    `robust` (`None`, plain least squares, stays so unless `loss` names a loss;
    `loss=None` means plain least squares as before). Any other keyword is the
    `TypeError` Python would raise.
    """
    if not old:
        return options, robust
    allowed = LM_KEYWORDS + (ROBUST_KEYWORDS if robust_fit else ())
    unknown = [k for k in old if k not in allowed]
    if unknown:
        raise TypeError(f"{fit}() got an unexpected keyword argument {unknown[0]!r}")
    lm = {k: old[k] for k in LM_KEYWORDS if k in old}
    rob = {k: old[k] for k in ROBUST_KEYWORDS if k in old}
    replacement = " and ".join(
        f"{name}({', '.join(f'{k}=...' for k in keys)})"
        for name, keys in (("options=LMOptions", lm), ("robust=RobustOptions", rob))
        if keys
    )
    warnings.warn(
        f"{fit}({', '.join(f'{k}=' for k in old)}) is deprecated and will be removed in the next "
        f"release: pass {replacement}",
        DeprecationWarning,
        stacklevel=3,
    )
    options = dataclasses.replace(options, **lm) if lm else options
    if rob:
        loss = rob.pop("loss", robust.loss if robust is not None else None)
        if loss is None:  # plain least squares, as before: c, reject and rounds never applied
            robust = None
        else:
            robust = dataclasses.replace(robust if robust is not None else RobustOptions(), loss=loss, **rob)
    return options, robust
