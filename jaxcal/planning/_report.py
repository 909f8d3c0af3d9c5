"""What `jaxcal plan --evaluate` shows: the prediction as rows, and a plot of the EE sigma over the workspace."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._correction import zero_correction
from .._uncertainty import tool_points
from ..io._files import atomic_file
from ._evaluate import PlanEvaluation
from ._scene import PlanScene


def parameter_rows(ev: PlanEvaluation, top: int | None = None) -> list[tuple[str, str]]:
    """`(name, predicted 1-sigma with unit)` of every free parameter (largest first with `top`)."""
    rows = []
    for name, f, s in zip(ev.names, ev.free, ev.std):
        if not f:
            continue
        last = name.rsplit(".", 1)[-1]
        if last in ("tx", "ty", "tz"):
            rows.append((name, s, f"{1e3 * s:.4f} mm"))
        elif last in ("rx", "ry", "rz") or name.endswith("zero_offset"):
            rows.append((name, s, f"{np.degrees(s):.5f} deg"))
        elif name.endswith(".rate"):
            rows.append((name, s, f"{1e2 * s:.5f} %"))
        else:
            rows.append((name, s, f"{s:.4g}"))
    if top is not None:
        rows = sorted(rows, key=lambda r: -r[1])[:top]
    return [(n, text) for n, _, text in rows]


def workspace_points(scene: PlanScene, configs) -> np.ndarray:
    """The EE point (base frame, m) at every workspace configuration."""
    n = scene.nominal.num_joints
    f = jax.jit(
        lambda q: tool_points(
            scene.nominal, jnp.eye(4), scene.T_mount[None], jnp.zeros(6), zero_correction(n, 1), q
        )
    )
    return np.asarray(f(jnp.asarray(configs)))


def plot_evaluation(ev: PlanEvaluation, scene: PlanScene, configs, path, title: str = "") -> Path:
    """Predicted EE error across the workspace: top view and side view of the EE points coloured
    by it (mm), and its histogram; written to `path` (PNG). With an arm model (`ev.ee_bias`) the
    maps show the whole error, noise and the arm's bias together (the bias usually dominates), and
    the histogram each part and the total; without one, the noise's 1-sigma."""
    p = workspace_points(scene, configs)
    sigma = 1e3 * np.asarray(ev.ee_sigma)
    biased = ev.ee_bias.size > 0
    s = 1e3 * np.asarray(ev.ee_total) if biased else sigma
    what = "predicted EE error, noise and the arm's bias (mm)" if biased else "predicted EE 1-sigma (mm)"
    from matplotlib.figure import Figure  # only when a report is drawn: importing jaxcal stays light

    fig = Figure(figsize=(15, 4.6), layout="constrained")  # no pyplot: no global state, any backend
    ax = fig.subplots(1, 3)
    vmin, vmax = (float(v) for v in np.percentile(s, [1, 99]))  # the spread, not the distance from 0
    for a, (i, j), lab in zip(ax[:2], ((0, 1), (0, 2)), (("x m", "y m"), ("x m", "z m"))):
        sc = a.scatter(p[:, i], p[:, j], c=s, s=6, cmap="viridis", vmin=vmin, vmax=vmax)
        a.set_xlabel(lab[0])
        a.set_ylabel(lab[1])
        a.set_aspect("equal")
    fig.colorbar(sc, ax=ax[:2], label=what)
    if biased:
        bins = np.linspace(0.0, float(np.max(s)), 41)
        parts = (
            (sigma, "#4060a0", "noise 1-sigma", ev.ee_rms),
            (1e3 * ev.ee_bias, "#d08020", "arm's bias", ev.ee_bias_rms),
        )
        for values, colour, name, rms in parts:
            ax[2].hist(values, bins=bins, color=colour, alpha=0.7, label=f"{name}, RMS {1e3 * rms:.3f} mm")
        total = 1e3 * ev.ee_total_rms
        ax[2].axvline(total, color="k", ls="--", label=f"total RMS {total:.3f} mm")
        ax[2].set_xlabel("predicted EE error (mm)")
    else:
        ax[2].hist(s, bins=40, color="#4060a0")
        ax[2].axvline(1e3 * ev.ee_rms, color="k", ls="--", label=f"RMS {1e3 * ev.ee_rms:.3f} mm")
        ax[2].axvline(1e3 * ev.ee_p95, color="r", ls=":", label=f"p95 {1e3 * ev.ee_p95:.3f} mm")
        ax[2].set_xlabel("predicted EE 1-sigma (mm)")
    ax[2].legend()
    fig.suptitle(
        title or f"{ev.frames} frames, sigma {ev.sigma_px:g} px: predicted EE error over the workspace"
    )
    path = Path(path)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    return path
