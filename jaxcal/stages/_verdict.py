"""Stage 7, verdict: the answer checked against physics before anyone trusts it.

A calibration engineer looks at a result before using it: are the
corrections within manufacturing tolerance, does the target's printed size
fit the arm's link lengths, are the residuals at the detector's noise, did
every solver converge, are self-calibrated intrinsics plausible. Each check
here is one of those, with its limit in `Limits` (documented defaults; pass
your own to `jaxcal.calibrate(limits=...)`). A result that fails one is
`status: "suspect"` with its reasons (the CLI exits 3); a solver that failed
makes it `"failed"`. What a user should know of a result that passes (samples
a robust fit set aside, parameters held because the data cannot see them) is
in its `notes`.
"""

from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import equinox as eqx
import numpy as np

from .._kinematics import PRISMATIC, joint_axes_at_zero
from ..io._tracker import DeviceInfo
from ..records import Judgement, ParameterRow
from ..records_stages import Check
from . import _programs
from ._armcheck import arm_check
from ._axes_check import axis_spacing_ratio, reach_rms, reversed_joints, spacing_limits
from ._blur import blur_rows
from ._observe import Observations
from ._prior import prior_row
from ._refine import Refined, succeeded
from ._setup import Setup
from ._synchronise import Sync
from ._terms import LAG
from ._timing import timing_checks
from ._two_stage import TwoStage, listed
from .limits import Limits


@dataclass(frozen=True)
class Verdict(Judgement):
    """`status` (`ok`, `suspect` or `failed`), the failed checks' `reasons` (`Judgement`, the
    shape hand-eye's verdict shares), every check with its value and limit (`checks`), and
    `notes`: what the user should know that does not make the result suspect (as hand-eye's)."""

    checks: tuple[Check, ...] = field(default_factory=tuple)
    notes: tuple[str, ...] = ()


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


#: The causes a failed check names, in the order its reason leads the others: they explain the
#: symptoms (corrections out of tolerance, large residuals) that follow them.
CAUSES = ("encoder_sense", "rolling_shutter", "camera_model", "timing", "blur", "arm", "correlated_errors")


class _Checks:
    def __init__(self):
        self.rows, self.symptoms, self.causes, self.notes = [], [], [], []

    def add(self, name: str, value: float, limit: float, message: str, cause: str | None = None) -> None:
        """A check row; a failed one's `message` is a reason, those naming a `cause` (`CAUSES`)
        first, in `CAUSES`' order."""
        ok = bool(np.isfinite(value) and value <= limit)
        self.rows.append(Check(name, float(value), float(limit), ok))
        if not ok:
            if cause is None:
                self.symptoms.append(message)
            else:
                self.causes.append((CAUSES.index(cause), len(self.causes), message))

    def also_from(self, cause: str, symptom: str, prefix: str) -> None:
        """Where a check naming `cause` failed, prefix the failed reasons naming `symptom` (a cause
        whose signs the first makes too: a slow encoder log's, read as a sagging arm's)."""
        if any(i == CAUSES.index(cause) for i, _, _ in self.causes):
            k = CAUSES.index(symptom)
            self.causes = [(i, n, prefix + m if i == k else m) for i, n, m in self.causes]

    @property
    def reasons(self) -> list[str]:
        return [m for _, _, m in sorted(self.causes)] + self.symptoms

    def at_least(self, name: str, value: float, limit: float) -> bool:
        """A check that `value` is at least `limit` (its reason is the caller's); whether it passed."""
        ok = bool(np.isfinite(value) and value >= limit)
        self.rows.append(Check(name, float(value), float(limit), ok))
        return ok


#: Stop-and-shoot samples scattering less than this fraction of the noise they state about the
#: calibrated model: the stated noise is wrong (a unit), not a good tracker.
QUIET_NOISE_SCALE = 0.1
#: A joint origin this many times past its limit suggests the wrong robot model, not a worn arm ...
WRONG_MODEL_FACTOR = 5.0
#: ... or, the first joint's with the device's frame given as the base, a device elsewhere.
BASE = "Calibrate without --device-is-base (the device's pose is then fitted)"


