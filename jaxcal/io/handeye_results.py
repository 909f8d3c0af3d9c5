"""Writing a hand-eye calibration: `result.json`, the camera pose for OpenCV, ROS and easy_handeye, `report.md`.

```
OUT/
  result.json                      everything (see `hand_eye_summary`)
  camera_<name>.yaml               OpenCV FileStorage: T_robot_cam, K, distortion, std
  ros_<name>.launch.yaml           ROS 2 launch file: a tf2_ros static_transform_publisher
  ros_<name>.txt                   its command line (ROS 2 and ROS 1 argument orders)
  easy_handeye_<name>.yaml         easy_handeye's calibration file (frames, translation, quaternion xyzw)
  report.md, residuals.png, consistency.png
```

The directory is written atomically (`jaxcal.io._files.atomic_directory`).
"""

import json
from pathlib import Path

import jax
import numpy as np

from .._device import result_is
from .._npgeom import matrix_to_quaternion
from . import ros
from ._files import atomic_directory
from ._provenance import made_by
from .camera_yaml import intrinsics_fields, pose_fields, write_camera_yaml

#: `result.json`'s schema for a `jaxcal handeye` result (what `jaxcal check` recognises).
HANDEYE_RESULT_SCHEMA = "jaxcal.handeye_result"


def _code(code) -> str:
    if result_is(code):
        return "successful"
    if result_is(code, "nonlinear_max_steps_reached"):
        return "max_steps_reached"
    return "failed"


def _index(code, i: int):
    return jax.tree.map(lambda x: x[i], code)


def _std(std6) -> dict:
    std6 = np.asarray(std6)
    return {"translation_mm": (1e3 * std6[:3]).tolist(), "rotation_deg": np.degrees(std6[3:]).tolist()}


def _transform(T) -> dict:
    T = np.asarray(T)
    return {
        "matrix": T.tolist(),
        "translation_m": T[:3, 3].tolist(),
        "quaternion_xyzw": matrix_to_quaternion(T[:3, :3]).tolist(),
    }


def camera_frames(run, c: int) -> tuple[str, str]:
    """`(parent, child)` frame names of camera `c`'s pose: the flange (eye-in-hand) or base, and the camera."""
    cap = run.capture
    return (cap.ee_frame if cap.eye_in_hand else cap.base_frame), cap.cameras[c].frame_id


def _camera_entry(run, c: int) -> dict:
    """Camera `c`'s block of `result.json`: its pose with std and k-fold spread, intrinsics, size,
    what `jaxcal check` needs, and the error against the truth when known."""
    cap, r = run.capture, run.result
    cam = cap.cameras[c]
    parent, child = camera_frames(run, c)
    entry = {
        "parent_frame": parent,
        "child_frame": child,
        "T_robot_cam": _transform(r.T_robot_cam[c]),
        "T_cam_robot": np.asarray(r.T_cam_robot[c]).tolist(),
        "std": _std(r.std_robot_cam[c]),
        "intrinsics": {
            "K": np.asarray(run.intrinsics[c].K).tolist(),
            "distortion": np.asarray(run.intrinsics[c].distortion).tolist(),
            "source": run.intrinsics[c].source,
            "rms_px": run.intrinsics[c].rms_px,
        },
        "views": int(run.detected[c].sum()),
        "width": cam.width,
        "height": cam.height,
        "check": _check_block(r, c, len(cap.cameras)),
        # The images' scale against the robot's (1: the target's size and K agree with the arm's
        # motion) and the lens test (`jaxcal.handeye._verdict`), where the capture allows them.
        **run.checks.get(cam.name, {}),
    }
    if run.kfold is not None:
        entry["kfold_std"] = _std(run.kfold.std_robot_cam[c])
        t = np.linalg.norm(run.kfold.std_robot_cam[c, :3]) / max(
            np.linalg.norm(r.std_robot_cam[c, :3]), 1e-300
        )
        w = np.linalg.norm(run.kfold.std_robot_cam[c, 3:]) / max(
            np.linalg.norm(r.std_robot_cam[c, 3:]), 1e-300
        )
        entry["kfold_over_std"] = {"translation": float(t), "rotation": float(w)}
    if run.truth_error is not None:
        entry["truth_error"] = {
            "translation_mm": float(1e3 * run.truth_error[c, 0]),
            "rotation_deg": float(np.degrees(run.truth_error[c, 1])),
        }
    return entry


