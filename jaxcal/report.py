"""Writing a calibration's results: `result.json`, `calibrated.urdf`, the camera pose as
OpenCV YAML, and `report.md` with its plots. Everything goes into a temporary
directory beside the destination and is renamed into place, so a failure
leaves nothing partial behind.
"""

import importlib
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ._kinematics import REVOLUTE
from ._tables import PhysicalTable, base_flange_std, physical_table
from .compensation import compensation_of
from .io._files import atomic_directory
from .io._provenance import made_by
from .io.camera_yaml import intrinsics_fields, pose_fields, write_camera_yaml
from .io.compensation import COMPENSATION_FILE, compensation_json
from .io.dataset import finite_json, write_json
from .io.dh_tables import dh_table_json, is_table_file
from .io.result import ESTIMATE_FILE, pose_figures, write_estimate
from .io.robot_files import is_ur, ur_kinematics_text, write_ros_camera_files
from .io.ros import write_static_transform
from .io.urdf import save_urdf
from .records import PoseFigures
from .summary import clock_line, fmt, joints_table, refinement_line, terms_tables, truth_line, truth_table


class ArcGeometry(NamedTuple):
    """A joint's marker positions in its fitted arc's plane (mm; see `arc_geometry`)."""

    u: np.ndarray
    v: np.ndarray
    #: The arc's radius (nan for a prismatic joint's line).
    radius: float
    radial: np.ndarray
    axial: np.ndarray


def arc_geometry(result, j: int) -> ArcGeometry:
    """Joint `j`'s measured marker positions in its fitted arc's plane.

    **Returns:** `u`, `v` (mm, in-plane, about the fitted axis point), `radius`
    (mm), `radial` and `axial` residuals (mm) of every observed frame (first marker).
    """
    V = np.asarray(result.arc_fit.direction[j])
    Q = np.asarray(result.arc_fit.point[j])
    mask = result.sweeps.mask[j, 0]
    P = result.sweeps.positions[j, 0][mask]
    if not np.all(np.isfinite(Q)):
        # A prismatic joint (`fit_line`): `u` along the travel, `v` across it, about the
        # positions' centroid; no radius; the lateral deviation as the radial residual.
        d = P - P.mean(0)
        h = d @ V
        lateral = d - h[:, None] * V
        e1 = np.linalg.svd(lateral, full_matrices=False)[2][0] if len(P) > 1 else np.cross(V, [1.0, 0, 0])
        v = 1e3 * lateral @ e1
        return ArcGeometry(u=1e3 * h, v=v, radius=float("nan"), radial=v, axial=np.zeros_like(v))
    d = P - Q
    h = d @ V
    inplane = d - h[:, None] * V
    e1 = inplane[0] / np.linalg.norm(inplane[0])
    e2 = np.cross(V, e1)
    rho = np.linalg.norm(inplane, axis=1)
    return ArcGeometry(
        u=1e3 * inplane @ e1,
        v=1e3 * inplane @ e2,
        radius=1e3 * rho.mean(),
        radial=1e3 * (rho - rho.mean()),
        axial=1e3 * (h - h.mean()),
    )