def _corrections(
    c: _Checks,
    parameters: tuple[ParameterRow, ...],
    limits: Limits,
    measured_mounts: set,
    base_given: str = "",
) -> None:
    """Joint origins, zero offsets and mounts against their nominal values; `base_given`: the first
    joint's origin (`NAME.origin`) when the device's frame was given as the robot's base, which
    takes up a device elsewhere."""
    rows = {p.name: p for p in parameters}
    groups: dict[str, dict] = {}
    for p in parameters:
        if p.group not in ("correction", "mount") or p.name.endswith(".zero_offset"):
            continue
        owner, _, what = p.name.rpartition(".")
        groups.setdefault(owner, {})[what] = p.estimate - p.nominal
    for owner, d in groups.items():
        mount = owner.endswith(".mount")
        if mount and owner.rpartition(".")[0] in measured_mounts:
            continue  # no nominal mount in the metadata: the measured one is the reference
        mm = 1e3 * float(np.linalg.norm([d.get(k, 0.0) for k in "xyz"]))
        deg = float(np.degrees(np.max(np.abs(_wrap([d.get(k, 0.0) for k in ("roll", "pitch", "yaw")])))))
        lim_mm, lim_deg = (
            (limits.mount_mm, limits.mount_deg) if mount else (limits.origin_mm, limits.origin_deg)
        )
        far = ""
        if not mount and mm > WRONG_MODEL_FACTOR * lim_mm:
            far = "; far beyond how much a real arm differs from its datasheet: is the robot model (URDF or DH table) "
            far += (
                "this arm's?"
                if owner != base_given
                else f"this arm's? Or is the device's frame not its base? {BASE}"
            )
        c.add(f"{owner}.mm", mm, lim_mm, f"{owner} moved {mm:.1f} mm from nominal (limit {lim_mm:g} mm){far}")
        c.add(
            f"{owner}.deg", deg, lim_deg, f"{owner} turned {deg:.2f} deg from nominal (limit {lim_deg:g} deg)"
        )
    for name, p in rows.items():
        if name.endswith(".zero_offset") and p.unit == "m":  # a prismatic joint's, against the origins'
            mm = 1e3 * abs(p.estimate - p.nominal)
            c.add(
                name,
                mm,
                limits.origin_mm,
                f"{name} moved {mm:.1f} mm from nominal (limit {limits.origin_mm:g} mm)",
            )
        elif name.endswith(".zero_offset"):
            deg = float(np.degrees(abs(_wrap(p.estimate - p.nominal))))
            c.add(
                name,
                deg,
                limits.zero_offset_deg,
                f"{name} moved {deg:.2f} deg from nominal (limit {limits.zero_offset_deg:g} deg)",
            )


def _uncertainties(c: _Checks, parameters: tuple[ParameterRow, ...], limits: Limits, tol: float) -> None:
    """A free joint origin or zero offset whose standard deviation is a third of its
    plausible correction or more: the data barely see it, and its value is not to be
    read (the tool point may still be fine; a parameter table is not)."""
    worst: dict[str, tuple[float, float, str]] = {}
    for p in parameters:
        if p.group != "correction" or not p.free or p.std is None:
            continue
        owner, _, what = p.name.rpartition(".")
        if p.unit == "m":
            ratio, shown = 1e3 * p.std / (limits.origin_mm / 3), f"{1e3 * p.std:.2f} mm"
        elif what == "zero_offset":
            ratio, shown = (
                np.degrees(p.std) / (limits.zero_offset_deg / 3),
                f"{np.degrees(p.std):.3f} deg",
            )
        else:
            ratio, shown = np.degrees(p.std) / (limits.origin_deg / 3), f"{np.degrees(p.std):.3f} deg"
        if ratio > worst.get(owner, (0.0,))[0]:
            worst[owner] = (float(ratio), float(ratio), f"{p.name} +- {shown}")
    for owner, (ratio, _, text) in worst.items():
        c.add(
            f"{owner}.std",
            ratio,
            1.0,
            f"{text}: freed but barely determined (a third of its plausible correction or more); the capture "
            f"does not pin it: add poses that move it, or hold it with a larger identifiability tolerance "
            f"(calibrate --config identifiability-tol=TOL, Python identifiability_tol=; now {tol:g})",
        )


