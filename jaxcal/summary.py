"""A `CalibrationResult`'s facts as text: one formatter for the console
(`jaxcal calibrate`) and `report.md`, so that both say the same thing the same way.

Each function returns plain strings (`TextTable`: a title, a header and rows);
`TextTable.markdown` renders it for `report.md`, the command line renders it
with rich.
"""

from dataclasses import dataclass

from .records import row_of


@dataclass(frozen=True)
class TextTable:
    """A table as text: its title, column names and rows of cells."""

    title: str
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]

    def markdown(self) -> list[str]:
        """The table as `report.md` lines (the first column left-aligned, the others right)."""
        align = ["---"] + ["---:"] * (len(self.header) - 1)
        return [
            "| " + " | ".join(self.header) + " |",
            "| " + " | ".join(align) + " |",
            *("| " + " | ".join(r) + " |" for r in self.rows),
        ]


def fmt(x, spec: str = ".3f") -> str:
    """A number, or `n/a` for None."""
    return "n/a" if x is None else format(x, spec)


def joints_table(result) -> TextTable:
    """Per joint its arc fit: frames, residual RMS, the reduction ratio with its std and
    the solver; against the truth (synthetic data) the true ratio and the axis error."""
    v = result.validation
    header = ["joint", "frames", "pos RMS mm", "rot RMS deg", "ratio nominal", "ratio", "std", "solver"]
    if v is not None:
        header += ["ratio true", "axis err deg"]
    rows = []
    for k, a in enumerate(result.arcs):
        row = [
            a.joint,
            str(a.frames),
            f"{a.position_rms_mm:.3f}",
            fmt(a.rotation_rms_deg, ".4f"),
            f"{a.ratio_nominal:.4f}",
            fmt(a.ratio, ".4f"),
            fmt(a.ratio_std, ".4f"),
            f"{a.solver.result} ({a.solver.steps} steps)",
        ]
        if v is not None:
            e = row_of(v.parameter_errors, "joint", a.joint)
            row += [f"{v.true_ratios[k]:.4f}", f"{e.axis_direction_deg:.3f}"]
        rows.append(tuple(row))
    return TextTable(f"Joint sweeps ({result.kind.sensor} {result.camera})", tuple(header), tuple(rows))


def truth_table(result) -> TextTable | None:
    """Against the truth (synthetic data): the end-effector error of the nominal model,
    the two-stage start (when refined) and the calibration; the fixed frame's, the
    ratios' and the clock's errors. None without a truth."""
    v = result.validation
    if v is None:
        return None
    refined = v.refined
    # Without sweeps the refinement starts from the nominal robot and a closed-form camera pose.
    start = ["two-stage" if result.kind.has_arcs else "start (closed form)"] if refined else []
    header = ("", "nominal model", *start, "refined" if refined else "calibrated")
    pad = ("",) if refined else ()
    rows = [
        (
            "EE RMS mm",
            f"{v.ee_rms_mm_before:.3f}",
            *((f"{v.ee_rms_mm_two_stage:.3f}",) if refined else ()),
            f"{v.ee_rms_mm_after:.3f}",
        ),
        (
            "EE max mm",
            f"{v.ee_max_mm_before:.3f}",
            *((f"{v.ee_max_mm_two_stage:.3f}",) if refined else ()),
            f"{v.ee_max_mm_after:.3f}",
        ),
    ]
    c = v.T_cam_base_error
    rows.append((f"{result.kind.fixed_frame} error", "", *pad, f"{c.trans_mm:.3f} mm, {c.rot_deg:.4f} deg"))
    ratio = [abs(e.ratio_percent) for e in v.parameter_errors if e.ratio_percent is not None]
    if ratio:
        rows.append(("max ratio error %", "", *pad, f"{max(ratio):.4f}"))
    if v.clock_offset_error_ms is not None and result.clock.estimated:
        rows.append(("clock offset error ms", "", *pad, f"{v.clock_offset_error_ms:.3f}"))
    title = f"Before / after, against the truth ({v.ee_point}, {v.configurations} random configurations)"
    return TextTable(title, header, tuple(rows))