def hand_eye_summary(run) -> dict:
    """Everything `result.json` holds: status, transforms with std and k-fold spread, per-frame residuals,
    rejected frames with reasons, the consistency check, the solver's stages, and the truth when known."""
    cap, r, obs = run.capture, run.result, run.observations
    F = obs.frames
    sigma = obs.sigma_px
    cams = {cam.name: _camera_entry(run, c) for c, cam in enumerate(cap.cameras)}
    frames = []
    rms = np.asarray(r.group_rms)[:, :F] * sigma
    robot_rms = np.asarray(r.robot_rms)[:F]
    for f, name in enumerate(cap.frames):
        frames.append(
            {
                "frame": name,
                "detected": {cam.name: bool(run.detected[c, f]) for c, cam in enumerate(cap.cameras)},
                "rms_px": {
                    cam.name: (None if not np.isfinite(rms[c, f]) else float(rms[c, f]))
                    for c, cam in enumerate(cap.cameras)
                },
                "robot_correction_sigma": None if not np.isfinite(robot_rms[f]) else float(robot_rms[f]),
                "rejected": f in run.rejected,
                "reason": run.rejected.get(f),
                "inconsistent_rotation": bool(obs.consistency.inconsistent[f]),
            }
        )
    mc = obs.consistency
    return {
        "schema": HANDEYE_RESULT_SCHEMA,
        "schema_version": 1,
        "status": run.verdict.status,
        "reasons": list(run.verdict.reasons),
        "notes": list(run.verdict.notes),
        "arrangement": cap.arrangement,
        "capture": str(cap.root),
        "target": {
            "spec": cap.target.to_dict(),
            "parent_frame": cap.base_frame if cap.eye_in_hand else cap.ee_frame,
            "T_robot_target": _transform(r.T_robot_board),
            "std": _std(r.std_robot_board),
            "kfold_std": None if run.kfold is None else _std(run.kfold.std_robot_board),
            "symmetric_views_turned": [
                {"camera": cap.cameras[c].name, "frame": cap.frames[f], "degrees": a}
                for c, f, a in obs.turned
            ],
        },
        "cameras": cams,
        "rejected_frames": [
            {
                "frame": cap.frames[f],
                "cameras": [cap.cameras[c].name for c in np.flatnonzero(np.asarray(r.rejected)[:, f])],
                "reason": why,
            }
            for f, why in sorted(run.rejected.items())
        ],
        "frames": frames,
        "robot_noise": _robot_noise(r),
        "robot_noise_model": _robot_noise_model(run),
        "held_out": _held_out(run.noise.fit.held_out),
        "consistency": {
            "tolerance_deg": mc.tolerance_deg,
            "disagreeing_fraction": mc.disagreeing_fraction,
            "median_difference_deg": mc.median_error_deg,
            "mean_difference_deg": mc.mean_error_deg,
            "inconsistent_frames": [cap.frames[f] for f in mc.inconsistent_frames()],
        },
        "kfold": None
        if run.kfold is None
        else {
            "folds": run.kfold.folds,
            "converged": np.asarray(run.kfold.converged).tolist(),
            "fold_frames": [[cap.frames[f] for f in fold] for fold in run.kfold.fold_frames],
        },
        "solver": {
            "stages": [
                {
                    "name": name,
                    "result": _code(_index(r.stage_result, i)),
                    "steps": int(np.asarray(r.stage_steps)[i]),
                }
                for i, name in enumerate(("robust", "plain"))
            ],
            "max_steps": run.max_steps,
            "pixel_rms_px": float(r.pixel_rms),
            "sigma_px": sigma,
            "variance_factor": float(r.variance_factor),
            "frames": F,
            "padded_frames": int(np.shape(r.T_base_ee)[0]),
        },
        "seconds": run.seconds,
    }


def _check_block(r, c: int, cameras: int) -> dict:
    """What `jaxcal check` needs of camera `c`: the joint covariance of the camera's and the
    target's tangent deltas ($X = \\hat X \\exp(\\xi_X)$, $Y = \\hat Y \\exp(\\xi_Y)$, 12 x 12), from
    the solve's model and its frame-robust (cluster) covariance."""
    idx = np.r_[6 * c : 6 * c + 6, 6 * cameras : 6 * cameras + 6]
    block = lambda m: np.asarray(m)[np.ix_(idx, idx)].tolist()  # noqa: E731
    return {
        "parameters": "T_cam_robot = T_cam_robot_hat exp(xi_cam), T_robot_target = T_robot_target_hat exp(xi_target); "
        "xi = (translation m, rotation rad)",
        "covariance": block(r.cov),
        "covariance_frames": block(r.cov_frames),
    }