def _point_fit(c: _Checks, setup: Setup, two: TwoStage, limits: Limits) -> None:
    """Stop-and-shoot poses: the samples the robust point fit rejected (a note, or a reason past
    `limits.outlier_fraction`), the parameters held because the data cannot see them (a note),
    and every joint's span over the poses (`limits.joint_span_deg`, `joint_span_mm`)."""
    pf = two.points
    k, share = len(pf.outliers), len(pf.outliers) / max(pf.poses, 1)
    if k:
        d = [o.distance_mm for o in pf.outliers]
        far = f"{d[0]:.2f} mm" if k == 1 else f"{min(d):.2f}-{max(d):.2f} mm"
        text = (
            f"the robust point fit rejected {k} of the {pf.poses} poses, measured {far} from the calibrated "
            "model's point (a joint position or a measurement wrong), and left them out of the fit: "
            + listed([f"sample {o.sample} ({o.line}, {o.distance_mm:.2f} mm)" for o in pf.outliers])
        )
        if share <= limits.outlier_fraction:
            c.notes.append(text)
        else:
            c.symptoms.append(
                f"{text}; {100 * share:.0f} % of the poses, over the limit of "
                f"{100 * limits.outlier_fraction:g} %: check the joint positions and the measurements"
            )
    c.rows.append(
        Check("point_fit.rejected_share", share, limits.outlier_fraction, share <= limits.outlier_fraction)
    )
    # The calibrated model's (terms kept included) residual scale over the stated noise.
    scale, sigma_mm = (
        np.sqrt(float(pf.fit.sigma2)),
        1e3 * float(np.median(np.asarray(pf.problem.data.sigma)[pf.used])),
    )
    c.add(
        "point_fit.noise_scale",
        scale,
        limits.noise_scale,
        f"the samples scatter {scale:.0f} times the noise they state ({sigma_mm:.3g} mm) about the calibrated "
        "model: a noise in metres given as millimetres (import-csv --sigma-mm), or a model that misses most of the "
        "error",
    )
    if not c.at_least("point_fit.noise_scale_min", scale, QUIET_NOISE_SCALE):
        c.symptoms.append(
            f"the samples scatter only {scale:.2g} times the noise they state ({sigma_mm:.3g} mm) about the "
            "calibrated model: the stated noise is too large (millimetres given as metres: metadata.json "
            "device.sigma_m or the samples' sigma_m column, import-csv --sigma-mm), and every standard deviation, "
            "the certificate and verify's prediction with it"
        )
    if pf.prior is not None:
        if (row := prior_row(pf.prior)) is not None:
            c.add(*row)
    if pf.unseen:
        c.notes.append(
            "held at nominal because the samples cannot see them (each moves the measured point so little that, "
            f"alone, it would be known no better than a third of its plausible correction): {', '.join(pf.unseen)}"
        )
    nominal = setup.nominal
    q = np.asarray(pf.problem.data.q)[pf.used]
    still = []
    for j, name in enumerate(nominal.joint_names):
        prismatic = nominal.joint_types[j] == PRISMATIC
        span = float(np.ptp(q[:, j])) * (1e3 if prismatic else 180.0 / np.pi)
        limit = limits.joint_span_mm if prismatic else limits.joint_span_deg
        unit = "mm" if prismatic else "deg"
        if not c.at_least(f"{name}.span_{unit}", span, limit):
            still.append((name, f"{name} ({span:.2f} {unit})"))
    if still:
        names = [n for n, _ in still]
        held = [h for h in pf.held if h.split(".")[0] in names]
        c.symptoms.append(
            f"joints {', '.join(t for _, t in still)} hardly move over the {int(pf.used.sum())} poses (each needs "
            f"{limits.joint_span_deg:g} deg, or {limits.joint_span_mm:g} mm): the capture cannot determine their "
            "zero offsets nor the geometry they carry, so the model holds only at those joint positions; "
            + (f"held at nominal for want of motion: {', '.join(held)}; " if held else "")
            + "capture poses that move every joint"
        )


def _ee_sigma_mm(setup: Setup, two: TwoStage, refined: Refined | None) -> float:
    """RMS over random configurations of the propagated 1-sigma tool-point uncertainty (mm); with
    non-geometric terms kept, of the whole model's (their coefficients' uncertainty turns each
    joint by its basis there: a compliance the capture pins only near its own gravity torques
    shows here as the sag it leaves open over the workspace)."""
    if refined is None:
        fit = two.fit
        refs, cam, corr, cov = (
            (fit.T_cam_base0, fit.T_flange_marker0),
            fit.params.cam,
            fit.params.correction,
            fit.cov,
        )
    else:
        res, lay = refined.fit, refined.layout
        refs, cam, corr = refined.references, res.params.cam, res.params.correction
        idx = np.concatenate([np.arange(lay.axis_size), lay.index("terms")])  # the kept terms' too
        cov = np.asarray(res.cov)[np.ix_(idx, idx)]
    kept = refined.terms if refined is not None and refined.terms is not None and refined.terms.kept else None
    terms = None if kept is None else (kept.terms, kept.masses, kept.coms)
    sigma = _programs.end_effector_sigma(
        setup.nominal, *refs, cam, corr, cov, setup.dataset.joint_limits, terms
    )
    return float(1e3 * np.sqrt(np.mean(sigma**2)))