def truth_line(result) -> str | None:
    """Against the truth, the refined and the two-stage (or closed-form start) EE RMS read against
    the refined result's claimed uncertainty (the verdict's `ee_sigma_mm`: the propagated 1-sigma
    tool-point error, RMS over random configurations): which one is nearer the truth means
    something only when they differ by more than that. None without a truth, a refinement or
    the claim."""
    v = result.validation
    if v is None or not v.refined or result.verdict is None:
        return None
    sigma = next((c.value for c in result.verdict.checks if c.check == "ee_sigma_mm"), None)
    if sigma is None or not sigma > 0:
        return None
    start = "two-stage" if result.kind.has_arcs else "closed-form start"
    after, before = v.ee_rms_mm_after, v.ee_rms_mm_two_stage
    diff = abs(after - before)
    line = (
        f"Against the truth: refined {after:.3f} mm, {start} {before:.3f} mm (EE RMS); the refined result "
        f"claims {sigma:.3f} mm (1-sigma RMS), so the measured error is {after / sigma:.2f}x its claim"
    )
    if diff <= sigma:
        better = "refined" if after < before else start
        return line + (
            f"; the two differ by {diff:.3f} mm, within that claim: the {better} being nearer the truth on this "
            "capture is within the noise, not a sign of a better or a worse stage."
        )
    if after < before:
        return line + f"; the refinement is nearer the truth by {diff:.3f} mm, more than the claimed 1-sigma."
    return line + (
        f"; the refinement is further from the truth by {diff:.3f} mm, more than the claimed 1-sigma: a model "
        "error the refinement follows (see the reasons) or a claim too small."
    )


def clock_line(result) -> str:
    """The clock offset used, estimated (with its std) or given."""
    c = result.clock
    return f"Clock offset: {1e3 * c.offset_s:.2f} ms" + (
        f" (estimated, std {1e3 * c.std_s:.2f} ms)" if c.estimated else " (given)"
    )


def refinement_line(result) -> str | None:
    """The refinement in one sentence (None when it did not run)."""
    r = result.refinement
    if r is None:
        return None
    return (
        f"{r.corners} corners in {r.frames} frames, {r.free_parameters} parameters; "
        f"{r.loss}; solver {r.solver.result} ({r.solver.steps} steps). "
        f"Inlier RMS {r.inlier_rms_px:.3f} px, pixel sigma {r.sigma_px:.3f} px, "
        f"{r.outlier_corners} outlier corners; condition number {r.condition_number:.3g}."
    )


def terms_tables(result) -> tuple[TextTable, ...]:
    """The non-geometric terms (`result.terms`): the models cross-validation compared (the
    geometric one first) with what was kept and why, then the kept coefficients with their
    std. Empty when no term was tried."""
    t = result.terms
    if t is None:
        return ()
    px = any(m.cv_mean_px is not None for m in t.models)
    unit = "px" if px else "mm"
    rows = []
    for m in t.models:
        cv = (m.cv_mean_px, m.cv_rms_px, m.cv_max_px) if px else (m.cv_mean_mm, m.cv_rms_mm, m.cv_max_mm)
        rows.append(
            (
                "+".join(["geometric", *m.terms]),
                str(m.free),
                *(fmt(x, ".4f") if x is not None else "-" for x in cv),
                "yes" if m.kept else "",
                m.why or "",
            )
        )
    block = f", left out in blocks of {t.block_frames} consecutive frames" if t.block_frames else ""
    models = TextTable(
        f"Non-geometric terms: {t.folds}-fold cross-validation{block}; kept: {'+'.join(t.kept) or 'none'}",
        ("model", "free", f"CV mean {unit}", f"CV RMS {unit}", f"CV max {unit}", "kept", "why"),
        tuple(rows),
    )
    coefficients = TextTable(
        "Kept non-geometric coefficients (rad per kN m of gravity torque, rad of lost motion or harmonic)",
        ("coefficient", "estimate", "std"),
        tuple((c.name, f"{c.estimate:.4g}", f"{c.std:.2g}") for c in t.coefficients if c.free),
    )
    return (models, coefficients) if coefficients.rows else (models,)