def _margins(fig, *, left: float, right: float, bottom: float, top: float, **space) -> None:
    """`fig.subplots_adjust` with the margins in inches (the same room at any figure size)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h, **space)


def warm_up_plots() -> threading.Thread:
    """Import matplotlib and load its fonts on a background thread (started, returned), so
    that a command which plots at its end finds them ready: `jaxcal calibrate` starts it
    while it calibrates (mostly waiting on XLA, without Python's lock)."""
    thread = threading.Thread(target=_load_matplotlib, name="jaxcal plots warm-up")
    thread.start()
    return thread


def _load_matplotlib() -> None:
    for name in ("matplotlib.figure", "matplotlib.backends.backend_agg", "matplotlib.font_manager"):
        module = importlib.import_module(name)
    module.fontManager.findfont("DejaVu Sans")


def plot_arcs(result):
    """Every joint's marker positions in its fitted arc's plane, with the fitted
    circle (a matplotlib `Figure`, made without pyplot: no global state, any backend)."""
    from matplotlib.figure import Figure

    names = [a.joint for a in result.arcs]
    cols = min(3, len(names))
    rows = int(np.ceil(len(names) / cols))
    fig = Figure(figsize=(4 * cols, 3.6 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for j, name in enumerate(names):
        ax = axes[j // cols][j % cols]
        g = arc_geometry(result, j)
        if not np.isfinite(g.radius):  # a prismatic joint: its travel, no arc
            ax.plot(g.u, g.v, ".", ms=4, color="tab:red", label="marker (PnP)")
            ax.set_title(f"{name}: travel {np.ptp(g.u):.1f} mm (lateral x1)", fontsize=9)
            ax.set_xlabel("mm along the fitted direction", fontsize=8)
            continue
        t = np.linspace(0, 2 * np.pi, 400)
        ax.plot(
            g.radius * np.cos(t),
            g.radius * np.sin(t),
            "-",
            lw=0.8,
            color="tab:blue",
            label="fitted arc",
        )
        ax.plot(g.u, g.v, ".", ms=4, color="tab:red", label="marker (PnP)")
        ax.plot([0], [0], "+", color="k")
        span = max(np.ptp(g.u), np.ptp(g.v), 20.0)
        ax.set_xlim(g.u.mean() - 0.7 * span, g.u.mean() + 0.7 * span)
        ax.set_ylim(g.v.mean() - 0.7 * span, g.v.mean() + 0.7 * span)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: r = {g.radius:.1f} mm", fontsize=9)
        ax.set_xlabel("mm (in the arc's plane)", fontsize=8)
        if j == 0:
            ax.legend(fontsize=7)
    for k in range(len(names), rows * cols):
        axes[k // cols][k % cols].axis("off")
    # Fixed margins (inches) rather than `tight_layout`, which draws the figure once more to measure it.
    _margins(fig, left=0.55, right=0.15, bottom=0.45, top=0.3, wspace=0.3, hspace=0.45)
    return fig


def plot_residuals(result):
    """Histograms of the radial and along-axis arc residuals of every frame (a `Figure`)."""
    from matplotlib.figure import Figure

    geometry = [arc_geometry(result, j) for j in range(len(result.arcs))]
    fig = Figure(figsize=(9, 3.4))
    ax = fig.subplots(1, 2)
    ax[0].hist(np.concatenate([g.radial for g in geometry]), bins=30, color="tab:blue", histtype="stepfilled")
    ax[0].set_title("radial residual (mm)", fontsize=9)
    ax[1].hist(
        np.concatenate([g.axial for g in geometry]), bins=30, color="tab:orange", histtype="stepfilled"
    )
    ax[1].set_title("along-axis residual (mm)", fontsize=9)
    _margins(fig, left=0.45, right=0.15, bottom=0.35, top=0.3, wspace=0.2)
    return fig


def plot_ee_errors(result):
    """End-effector error against the truth, nominal model vs calibrated, over the
    validation's random configurations (a `Figure`; `None` without a truth)."""
    if result.ee_errors is None:
        return None
    from matplotlib.figure import Figure

    before, after = result.ee_errors.before, result.ee_errors.after
    fig = Figure(figsize=(7, 3.6))
    ax = fig.subplots()
    bins = np.logspace(np.log10(max(min(after.min(), before.min()), 1e-3)), np.log10(before.max() * 1.1), 50)
    ax.hist(
        before,
        bins=bins,
        histtype="stepfilled",
        alpha=0.7,
        label=f"nominal model (RMS {np.sqrt(np.mean(before**2)):.2f} mm)",
    )
    two = result.ee_errors.two_stage if result.refinement is not None else None
    if two is not None:
        start = "two-stage" if result.kind.has_arcs else "closed-form start"
        ax.hist(
            two,
            bins=bins,
            histtype="stepfilled",
            alpha=0.6,
            label=f"{start} (RMS {np.sqrt(np.mean(two**2)):.3f} mm)",
        )
    label = "refined" if two is not None else "calibrated"
    ax.hist(
        after,
        bins=bins,
        histtype="stepfilled",
        alpha=0.7,
        label=f"{label} (RMS {np.sqrt(np.mean(after**2)):.3f} mm)",
    )
    ax.set_xscale("log")
    ax.set_xlabel(f"end-effector position error (mm), {len(before)} random configurations")
    ax.legend(fontsize=8)
    _margins(fig, left=0.55, right=0.15, bottom=0.5, top=0.15)
    return fig


def _plots(result, out: Path) -> list[tuple[str, str]]:
    figs = []
    for name, plot, caption in (
        ("arcs.png", plot_arcs, "Marker positions of every sweep in its fitted arc's plane"),
        ("residuals.png", plot_residuals, "Arc residuals of every frame (distance from the fitted circle)"),
        ("ee_error.png", plot_ee_errors, "End-effector error against the truth, before and after"),
    ):
        if plot is not plot_ee_errors and result.arc_fit is None:
            continue  # a pose-based capture has no arcs
        fig = plot(result)
        if fig is None:
            continue
        fig.savefig(out / name, dpi=110)
        figs.append((name, caption))
    return figs


def _camera_yaml(path: Path, name: str, T_cam_base, std, K, dist, *, T_flange_cam=None) -> None:
    """OpenCV YAML of one camera (`jaxcal.io.camera_yaml`): intrinsics and its pose. With
    `T_flange_cam` (eye-in-hand) the pose is the camera's on the flange, and `T_cam_base`
    holds the board's $T_{board,base}$ (written under that name)."""
    fields = [("camera_name", name)]
    if T_flange_cam is not None:
        fields += pose_fields("T_flange_cam", T_flange_cam, inverse="T_cam_flange")
    fixed, inverse = (
        ("T_cam_base", "T_base_cam") if T_flange_cam is None else ("T_board_base", "T_base_board")
    )
    # 1-sigma of the right-multiplied twist T = T0 @ exp(xi): tx ty tz (m), rx ry rz (rad).
    fields += pose_fields(fixed, T_cam_base, std, inverse=inverse)
    write_camera_yaml(path, fields + intrinsics_fields(K, dist))


def dh_tables(result) -> dict[str, PhysicalTable]:
    """The calibrated arm's DH and MDH tables with their standard deviations
    (`jaxcal.physical_table`); empty when a joint is prismatic or the result
    holds no estimate."""
    if not has_dh_tables(result):
        return {}
    return {c: physical_table(result, c) for c in ("dh", "mdh")}


def has_dh_tables(result) -> bool:
    """Whether `write_outputs` writes DH and MDH tables: an all-revolute arm and an estimate."""
    return result.estimate is not None and all(k == REVOLUTE for k in result.model.joint_types)


def dh_table_document(result, table: PhysicalTable) -> dict:
    """The `calibrated_{dh,mdh}.json` payload of one of `dh_tables`."""
    return dh_table_json(
        table.table,
        robot=Path(result.robot_urdf).stem,
        base_link=result.model.link_names[0],
        flange_link=result.model.link_names[-1],
        std=table.std_table,
        base_flange_std={k: v.tolist() for k, v in base_flange_std(table).items()},
        nominal=table.nominal_table,
        reduction_ratio=result.model.reduction_ratio,
        source=f"jaxcal calibrate of {result.dataset} (status {result.status}): the calibrated model's "
        "table; frames and the parallel-axis rule as in jaxcal._dh, std propagated from the estimate's covariance",
    )


def _dh_section(tables: dict[str, PhysicalTable]) -> list[str]:
    if "dh" not in tables:
        return []
    t = tables["dh"]
    tab, nom, sd = t.table, t.nominal_table, t.std_table
    lines = [
        "## DH table (standard DH, calibrated; `calibrated_dh.json`, MDH in `calibrated_mdh.json`)",
        "",
        "$A_i = R_z(\\theta_i + q_i) T_z(d_i) T_x(a_i) R_x(\\alpha_i) R_y(\\beta_i)$; the base and flange "
        "transforms are in the files. Rows marked *parallel* join axes within 10 degrees of parallel: "
        "there $d$ is ill-conditioned, so it is held at 0 and Hayati's $\\beta$ is estimated instead.",
        "",
        "| joint | theta deg | d mm | a mm | alpha deg | beta deg | row |",
        "| --- | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    deg, mm = np.degrees, lambda v: 1e3 * np.asarray(v)
    conv = {"theta": deg, "d": mm, "a": mm, "alpha": deg, "beta": deg}
    for i, j in enumerate(tab.joint_names):
        cells = []
        for c, f in conv.items():
            e, n, s_ = (float(f(np.asarray(getattr(x, c))[i])) for x in (tab, nom, sd))
            cells.append(f"{e:.3f} ± {s_:.3f} (nom {n:.3f})")
        lines.append(f"| {j} | " + " | ".join(cells) + f" | {'parallel' if tab.parallel[i] else ''} |")
    return lines + [""]


def _markdown(result, figs, tables=None, run=None) -> str:
    lines = [
        f"# jaxcal calibration of `{result.dataset}`",
        "",
        f"{result.kind.sensor.capitalize()} `{result.camera}`, "
        f"{result.kind.targets_label} {', '.join(f'`{t}`' for t in result.targets)}; "
        f"solvers: {'all successful' if result.ok else '**FAILED**'}; status **{result.status}**.",
        "",
    ]
    lines += made_by(run)
    if result.reasons:
        lines += ["## Why the result is " + result.status, ""] + [f"- {r}" for r in result.reasons] + [""]
    notes = () if result.verdict is None else result.verdict.notes
    if notes:
        lines += ["## Noted by the verdict", ""] + [f"- {n}" for n in notes] + [""]
    lines += (
        _point_fit_section(result)
        + _truth_section(result)
        + _refinement_section(result)
        + _terms_section(result)
        + _camera_section(result)
    )
    lines += _joints_section(result) + _dh_section(tables or {}) + _frames_section(result)
    lines += ["## Plots", ""]
    for name, caption in figs:
        lines += [f"![{caption}]({name})", "", f"*{caption}*", ""]
    return "\n".join(lines)


def _point_fit_section(result) -> list[str]:
    """Stop-and-shoot poses: the models tried, the samples rejected or merged, the unseen parameters."""
    pf = result.point_fit
    if pf is None:
        return []
    r = pf.residual_mm
    lines = [
        "## Point fit (stop-and-shoot poses)",
        "",
        f"{pf.poses} distinct poses"
        + (f" ({len(pf.repeats)} repeated samples merged into them)" if pf.repeats else "")
        + f", {int(pf.used.sum())} fitted; fitted residual {r.mean:.4f} mm mean, {r.rms:.4f} mm RMS, "
        f"{r.max:.4f} mm max; the residuals' robust scatter is {pf.robust_scale:.2f} times the samples' sigma.",
        "",
    ]
    if result.terms is None:  # with terms tried, the models are the terms section's table
        lines += [
            "| model | free parameters | CV mean mm | CV RMS mm | kept |",
            "| --- | ---: | ---: | ---: | --- |",
        ]
    for m in pf.models if result.terms is None else ():
        cv = [fmt(x, ".4f") if x is not None else "-" for x in (m.cv_mean_mm, m.cv_rms_mm)]
        lines.append(
            f"| {'+'.join(['geometric', *m.terms])} | {m.free} | {' | '.join(cv)} | {'yes' if m.kept else ''} |"
        )
    if pf.outliers:
        lines += [
            "",
            "Samples the robust point fit rejected (distance from the calibrated model's point; deletion "
            "residual in robust sigmas):",
            "",
            "| sample | line | distance mm | robust sigmas |",
            "| ---: | --- | ---: | ---: |",
        ]
        lines += [f"| {o.sample} | {o.line} | {o.distance_mm:.3f} | {o.radius:.1f} |" for o in pf.outliers]
    if pf.repeats:
        shown = ", ".join(f"{p.sample} (= {p.of_sample})" for p in pf.repeats)
        lines += [
            "",
            f"Samples repeating an earlier sample's joint positions, merged into its pose: {shown}.",
        ]
    if pf.unseen:
        lines += ["", f"Held at nominal because the samples cannot see them: {', '.join(pf.unseen)}."]
    if pf.prior is not None:
        share = np.asarray(pf.prior.share)
        most = np.argsort(-share)[:3]
        lines += [
            "",
            f"A fleet's prior ({pf.prior.file}, learnt on {pf.prior.units} units) covers {len(share)} "
            f"parameters; of their information it gave {share.mean():.0%} on average (the data the rest), "
            "most to " + ", ".join(f"{pf.prior.names[i]} ({share[i]:.0%})" for i in most) + ".",
        ]
    return lines + [""]


def _truth_section(result) -> list[str]:
    table = truth_table(result)
    if table is None:
        return []
    c = result.validation.T_cam_base_error
    return [
        "## Against the truth (synthetic dataset)",
        "",
        *table.markdown(),
        "",
        *((line, "") if (line := truth_line(result)) is not None else ()),
        f"{result.kind.fixed_frame} error in the estimator's gauge ({c.gauge}); against the truth's own "
        f"pose: {c.raw_trans_mm:.3f} mm, {c.raw_rot_deg:.4f} deg.",
        "",
    ]


def _refinement_section(result) -> list[str]:
    v = result.validation
    ref = result.refinement
    if ref is None:
        return []
    lines = [
        "## Refinement (reprojection of every corner)",
        "",
        refinement_line(result),
        "",
        "Frames whose corners stay outliers: "
        + (", ".join(str(f) for f in ref.outlier_frames) if ref.outlier_frames else "none"),
        "",
        "Correlations above 0.95: "
        + (
            "; ".join(f"{p.a} / {p.b} ({p.rho:+.3f})" for p in ref.correlations)
            if ref.correlations
            else "none"
        ),
        "",
        "Unidentifiable directions at the solution: "
        + (
            "; ".join(", ".join(r.name for r in w.parameters) for w in ref.weak_directions)
            if ref.weak_directions
            else "none beyond the parameters held at nominal"
        ),
        "",
    ]
    if v is not None and v.T_cam_base_error_two_stage is not None:
        c2 = v.T_cam_base_error_two_stage
        lines += [
            f"Two-stage {'T_board_base' if result.eye_in_hand else 'T_cam_base'} error: "
            f"{c2.trans_mm:.3f} mm, {c2.rot_deg:.4f} deg.",
            "",
        ]
    return lines


def _terms_section(result) -> list[str]:
    """The non-geometric terms tried, kept and estimated (`summary.terms_tables`), and notes."""
    tables = terms_tables(result)
    if not tables:
        return (
            [f"- {n}" for n in result.terms.notes] + [""]
            if result.terms is not None and result.terms.notes
            else []
        )
    lines = ["## Non-geometric terms", ""]
    for table in tables:
        lines += [f"**{table.title}**", "", *table.markdown(), ""]
    if result.terms.kept:
        lines += [
            "The kept terms move each joint off where the rigid model (`calibrated.urdf`) puts it; "
            "`compensation.json` holds them for the robot side (`jaxcal.compensate`).",
            "",
        ]
    return lines + [f"- {n}" for n in result.terms.notes] + ([""] if result.terms.notes else [])


def _pose_line(T: PoseFigures) -> str:
    return (
        f"translation {np.round(T.xyz_m * 1e3, 3).tolist()} mm "
        f"(std {np.round(T.std_xyz_mm, 3).tolist()} mm, {np.round(T.std_rot_deg, 4).tolist()} deg)"
    )


def _camera_section(result) -> list[str]:
    v = result.validation
    fixed = result.kind.fixed_frame
    T = pose_figures(result.T_cam_base, result.std_cam)
    lines = [
        f"## {result.kind.sensor.capitalize()} pose",
        "",
        *(
            [
                f"Eye-in-hand: camera {result.camera} on the flange, board {result.board} in the world. "
                f"T_flange_cam translation {np.round(result.T_flange_target[0][:3, 3] * 1e3, 3).tolist()} mm "
                "(its standard deviations are the mount rows of the parameter table).",
                "",
            ]
            if result.eye_in_hand
            else []
        ),
        f"{fixed} {_pose_line(T)}; quaternion (xyzw) {np.round(T.quaternion_xyzw, 6).tolist()}.",
        "",
    ]
    errs = {e.camera: e for e in (v.other_cameras or ())} if v is not None else {}
    for c in result.other_cameras:
        line = (
            f"Camera {c.camera} ({c.views} views, refined with the robot): T_cam_base "
            f"{_pose_line(pose_figures(c.T_cam_base, c.std_cam))}."
        )
        if c.camera in errs:
            e = errs[c.camera]
            line += (
                f" Pose relative to {result.camera} vs the truth: {e.refined.trans_mm:.3f} mm, "
                f"{e.refined.rot_deg:.4f} deg (start from PnP: {e.start.trans_mm:.3f} mm, "
                f"{e.start.rot_deg:.4f} deg)."
            )
        lines += [line, ""]
    return lines + [clock_line(result), ""]


def _joints_section(result) -> list[str]:
    lines = ["## Joints", "", *joints_table(result).markdown()]
    for a in result.arcs:
        if a.scale is not None:
            lines += [
                "",
                f"{a.joint} is prismatic: its ratio is in motor rad per m; the scale (true travel per "
                f"commanded travel) is {a.scale:.6f} +- {a.scale_std:.6f} over {a.travel_mm:.1f} mm.",
            ]
    rejected = [(a.joint, o) for a in result.arcs for o in a.outliers]
    if rejected:
        lines += [
            "",
            "Samples the robust arc fits rejected (whitened residual in noise units):",
            "",
            "| joint | target | frame | time s | residual |",
            "| --- | --- | ---: | ---: | ---: |",
        ]
        lines += [
            f"| {j} | {o.target} | {o.frame} | {o.timestamp_s:.3f} | {o.residual:.1f} |" for j, o in rejected
        ]
    lines += [
        "",
        "## Parameters (nominal, estimate, standard deviation)",
        "",
        "| parameter | unit | nominal | estimate | std | estimated |",
        "| --- | --- | ---: | ---: | ---: | --- |",
    ]
    for p in result.parameters:
        lines.append(
            f"| {p.name} | {p.unit} | {p.nominal:.6f} | {p.estimate:.6f} | {p.std:.2e} | "
            f"{'yes' if p.free else 'held at nominal'} |"
        )
    lines += [
        "",
        "## Identifiability",
        "",
        f"Held at nominal (the {result.kind.sensor} cannot see them): " + ", ".join(result.frozen),
        "",
        "These are the estimator's corrections: `origin.tx` .. `origin.rz` move and turn a joint's frame "
        "(a twist, m and rad), where the table above gives the frame's resulting URDF origin (`x` .. `yaw`).",
        "",
    ]
    return lines


def _frames_section(result) -> list[str]:
    f = result.frames
    lines = [
        "## Frames",
        "",
        f"{f.images} images; target found in {f.target_found}; {f.no_target} without a target, "
        f"{f.outside_encoder_log} outside the encoder log, {f.not_in_a_sweep} in no single-joint sweep; "
        f"dropped capture indices: {len(f.dropped_capture_indices)}.",
        "",
    ]
    if result.warnings:
        lines += ["## Notes", ""] + [f"- {w}" for w in result.warnings] + [""]
    return lines


def write_outputs(result, out, *, overwrite: bool = False, inputs=None, checked=None, run=None) -> Path:
    """Write `result` into directory `out` (atomically): `result.json`,
    `calibrated.urdf`, `estimate.npz` (the final solve's vector, covariance and
    references: `jaxcal.io.result.write_estimate`), `camera_<name>.yaml`, the camera's pose for ROS
    (`ros_<name>.launch.yaml`, `ros_<name>.txt`, `easy_handeye_<name>.yaml`),
    for a UR arm `ur_calibration.yaml` (`jaxcal.io.robot_files`), for a
    revolute arm the calibrated DH and MDH tables with their standard
    deviations (`calibrated_dh.json`, `calibrated_mdh.json`: `jaxcal.io.dh_tables`),
    `report.md` and its PNG plots.

    `out` may not be, contain or lie inside the dataset or any of `inputs`
    (default: the result's dataset); an existing non-empty `out` is replaced
    only with `overwrite` and only when it is a result jaxcal wrote (its
    `.jaxcal` marker). `checked`: the `jaxcal.io._files.OutputDir` found when
    the run started, so that a directory that appeared since is refused (see
    `jaxcal.io._files.atomic_directory`). `run`: how the result was made (the command line's
    `jaxcal.cli._common.run_record`), kept as `result.json`'s `run` and named in `report.md`.
    Raises `OutputError` naming `out`.
    """
    out = Path(out)
    inputs = (result.dataset,) if inputs is None else tuple(inputs)
    with (
        atomic_directory(out, overwrite=overwrite, inputs=inputs, kind="result", checked=checked) as tmp,
        ThreadPoolExecutor(1, thread_name_prefix="jaxcal tables") as pool,
    ):
        # The DH tables compile their Jacobian (seconds, mostly without Python's lock):
        # on a thread of their own while the other files and the plots are written.
        tables_pending = pool.submit(dh_tables, result)
        write_json(tmp / "result.json", finite_json(result.to_json() | ({} if run is None else {"run": run})))
        if result.estimate is not None:
            write_estimate(tmp / ESTIMATE_FILE, result.estimate)
        # A dataset whose robot is a DH/MDH table has no URDF to copy: a minimal one from the model.
        source = None if is_table_file(result.robot_urdf) else result.robot_urdf
        save_urdf(result.model, tmp / "calibrated.urdf", source=source)
        if not result.kind.images:
            _device_files(tmp, result)
        else:
            _camera_files(tmp, result)
        if is_ur(result.model):
            (tmp / "ur_calibration.yaml").write_text(ur_kinematics_text(result.model, result.nominal)[0])
        comp = compensation_of(result)
        if comp is not None:
            write_json(tmp / COMPENSATION_FILE, finite_json(compensation_json(comp)))
        figs = _plots(result, tmp)
        tables = tables_pending.result()
        for convention, table in tables.items():
            write_json(tmp / f"calibrated_{convention}.json", finite_json(dh_table_document(result, table)))
        (tmp / "report.md").write_text(_markdown(result, figs, tables, run))
    return out


def certificate_section(c) -> list[str]:
    """`report.md`'s section of an accuracy certificate (`jaxcal.records_check.Certificate`)."""
    s, e = c.summary, c.extrapolation
    worst = ", ".join(f"{np.degrees(v):.1f}" for v in s.worst.q)
    lines = [
        "## Accuracy certificate",
        "",
        f"The tool point's predicted error over the task region ({c.region.kind.replace('_', ' ')}, "
        f"{s.poses} poses, {c.frame} frame), from the calibration's covariance (`jaxcal certify`; "
        "`certificate.json` holds every pose):",
        "",
        "| mean | RMS | 95 % of the region within | worst pose's 95 % bound |",
        "| --- | --- | --- | --- |",
        f"| {s.mean_mm:.4f} mm | {s.rms_mm:.4f} mm | {s.p95_mm:.4f} mm | "
        f"{s.max_bound95_mm:.4f} mm at q = [{worst}] deg |",
        "",
    ]
    if e is not None:
        lines += [
            f"Calibrated workspace: {100 * e.share_of_poses_outside_joint_ranges:.0f} % of the region's poses "
            f"outside its joint ranges (up to {np.degrees(e.max_joint_excess):.1f} deg); predicted error "
            f"{e.error_ratio:.2f}x that over the calibrated configurations.",
            "",
        ]
    lines += [f"- caveat: {w}" for w in c.caveats] + [f"- note: {n}" for n in c.notes]
    return lines + ([""] if c.caveats or c.notes else [])


#: `write_ros_camera_files`' files per camera: `<kind>_<camera>.<ext>`.
ROS_CAMERA_FILES = (("ros", "launch.yaml"), ("ros", "txt"), ("easy_handeye", "yaml"))


def output_files(result) -> list[str]:
    """The files `write_outputs` writes besides `report.md` and its plots."""
    names = ["result.json", "calibrated.urdf"] + ([ESTIMATE_FILE] if result.estimate is not None else [])
    if not result.kind.images:
        if result.kind.fixed_frame_free:
            names += [f"ros_{result.camera}.launch.yaml", f"ros_{result.camera}.txt"]
    else:
        cams = [result.camera] + [c.camera for c in result.other_cameras]
        names += [f"camera_{c}.yaml" for c in cams]
        names += [f"{kind}_{c}.{ext}" for c in cams for kind, ext in ROS_CAMERA_FILES]  # every camera's
    names += ["ur_calibration.yaml"] if is_ur(result.model) else []
    names += [COMPENSATION_FILE] if compensation_of(result) is not None else []
    return names + (["calibrated_dh.json", "calibrated_mdh.json"] if has_dh_tables(result) else [])


def _device_files(tmp: Path, result) -> None:
    """A measuring device's pose in the base link as a ROS static transform (not with `device_is_base`)."""
    if result.kind.fixed_frame_free:
        write_static_transform(
            tmp,
            result.camera,
            np.linalg.inv(np.asarray(result.T_cam_base, np.float64)),
            result.model.link_names[0],
            result.camera,
            f"jaxcal calibration ({result.kind.describe()}, status {result.status})",
        )


def _camera_files(tmp: Path, result) -> None:
    """Each camera's OpenCV YAML and its pose for ROS."""
    _camera_yaml(
        tmp / f"camera_{result.camera}.yaml",
        result.camera,
        result.T_cam_base,
        result.std_cam,
        result.intrinsics.K,
        result.intrinsics.distortion,
        T_flange_cam=result.T_flange_target[0] if result.eye_in_hand else None,
    )
    for c in result.other_cameras:
        _camera_yaml(
            tmp / f"camera_{c.camera}.yaml",
            c.camera,
            c.T_cam_base,
            c.std_cam,
            c.K,
            c.distortion,
        )
    write_ros_camera_files(tmp, result)