def _ee_sigma_of(setup: Setup, two: TwoStage, refined: Refined, cov) -> float:
    """`_ee_sigma_mm` of the refined result with the covariance `cov` (flat) in place of its own."""
    return _ee_sigma_mm(setup, two, replace(refined, fit=eqx.tree_at(lambda r: r.cov, refined.fit, cov)))


def _ratios(c: _Checks, setup: Setup, two: TwoStage, refined: Refined | None, limits: Limits) -> None:
    """The reported reduction ratios (refined when the refinement ran) against the nominal ones."""
    nominal = np.asarray(setup.nominal.reduction_ratio)
    if refined is not None and refined.ratios is not None:
        ratios = [r for r, _ in refined.ratios]
    else:
        ratios = [a.ratio for a in two.arc_rows] or [None] * len(nominal)
    for joint, nom, ratio in zip(setup.nominal.joint_names, nominal, ratios):
        if ratio is None:
            continue
        pct = 100.0 * abs(ratio / nom - 1.0)
        c.add(
            f"{joint}.ratio",
            pct,
            limits.ratio_percent,
            f"{joint}: reduction ratio {ratio:.4g} is {pct:.1f} % from the nominal {nom:.4g} "
            f"(limit {limits.ratio_percent:g} %; encoder units or ratio wrong?)",
        )


def _axes(c: _Checks, setup: Setup, two: TwoStage, limits: Limits, timed_rows: Refined | None = None) -> None:
    """The arc fits, the axis fit, and the axes' spacing against the nominal robot's.
    With `timed_rows`, a refinement that timed every corner of a rolling shutter at its row,
    the fits' residuals are left out (PnP's one-instant poses of the skewed plates bend the
    arcs) and the spacing is the refined robot's, which a target printed at another size
    still scales; otherwise the arcs' (the axes measured through the target)."""
    residuals = timed_rows is None
    for a in two.arc_rows if residuals else ():
        c.add(
            f"{a.joint}.arc_residual",
            a.residual_rms,
            limits.arc_residual,
            f"{a.joint}: the arc fit's whitened residual RMS is {a.residual_rms:.2f} (expected about 1): "
            "its poses do not lie on one arc (wrong clock, encoder or frames?)",
        )
    rms = float(two.fit.residual_rms) if residuals else 0.0
    c.add(
        "axis_residual",
        rms,
        limits.axis_residual,
        f"the axis fit's whitened residual RMS is {rms:.3g} (expected about 1): the measured axes do not fit the "
        "nominal robot's structure",
    )
    names = setup.nominal.joint_names
    reversed_ = reversed_joints(setup, two.arcs)
    c.add(
        "encoder_sense",
        len(reversed_),
        0,
        "; ".join(
            f"joint {names[j]!r} turns the other way than the robot file's axis: its axis, measured through the "
            f"target in the encoder log's sense, points against those of {', '.join(repr(names[k]) for k in others)}, "
            "which the robot file has it agree with; negate its column of the encoder log (or its URDF axis)"
            for j, others in reversed_
        ),
        cause="encoder_sense",
    )
    if timed_rows is None:
        scale, pairs = axis_spacing_ratio(setup, two.arcs)
        seen = "the joint axes measured through the target are"
    else:
        model = timed_rows.fit.model
        point, direction = joint_axes_at_zero(model)
        point = np.where(np.asarray(model.joint_types)[:, None] == PRISMATIC, np.nan, point)
        scale, pairs = axis_spacing_ratio(setup, SimpleNamespace(point=point, direction=direction))
        seen = "the refined robot's joint axes (every corner timed at its row) are"
    if not pairs:
        return
    pct = 100.0 * abs(scale - 1.0)
    limit, noted = spacing_limits(sum(nm for _, _, nm in pairs), limits.board_scale_percent)
    square = [t.spec for t in setup.targets if getattr(t.spec, "square_length", None)]
    hint = "; ".join(
        f"{t.name!r}'s square of {1e3 * t.square_length / scale:.2f} mm would fit"
        for t in square
        if scale > 0
    )
    hint = f"; {hint}" + (" (were every target's size off alike)" if len(square) > 1 else "") if hint else ""
    c.add(
        "board_scale",
        pct,
        limit,
        f"{seen} {100 * scale:.1f} % of the nominal robot's spacing "
        f"({', '.join(f'{n} {1e3 * m:.1f} vs {1e3 * nm:.1f} mm' for n, m, nm in pairs)}): is the target's "
        f"printed size the one in metadata.json{hint}?",
    )
    if noted < pct <= limit:  # passed, but further off than an arm's own
        seen_from = getattr(two.fit, "T_cam_base0", None) if setup.board is None else None  # a fixed camera
        moved = 10.0 * pct * reach_rms(setup.nominal, setup.dataset.joint_limits, seen_from)
        c.notes.append(
            f"{seen} {100 * scale:.2f} % of the nominal robot's spacing, further off than a real arm's axes "
            f"miss their datasheet (about {noted:.2g} % here): were the target's printed size that "
            f"far off{f' ({hint[2:]})' if hint else ''}, the tool point would lie {moved:.1f} mm RMS off, which "
            "the claimed uncertainty does not count; measure the printed target across its whole width"
        )