def _robot_noise(r) -> "dict | None":
    """Per axis, the robot pose noise the solve used: estimated from the data or given; None: exact poses."""
    if r.robot_sigma is None:
        return None
    noise = np.asarray(r.robot_sigma)
    return {
        "estimated": bool(np.all(np.asarray(r.robot_sigma_estimated))),
        "translation_mm": float(1e3 * noise[0]),
        "rotation_deg": float(np.degrees(noise[3])),
        "dof": None if r.robot_dof is None else np.asarray(r.robot_dof, float).tolist(),
    }


def _robot_noise_model(run) -> dict:
    """The robot-noise model kept, what was asked, why, and every model solved with its held-out
    reprojection (per camera `T_robot_cam` too, to compare them)."""
    choice = run.noise
    return {
        "model": choice.fit.model,
        "asked": choice.setting.mode,
        "basis": choice.basis,
        "models": [
            {
                "model": f.model,
                "chosen": k == choice.chosen,
                "robot_noise": _robot_noise(f.result),
                "held_out_rms_px": None if f.held_out is None else f.held_out.rms_px,
                "in_sample_rms_px": float(f.result.pixel_rms),
                "rejected_frames": int(np.asarray(f.result.rejected).any(0).sum()),
                "T_robot_cam": {
                    cam.name: _transform(np.asarray(f.result.T_robot_cam)[c])
                    for c, cam in enumerate(run.capture.cameras)
                },
            }
            for k, f in enumerate(choice.fits)
        ],
    }


def _held_out(held) -> "dict | None":
    """The kept model's held-out reprojection beside its in-sample one, and the robot pose noise it reads as."""
    if held is None:
        return None
    return {
        "rms_px": held.rms_px,
        "in_sample_rms_px": held.in_sample_px,
        "sigma_px": held.sigma_px,
        "folds": held.folds,
        "frames": held.frames,
        "px_per_1mm_0.1deg": held.scale_px,
        "robot_noise_level": dict(zip(("translation_mm", "rotation_deg"), held.noise)),
    }


# --------------------------------------------------------------------------- camera pose files


def write_opencv_yaml(path: Path, run, c: int) -> None:
    """OpenCV FileStorage YAML (`jaxcal.io.camera_yaml`): `T_robot_cam` (4x4), `K`, `distortion`,
    `std` (6: m, rad) and the frames."""
    parent, child = camera_frames(run, c)
    cam, intrinsics = run.capture.cameras[c], run.intrinsics[c]
    fields = [("arrangement", run.capture.arrangement), ("parent_frame", parent), ("child_frame", child)]
    fields += pose_fields(
        "T_robot_cam", run.result.T_robot_cam[c], run.result.std_robot_cam[c], std_key="std_robot_cam"
    )
    fields += intrinsics_fields(intrinsics.K, intrinsics.distortion, keys=("K", "distortion"))
    fields += [("image_width", cam.width), ("image_height", cam.height), ("status", run.verdict.status)]
    write_camera_yaml(path, fields)


def static_transform_args(run, c: int) -> dict:
    """The `static_transform_publisher` argument lines of camera `c`'s pose (see `jaxcal.io.ros`)."""
    return ros.static_transform_args(run.result.T_robot_cam[c], *camera_frames(run, c))


def ros2_static_transform_args(run, c: int) -> str:
    """ROS 2's `static_transform_publisher` arguments (named flags) of camera `c`'s pose."""
    return static_transform_args(run, c)["ros2"]


def write_ros(folder: Path, run, c: int) -> None:
    """Camera `c`'s pose as a ROS static transform and as easy_handeye's YAML."""
    cap, name = run.capture, run.capture.cameras[c].name
    T = run.result.T_robot_cam[c]
    comment = f"jaxcal hand-eye calibration ({cap.arrangement}, status {run.verdict.status})"
    ros.write_static_transform(folder, name, T, *camera_frames(run, c), comment)
    ros.write_easy_handeye(
        folder / f"easy_handeye_{name}.yaml",
        T,
        eye_on_hand=cap.eye_in_hand,
        base_frame=cap.base_frame,
        effector_frame=cap.ee_frame,
        camera_frame=cap.cameras[c].frame_id,
        marker_frame=cap.target_frame,
    )


# --------------------------------------------------------------------------- report