def _refinement(c: _Checks, refined: Refined, limits: Limits) -> None:
    s = refined.summary
    c.add(
        "sigma_px",
        s.sigma_px,
        limits.sigma_px,
        f"the refinement's pixel noise is {s.sigma_px:.2f} px (limit {limits.sigma_px:g} px)",
    )
    frac = s.outlier_corners / max(s.corners, 1)
    c.add(
        "outlier_fraction",
        frac,
        limits.outlier_fraction,
        f"the refinement rejected {100 * frac:.0f} % of the corners (limit {100 * limits.outlier_fraction:g} %)",
    )


def _shutter(c: _Checks, refined: Refined, limits: Limits) -> None:
    """The residuals of a global-shutter refinement against a rolling shutter's
    pattern (`_refine.shutter_test`): an offset growing down the image rows with the
    marker's image speed, which the clock offset (one time for every row) cannot absorb."""
    for t in refined.shutter_test or ():
        big = abs(t.readout_s) >= limits.readout_s
        c.add(
            f"{t.camera}.rolling_shutter_sigmas",
            t.sigmas if big else 0.0,
            limits.shutter_sigmas,
            f"camera {t.camera!r}: the residuals shift along the image rows with the joints' speed, as a rolling "
            f"shutter's do: its rows read out over about {1e3 * t.readout_s:.1f} ms ({1e6 * t.line_delay_s:.1f} "
            f"us per row, {t.sigmas:.0f} sigmas) and the calibration timed every row at the frame's stamp; give "
            'cameras[].line_delay_s in metadata.json (the readout over the image height) or "estimate", or sweep '
            "slower, or film the poses standing still (stop-and-shoot)",
            cause="rolling_shutter",
        )


def _camera_model(c: _Checks, refined: Refined, K_std: np.ndarray | None, limits: Limits) -> None:
    """The residuals against a radial distortion beyond the first camera's given lens, and against
    other focal lengths or another principal point than its given ones (`jaxcal._diagnostics`'
    `lens_test` and `intrinsics_test`; against `K_std`, that K's stated uncertainty, where given):
    the larger first, where both fail."""
    rows = []
    if (t := refined.lens_test) is not None:
        rows.append(
            (
                t.sigmas,
                f"{t.camera}.lens_sigmas",
                t.sigmas if t.shift_px >= limits.lens_px else 0.0,
                limits.lens_sigmas,
                f"camera {t.camera!r}: the residuals grow with the distance from the image's centre, as a lens's radial "
                f"distortion does ({t.sigmas:.0f} sigmas): a distortion of k1 {t.k1:+.3g}, k2 {t.k2:+.3g} beyond the "
                f"metadata's would shift the image's corners by {t.shift_px:.1f} px, and the calibration bent the robot "
                "to fit it; give cameras[].distortion (and K) from the camera's own calibration in metadata.json, or "
                "leave cameras[].K out to have the intrinsics self-calibrated",
            )
        )
    if (t := refined.intrinsics_test) is not None:
        rows.append(_intrinsics_row(c, t, refined, K_std, limits))
    for _, *row in sorted(rows, key=lambda r: -r[0]):
        c.add(*row, cause="camera_model")


def _intrinsics_row(c: _Checks, t, refined: Refined, K_std: np.ndarray | None, limits: Limits) -> tuple:
    """The intrinsics test's check row. Where `cameras[].K_std` is stated, the claimed uncertainty
    already counts K's errors up to it: the step the residuals point to is then held against it
    (in its standard deviations), and one within `limits.intrinsics_sigmas` of them passes (a note)."""
    f = refined.problem.K0[0, 0], refined.problem.K0[1, 1]
    step = (
        f"focal lengths fx {100 * t.fx_px / f[0]:+.2f} %, fy {100 * t.fy_px / f[1]:+.2f} % and the principal point "
        f"moved ({t.cx_px:+.1f}, {t.cy_px:+.1f}) px"
    )
    value = t.sigmas if t.shift_px >= limits.intrinsics_px else 0.0
    fix = "give cameras[].K from the camera's own calibration at this resolution and focus"
    message = (
        f"sigmas): {step} would shift the image's corners by {t.shift_px:.1f} px, and the calibration moved the "
        f"camera and bent the robot to fit them; {fix}, or state how well K is known as cameras[].K_std (px) to "
        "have it counted in the claimed uncertainty, or leave cameras[].K out to have the intrinsics self-calibrated"
    )
    if K_std is not None:
        beyond = float(np.max(np.abs([t.fx_px, t.fy_px, t.cx_px, t.cy_px]) / np.asarray(K_std)))
        if beyond <= limits.intrinsics_sigmas:  # within K's stated uncertainty: counted, a pass
            if value > limits.intrinsics_sigmas:
                c.notes.append(
                    f"camera {t.camera!r}: the residuals point to other intrinsics than metadata.json's ({step}), "
                    f"within {beyond:.1f} of cameras[].K_std's standard deviations: counted in the claimed uncertainty"
                )
            value = 0.0
        message = (
            f"sigmas): {step}, {beyond:.0f} times the largest of cameras[].K_std's standard deviations, would shift "
            f"the image's corners by {t.shift_px:.1f} px; {fix}, with its own uncertainty as K_std"
        )
    prefix = (
        f"camera {t.camera!r}: the residuals point to other intrinsics than metadata.json's ({t.sigmas:.0f} "
    )
    return t.sigmas, f"{t.camera}.intrinsics_sigmas", value, limits.intrinsics_sigmas, prefix + message


def _focal_note(c: _Checks, setup: Setup, two: TwoStage, refined: Refined, sigma: float) -> None:
    """How far the result leans on the first camera's held focal lengths: the tool point's RMS move
    were they 0.1 % longer (`Refined.focal_shift` through the tool point's Jacobian), noted where
    it is half the claimed 1-sigma or more (a claim that takes `K` as exact: `cameras[].K_std` not given)."""
    if refined.focal_shift is None or setup.camera.K_std is not None:
        return
    shift = np.asarray(refined.focal_shift, np.float64)
    moved = _ee_sigma_of(setup, two, refined, np.outer(shift, shift))
    if moved >= 0.5 * sigma:
        c.notes.append(
            f"the result leans on metadata.json's K: were its focal lengths 0.1 % longer, the tool point would "
            f"move {moved:.2f} mm RMS, against a claimed 1-sigma of {sigma:.2f} mm that takes K as exact; state "
            "K's uncertainty as cameras[].K_std to have it counted, or leave cameras[].K out: the intrinsics are "
            "then self-calibrated and their uncertainty counted"
        )


#: What would separate each non-geometric family from the geometry, for the note on those left out.
_SEPARATES = {
    "compliance": "poses whose gravity torques differ more (the arm stretched and folded, the wrist up and down)",
    "backlash": "each pose approached from both directions",
    "harmonic1": "each joint at more angles over its turn",
    "harmonic2": "each joint at more angles over its turn",
}


def _cause_words(cause: str) -> tuple[str, str]:
    """A `stages._terms.unresolved` cause in words, and what capture would resolve it."""
    if cause == LAG:
        return (
            "the compliance's lag under the arm's own acceleration, which sweeps at one speed cannot tell from "
            "the reduction ratios",
            "each sweep filmed both ways, the second at another speed",
        )
    families = cause.split("+")
    return (
        f"{' and '.join(families)}, left out because the held-out views could not tell "
        f"{'it' if len(families) == 1 else 'them'} from the geometry",
        "; ".join(_SEPARATES.get(f, f"{f} varied") for f in families),
    )