def plot_residuals(run):
    """Per-frame reprojection RMS per camera (px; rejected frames in red, undetected marked) and
    each frame's median robot-versus-camera rotation-angle difference (a matplotlib `Figure`, no pyplot)."""
    from matplotlib.figure import Figure

    cap, r, obs = run.capture, run.result, run.observations
    F = obs.frames
    rms = np.asarray(r.group_rms)[:, :F] * obs.sigma_px
    rejected = np.asarray(r.rejected)[:, :F]
    C = len(cap.cameras)
    fig = Figure(figsize=(max(6.0, 0.28 * F + 2.0), 2.6 * (C + 1)))
    axes = fig.subplots(C + 1, 1, squeeze=False)[:, 0]
    x = np.arange(F)
    for c, cam in enumerate(cap.cameras):
        ax = axes[c]
        y = np.nan_to_num(rms[c], nan=0.0)
        colours = np.where(rejected[c], "tab:red", "tab:blue")
        ax.bar(x, y, color=colours)
        missing = ~run.detected[c]
        ax.plot(x[missing], np.zeros(missing.sum()), "x", color="k", label="target not found")
        ax.axhline(obs.sigma_px, color="k", lw=0.8, ls="--", label=f"detector noise {obs.sigma_px:.3g} px")
        ax.set_ylabel("RMS px")
        ax.set_title(f"camera {cam.name}: reprojection RMS per frame (red: rejected)")
        ax.legend(loc="upper right", fontsize=7)
    ax = axes[-1]
    pair = obs.consistency.pair_error_deg
    diff = np.array([np.median(row[np.isfinite(row)]) if np.isfinite(row).any() else 0.0 for row in pair])
    ax.bar(
        x,
        np.nan_to_num(diff[:F], nan=0.0),
        color=np.where(obs.consistency.inconsistent[:F], "tab:red", "tab:green"),
    )
    ax.axhline(obs.consistency.tolerance_deg, color="k", lw=0.8, ls="--", label="tolerance")
    ax.set_ylabel("deg")
    ax.set_title("median |robot - camera| relative rotation angle with the other frames")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_xticks(x)
    ax.set_xticklabels(cap.frames, rotation=90, fontsize=6)
    for a in axes[:-1]:
        a.set_xticks(x)
        a.set_xticklabels([])
    fig.tight_layout()
    return fig


def _fmt(v, digits=3) -> str:
    return f"{v:.{digits}f}"


def _model_sentence(m: dict) -> str:
    return f"model `{m['model']}` (asked: `{m['asked']}`; {m['basis'].split(' (')[0]}), "


def _model_table(s: dict) -> list[str]:
    """The robot-noise models solved, held out against in-sample, and the kept model's held-out figure."""
    lines = []
    h = s["held_out"]
    if h is not None:
        level = h["robot_noise_level"]
        lines += [
            f"Held out ({h['folds']} folds of consecutive frames, {h['frames']} frames, each predicted from its "
            f"reported robot pose): {_fmt(h['rms_px'])} px RMS against {_fmt(h['in_sample_rms_px'])} px in-sample "
            f"and the detector's {_fmt(h['sigma_px'])} px; robot pose noise of at most about "
            f"{_fmt(level['translation_mm'], 2)} mm / {_fmt(level['rotation_deg'], 3)} deg per axis.",
            "",
        ]
    models = s["robot_noise_model"]["models"]
    if len(models) > 1:
        lines += [
            "| robot-noise model | noise per axis | held out (px) | in-sample (px) | rejected frames | kept |"
        ]
        lines += ["| --- | --- | --- | --- | --- | --- |"]
        for m in models:
            rn = m["robot_noise"]
            noise = (
                "exact"
                if rn is None
                else f"{_fmt(rn['translation_mm'])} mm / {_fmt(rn['rotation_deg'], 4)} deg"
            )
            held = "n/a" if m["held_out_rms_px"] is None else _fmt(m["held_out_rms_px"])
            lines.append(
                f"| {m['model']} | {noise} | {held} | {_fmt(m['in_sample_rms_px'])} | {m['rejected_frames']} | "
                f"{'**yes**' if m['chosen'] else ''} |"
            )
        lines.append("")
    return lines