def _left_out_note(c: _Checks, setup: Setup, two: TwoStage, refined: Refined, sigma: float) -> None:
    """The claim's share from what the non-geometric terms cannot tell from the geometry
    (`stages._terms.unresolved`: the geometry's shift, counted in the covariance), noted where the
    tool point's RMS move is half the claimed 1-sigma or more."""
    t = refined.terms
    if t is None or t.shift is None:
        return
    cov = np.zeros_like(np.asarray(refined.fit.cov))
    cov[np.ix_(t.shift_at, t.shift_at)] = t.shift @ t.shift.T
    moved = _ee_sigma_of(setup, two, refined, cov)
    if moved < 0.5 * sigma:
        return
    words = [_cause_words(cause) for cause in t.shift_of]
    c.notes.append(
        f"the claimed 1-sigma of {sigma:.2f} mm counts what the model cannot tell from the geometry, "
        + "; ".join(w for w, _ in words)
        + f": with {'it' if len(words) == 1 else 'them'} the geometry moves the tool point {moved:.2f} mm RMS (the "
        f"model alone would claim {np.sqrt(max(sigma**2 - moved**2, 0.0)):.2f} mm); to tell them apart, capture "
        + "; ".join(fix for _, fix in words)
    )


def _correlation(c: _Checks, setup: Setup, two: TwoStage, refined: Refined, limits: Limits) -> None:
    """The residuals' errors that repeat along the capture or are shared by a pose's views
    (`stages._refine.error_correlation`): named, with how much the kernel sandwich grew the
    tool point's uncertainty."""
    t = refined.error_correlation
    if t is None:
        return
    grew, growth = "", 1.0
    if refined.cov_views is not None:  # the noise's share alone, without what the claim considers
        free = np.flatnonzero(np.asarray(refined.fit.free))
        cov = np.array(refined.fit.cov) - (0.0 if refined.considered is None else refined.considered)
        after = _ee_sigma_of(setup, two, refined, cov)
        cov[np.ix_(free, free)] = refined.cov_views
        before = _ee_sigma_of(setup, two, refined, cov)
        growth = after / before if before > 0 else float("inf")
        grew = (
            f"; the covariance now accounts for them (a kernel sandwich over {t.kernel_lags} frames: the noise's "
            f"share of the tool point's 1-sigma {before:.2f} -> {after:.2f} mm), but the estimate carries their bias"
        )
    lags = ", ".join(f"{r:.2f}" for r in t.autocorrelation)
    found = []
    if t.sigmas > limits.correlation_sigmas:
        found.append(
            f"the residuals repeat from frame to frame: each corner's residual correlates with its own in the next "
            f"frames of the capture ({lags} at lags 1-{len(t.autocorrelation)}, {t.sigmas:.1f} sigmas), where the "
            f"noise model takes them as independent{grew}. Correlated detector errors repeat so: images resampled "
            "at the sensor's resolution (an undistortion, a renderer's lens warp or scaling) or a pattern the motion "
            "carries along; give the camera's raw images with its lens in metadata.json, or film poses that differ "
            "more from frame to frame. So do the errors of a motion the model does not hold (an arm that sags or "
            "lags its motors: see the arm's reasons, if any)"
        )
    if t.pose_sigmas is not None and t.pose_sigmas > limits.correlation_sigmas:
        found.append(
            f"the views of one pose share their errors ({t.pose_sigmas:.1f} sigmas: the cameras or targets seen "
            f"at one capture index err alike, as an error of the robot's pose would make them){grew}"
        )
    if t.sigmas <= limits.correlation_sigmas:
        c.add("correlated_errors_sigmas", t.sigmas, limits.correlation_sigmas, "")
    if not found:
        return
    # Errors that repeat matter when they change the answer's uncertainty (`Limits.correlation_growth`).
    if growth > limits.correlation_growth:
        for message in found:
            c.add(
                "correlated_errors_growth",
                growth,
                limits.correlation_growth,
                message,
                cause="correlated_errors",
            )
    else:
        c.add("correlated_errors_growth", growth, limits.correlation_growth, "")  # passes
        c.notes += [
            f"{m} (its 1-sigma grew {growth:.2f}x, within the {limits.correlation_growth:g}x that makes a result "
            "suspect)"
            for m in found
        ]


def verdict(
    setup: Setup,
    obs: Observations,
    sync: Sync,
    two: TwoStage,
    refined: Refined | None,
    limits: Limits,
    arm_score: Future | None = None,
) -> Verdict:
    """Check the result (see the module docstring). `arm_score`: the arm-rigidity test's
    figures (`stages.finish_arm_score`), or its terms started ahead (`stages.start_arm_score`),
    if either ran."""
    c = _Checks()
    ran = refined is not None and refined.fit is not None
    measured = {t.name for t in setup.fit_targets if t.T_link_target is None}
    if setup.kind.sequential:
        measured |= {t.name for t in setup.targets}  # link mounts start from PnP
    given = "" if setup.kind.fixed_frame_free else f"{setup.nominal.joint_names[0]}.origin"
    _corrections(c, refined.parameters if ran else two.parameters, limits, measured, given)
    _uncertainties(c, refined.parameters if ran else two.parameters, limits, setup.identifiability_tol)
    if two.points is not None:
        _point_fit(c, setup, two, limits)
    _ratios(c, setup, two, refined if ran else None, limits)
    # A rolling shutter skews each plate (its rows seen at different times), which PnP's
    # one-instant poses cannot hold: the two-stage fits' residuals then say nothing of the
    # result when the refinement timed every corner at its row.
    skewed = ran and bool(refined.line_delays)
    if setup.kind.has_arcs:
        timing_checks(c, setup, sync, two, limits)
        _axes(c, setup, two, limits, refined if skewed else None)
        arm_check(c, setup, sync, two, refined, limits, arm_score)
        c.also_from("timing", "arm", "the timing named above moves the arcs so too, and may be all of it: ")
        for row in blur_rows(setup, obs.primary, sync):  # sweeps that lost most of their frames to blur
            c.add(*row, cause="blur")
    if ran:
        _refinement(c, refined, limits)
        _shutter(c, refined, limits)
        _camera_model(c, refined, setup.camera.K_std, limits)
        _correlation(c, setup, two, refined, limits)
    sigma = _ee_sigma_mm(setup, two, refined if ran else None)
    c.add(
        "ee_sigma_mm",
        sigma,
        limits.ee_sigma_mm,
        f"the data pin the tool point only to {sigma:.2f} mm (1-sigma RMS over random configurations, limit "
        f"{limits.ee_sigma_mm:g} mm): "
        + (
            "too few poses, joints that barely move, or a model the samples do not fit (the other reasons)"
            if isinstance(setup.camera, DeviceInfo)
            else "too little motion, too few frames, or intrinsics the capture cannot fix"
        ),
    )
    if ran:
        _focal_note(c, setup, two, refined, sigma)
        _left_out_note(c, setup, two, refined, sigma)
    self_calibrated = [o.camera.name for o in (obs.primary, *obs.others) if o.intrinsics.rms_px is not None]
    if self_calibrated and not ran:
        # Intrinsics fitted to the sweep images alone trade off against the camera's pose and
        # the link lengths; only the refinement frees them with the robot (`refine_intrinsics`).
        c.add(
            "self_calibrated_without_refinement",
            1.0,
            0.0,
            f"camera(s) {self_calibrated}: intrinsics self-calibrated from the sweep images and not refined with "
            "the robot (the refinement did not run): the two-stage result inherits their error, often tens of "
            "millimetres; run the refinement (drop no-refine) or give K and the distortion in metadata.json",
        )
    for o in (obs.primary, *obs.others):
        rms_px = o.intrinsics.rms_px
        if rms_px is not None:
            c.add(
                f"{o.camera.name}.intrinsics_rms_px",
                rms_px,
                limits.intrinsics_rms_px,
                f"camera {o.camera.name!r}: self-calibrated intrinsics reproject at {rms_px:.2f} px "
                f"(limit {limits.intrinsics_rms_px:g} px)",
            )
    failed = not two.solver.success or (ran and not succeeded(refined))
    reasons = c.reasons
    status = "failed" if failed else ("suspect" if reasons else "ok")
    if failed:
        reasons.insert(0, "a solver did not converge (see result.json 'solver')")
    return Verdict(status, tuple(reasons), tuple(c.rows), tuple(c.notes))