def report_markdown(summary: dict) -> str:
    s = summary
    lines = [
        "# jaxcal hand-eye calibration",
        "",
        f"Capture `{s['capture']}` ({s['arrangement'].replace('_', '-')}), status **{s['status']}**.",
        "",
    ]
    lines += made_by(s.get("run"))
    if s["reasons"]:
        lines += ["Why it is suspect:", ""] + [f"- {x}" for x in s["reasons"]] + [""]
    if s["notes"]:
        lines += ["Notes:", ""] + [f"- {x}" for x in s["notes"]] + [""]
    lines += [
        "| camera | pose of | in | t (mm) | quaternion xyzw | std t (mm) | std rot (deg) | k-fold t (mm) | k-fold rot (deg) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, c in s["cameras"].items():
        t = np.asarray(c["T_robot_cam"]["translation_m"]) * 1e3
        kf = c.get("kfold_std")
        lines.append(
            f"| {name} | {c['child_frame']} | {c['parent_frame']} | {np.round(t, 2).tolist()} | "
            f"{np.round(c['T_robot_cam']['quaternion_xyzw'], 5).tolist()} | "
            f"{_fmt(np.linalg.norm(c['std']['translation_mm']))} | {_fmt(np.linalg.norm(c['std']['rotation_deg']), 4)} | "
            + (
                f"{_fmt(np.linalg.norm(kf['translation_mm']))} | {_fmt(np.linalg.norm(kf['rotation_deg']), 4)} |"
                if kf
                else "n/a | n/a |"
            )
        )
    lines += [
        "",
        "Standard deviations are the norms of the three components (translation in the parent frame, "
        "rotation as a parent-frame rotation vector); the k-fold column is the jackknife spread over "
        f"{s['kfold']['folds'] if s['kfold'] else 0} folds of consecutive frames.",
        "",
    ]
    for name, c in s["cameras"].items():
        if "truth_error" in c:
            e = c["truth_error"]
            lines.append(
                f"Synthetic capture: camera {name} is off the truth by {_fmt(e['translation_mm'])} mm, {_fmt(e['rotation_deg'], 4)} deg."
            )
    sv = s["solver"]
    stages = ", ".join(f"{x['name']} {x['result']} in {x['steps']} steps" for x in sv["stages"])
    lines += [
        "",
        f"Solver: {stages}; reprojection RMS {_fmt(sv['pixel_rms_px'])} px against the detector's "
        f"{_fmt(sv['sigma_px'])} px (variance factor {_fmt(sv['variance_factor'], 2)}); {sv['frames']} frames.",
        "",
        "Robot pose noise: "
        + _model_sentence(s["robot_noise_model"])
        + (
            "exact poses."
            if s["robot_noise"] is None
            else f"{_fmt(s['robot_noise']['translation_mm'])} mm / {_fmt(s['robot_noise']['rotation_deg'], 4)} deg "
            f"per axis ({'estimated from the data' if s['robot_noise']['estimated'] else 'as given'})."
        ),
        "",
        f"Rotation-angle check: {100 * s['consistency']['disagreeing_fraction']:.0f}% of frame pairs differ by more "
        f"than {s['consistency']['tolerance_deg']:g} deg (median {_fmt(s['consistency']['median_difference_deg'])} deg).",
        "",
    ]
    lines += _model_table(s)
    if s["rejected_frames"]:
        lines += ["| rejected frame | cameras | reason |", "| --- | --- | --- |"]
        lines += [
            f"| {x['frame']} | {', '.join(x['cameras'])} | {x['reason']} |" for x in s["rejected_frames"]
        ]
        lines.append("")
    lines += ["![per-frame residuals](residuals.png)", ""]
    return "\n".join(lines)


def write_hand_eye_outputs(run, out, *, overwrite: bool = False, checked=None, made=None) -> Path:
    """Write every output of `run` (a `HandEyeRun`) into directory `out`, atomically.

    `out` may not be, contain or lie inside the capture; `overwrite` replaces
    only a result jaxcal wrote (see `jaxcal.io._files.atomic_directory`). `made`: how the
    result was made (`jaxcal.io._provenance.run_record`), kept as `result.json`'s `run`.

    **Returns:** `out`.
    """
    summary = hand_eye_summary(run) | ({} if made is None else {"run": made})
    inputs = (run.capture.root,)
    with atomic_directory(out, overwrite=overwrite, inputs=inputs, kind="result", checked=checked) as tmp:
        (tmp / "result.json").write_text(json.dumps(summary, indent=1) + "\n")
        for c, cam in enumerate(run.capture.cameras):
            write_opencv_yaml(tmp / f"camera_{cam.name}.yaml", run, c)
            write_ros(tmp, run, c)
        plot_residuals(run).savefig(tmp / "residuals.png", dpi=110)
        (tmp / "report.md").write_text(report_markdown(summary))
    return Path(out)
