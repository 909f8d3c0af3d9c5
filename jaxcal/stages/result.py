"""Stage 7, result: the stage records assembled into one immutable `CalibrationResult`."""

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from .._arcfit import ArcFitResult
from .._axisfit import AxisFitResult
from .._correction import Estimate
from .._kinematics import KinematicModel
from .._pointfit import PointFitResult
from .._refine import RefineResult
from ..io.dataset import Dataset
from ..io.result import result_to_json
from ..records import (
    ArcRow,
    Clock,
    EEErrors,
    FrameCounts,
    Intrinsics,
    OtherCamera,
    ParameterRow,
    RatioRow,
    RefinementSummary,
    SolverInfo,
    TermsSummary,
    ValidationReport,
)
from ._observe import Observations
from ._points import PointFit
from ._refine import Refined, succeeded
from ._setup import Setup
from ._synchronise import Sweeps, Sync
from ._terms import TermFit
from ._two_stage import TwoStage, result_name
from ._validate import Validation
from ._verdict import Verdict
from .kinds import CaptureKind


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Everything `calibrate` found (NumPy arrays, the calibrated `KinematicModel` and
    the typed records of `jaxcal.records`; each also reads as its `result.json` block,
    `result.clock["offset_s"]`, for code written against the dict results).

    - `model`, `nominal`: calibrated and nominal models; `T_cam_base` (4, 4);
      `T_flange_target`: calibrated marker mounts `(markers, 4, 4)`.
    - `parameters`: one `ParameterRow` per physical parameter (`name`, `unit`,
      `group`, `nominal`, `estimate`, `std`, `free`).
    - `frozen`: parameters the data cannot see, held at nominal.
    - `arcs`: per joint an `ArcRow`, the arc fit (empty for a pose-based capture);
      `sweeps`: the measurements (None without arcs).
    - `ratios`: per joint a `RatioRow`: the reduction ratio's `nominal`,
      `estimate`, `std` and whether it is `identifiable` (refined when the
      refinement ran).
    - `clock`: a `Clock`: offset (s), its std, and whether it was estimated.
    - `frames`: `FrameCounts`, used / dropped frames with reasons.
    - `intrinsics`: the first camera's `Intrinsics`; `solver`: `SolverInfo`.
    - `validation`: a `ValidationReport`, errors against the truth (synthetic
      datasets), else None; `ee_errors`: per configuration (`EEErrors`).
    - `refinement`: the reprojection refinement's `RefinementSummary` (`None`
      when it did not run); `refine_fit`: its `RefineResult`. When it ran, `model`,
      `T_cam_base`, `T_flange_target`, `parameters`, the ratios and the clock
      are the refined ones and the two-stage figures sit beside them.
    - `other_cameras`: further fixed cameras, each an `OtherCamera` (`camera`,
      `T_cam_base`, `std_cam`, `views`, ...): the refinement estimates their
      poses along with the robot (one model, one `T_cam_base` per camera).
    - `verdict`: the plausibility checks (`status`, `reasons`: see
      `jaxcal.stages.verdict`).
    - `kind`: the capture kind (`jaxcal.stages.kinds.CaptureKind`).
    - `estimate`: the final solve's parameter vector, covariance, free mask and
      references (`jaxcal.Estimate`): `jaxcal.parameters_to_model` maps a
      vector to the model, `jaxcal.physical_table` gives the URDF, DH and MDH
      tables with their covariance.
    - `eye_in_hand`: the camera rides on the flange and films `board`, fixed
      in the world. The fields keep their eye-to-hand names with the roles
      swapped: `T_cam_base` holds $T_{board,base}$ and `T_flange_target[0]`
      holds $T_{flange,cam}$ (`result.json` names them so).
    - Tracker data (`kind.device`): `camera` is the device's name,
      `T_cam_base` holds $T_{device,base}$ (the identity with
      `device_is_base`) and `T_flange_target[0]` the measured point's mount
      (`result.json`: `T_device_base`, `T_flange_point`); `frames` counts samples.
    - `point_fit`: stop-and-shoot tracker data, the `stages._points.PointFit`
      (its non-geometric terms, cross-validation, held parameters and the
      problem `jaxcal verify` predicts with; `result.json`'s `point_fit`).
    - `terms`: the non-geometric terms (`jaxcal._terms`) tried, kept (with their
      coefficients and std) and why (`result.json`'s `terms`), for camera and tracker
      data alike; `term_fit`: the kept ones with what applying them needs
      (`jaxcal.compensate`, `compensation.json`). None when none was tried.
    """

    dataset: Path
    robot_urdf: Path
    camera: str
    targets: tuple[str, ...]
    nominal: KinematicModel
    model: KinematicModel
    T_cam_base: np.ndarray
    std_cam: np.ndarray
    T_flange_target: np.ndarray
    parameters: tuple[ParameterRow, ...]
    frozen: tuple[str, ...]
    arcs: tuple[ArcRow, ...]
    ratios: tuple[RatioRow, ...]
    sweeps: Sweeps | None
    arc_fit: ArcFitResult | None
    axis_fit: AxisFitResult | PointFitResult | None
    clock: Clock
    frames: FrameCounts
    intrinsics: Intrinsics
    solver: SolverInfo
    kind: CaptureKind
    #: Seconds per step (`setup_s`, `detect_s`, ..., `total_s`): free-form, one key per timed step.
    timings: dict[str, float] = field(default_factory=dict)
    validation: ValidationReport | None = None
    warnings: tuple[str, ...] = ()
    ee_errors: EEErrors | None = None
    refinement: RefinementSummary | None = None
    refine_fit: RefineResult | None = None
    other_cameras: tuple[OtherCamera, ...] = ()
    board: str | None = None
    verdict: Verdict | None = None
    estimate: Estimate | None = None
    point_fit: PointFit | None = None
    terms: TermsSummary | None = None
    term_fit: TermFit | None = None

    @property
    def status(self) -> str:
        """`ok`, `suspect` (a plausibility check failed: see `reasons`) or `failed` (a solver)."""
        return "ok" if self.verdict is None else self.verdict.status

    @property
    def reasons(self) -> tuple[str, ...]:
        """Why the result is suspect or failed (empty when ok)."""
        return () if self.verdict is None else self.verdict.reasons

    @property
    def eye_in_hand(self) -> bool:
        return self.kind.fixed_board

    @property
    def ok(self) -> bool:
        """Every solver reported success and the estimate is finite."""
        return bool(self.solver.success) and bool(np.all(np.isfinite(self.T_cam_base)))

    def to_json(self) -> dict:
        """The `result.json` payload (plain Python types; see `jaxcal.io.result`)."""
        return result_to_json(self)


def dropped_capture_indices(ds: Dataset, camera: str) -> list:
    """Capture indices missing between a camera's first and last frame."""
    idx = np.sort(ds.frames.frame[ds.frames.camera == camera])
    if idx.size == 0:
        return []
    return sorted(set(range(int(idx[0]), int(idx[-1]) + 1)) - set(int(i) for i in idx))


def frames_summary(setup: Setup, obs: Observations, sync: Sync, two: TwoStage) -> FrameCounts:
    """How the two-stage camera's frames were used."""
    found, inside, joint = obs.primary.found, sync.inside, sync.joint
    return FrameCounts(
        images=int(len(obs.primary.rows)),
        target_found=int(found.sum()),
        no_target=int((~found).sum()),
        outside_encoder_log=int((~inside & ~sync.glitched).sum()),
        in_encoder_glitch=int(sync.glitched.sum()),
        not_in_a_sweep=0 if not setup.kind.single_joint_sweeps else int(((joint < 0) & inside & found).sum()),
        used_per_joint=two.counts,
        dropped_capture_indices=tuple(dropped_capture_indices(setup.dataset, setup.camera.name)),
        pnp_outliers=tuple(int(r) for r, _, _ in obs.primary.dropped),
        samples=None if setup.kind.images else int(len(obs.primary.rows)),
    )


def _arcs(two: TwoStage, refined: Refined | None) -> tuple[ArcRow, ...]:
    """The arc rows, with the refined ratios (the two-stage ones beside them) when refined."""
    if refined is None or refined.fit is None:
        return two.arc_rows
    rows = []
    for j, a in enumerate(two.arc_rows):
        a = dataclasses.replace(a, ratio_two_stage=a.ratio, ratio_std_two_stage=a.ratio_std)
        if refined.ratios is not None:
            a = dataclasses.replace(a, ratio=refined.ratios[j][0], ratio_std=refined.ratios[j][1])
        rows.append(a)
    return tuple(rows)


def _intrinsics(obs: Observations, refined: Refined | None) -> Intrinsics:
    """The first camera's intrinsics: refined when the refinement freed them (the start beside them)."""
    given = obs.primary.intrinsics
    if refined is None or refined.intrinsics is None:
        return given
    return dataclasses.replace(
        given,
        K=refined.intrinsics.K,
        distortion=refined.intrinsics.distortion,
        refined=True,
        std=refined.intrinsics.std,
        held_in_refinement=refined.intrinsics.held,
        K_start=given.K,
        distortion_start=given.distortion,
    )


def _ratio_table(setup: Setup, refined: Refined | None, arcs: tuple[ArcRow, ...]) -> tuple[RatioRow, ...]:
    nominal = np.asarray(setup.nominal.reduction_ratio)
    if arcs:
        return tuple(
            RatioRow(
                joint=a.joint,
                nominal=a.ratio_nominal,
                estimate=a.ratio,
                std=a.ratio_std,
                identifiable=a.ratio_identifiable,
                # A prismatic joint: motor rad per m, and the scale (true per commanded travel).
                ratio_unit=a.ratio_unit,
                scale=a.scale,
                scale_std=a.scale_std,
            )
            for a in arcs
        )
    refined_ratios = None if refined is None else refined.ratios
    return tuple(
        RatioRow(
            joint=j,
            nominal=float(nominal[k]),
            estimate=None if refined_ratios is None else refined_ratios[k][0],
            std=None if refined_ratios is None else refined_ratios[k][1],
            identifiable=refined_ratios is not None,
        )
        for k, j in enumerate(setup.nominal.joint_names)
    )


def _clock(sync: Sync, refined: Refined | None) -> Clock:
    """The clock offset: the refined one in front when the refinement estimated it."""
    clock = sync.clock
    if refined is None or refined.clock is None:
        return clock
    return dataclasses.replace(
        clock,
        offset_s_two_stage=clock.offset_s,
        std_s_two_stage=clock.std_s,
        offset_s=refined.clock.offset_s,
        std_s=refined.clock.std_s,
    )


def _solver(two: TwoStage, refined: Refined | None) -> SolverInfo:
    """The solvers' outcomes: the two-stage fits', and the refinement's when it ran."""
    if refined is None:
        return two.solver
    res = refined.fit
    return dataclasses.replace(
        two.solver,
        success=two.solver.success and succeeded(refined),
        refinement=result_name(res.result),
        refinement_steps=refined.summary.solver.steps,
        refinement_rounds_ok=bool(res.rounds_ok),
    )


def assemble(
    setup: Setup,
    obs: Observations,
    sync: Sync,
    two: TwoStage,
    refined: Refined | None,
    verdict: Verdict,
    validation: Validation | None,
    t_start: float,
) -> CalibrationResult:
    """One `CalibrationResult` from the stage records (the refined figures in
    front when the refinement ran, the two-stage ones beside them)."""
    fit = two.fit
    ran = refined is not None and refined.fit is not None
    res = refined.fit if ran else None
    warnings = (
        *setup.notes,
        *obs.notes,
        *sync.notes,
        *two.notes,
        *(refined.warnings if refined is not None else ()),
    )
    timings = {}
    for record in (setup, obs, sync, two, refined, validation):
        if record is not None:
            timings.update(record.timings)
    timings["total_s"] = time.perf_counter() - t_start
    return CalibrationResult(
        dataset=setup.dataset.root,
        robot_urdf=setup.dataset.robot_urdf,
        camera=setup.camera.name,
        targets=tuple(t.name for t in setup.targets),
        nominal=setup.nominal,
        model=jax.device_get(res.model if ran else fit.model),
        T_cam_base=np.asarray(res.T_cam_base if ran else fit.T_cam_base),
        std_cam=np.asarray(res.std if ran else fit.std)[:6],
        T_flange_target=np.asarray(res.T_flange_marker if ran else fit.T_flange_marker),
        parameters=refined.parameters if ran else two.parameters,
        frozen=refined.frozen if ran else two.frozen,
        arcs=(arcs := _arcs(two, refined)),
        ratios=_ratio_table(setup, refined if ran else None, arcs),
        sweeps=two.sweeps,
        arc_fit=jax.device_get(two.arcs),
        axis_fit=jax.device_get(fit),
        clock=_clock(sync, refined if ran else None),
        frames=frames_summary(setup, obs, sync, two),
        intrinsics=_intrinsics(obs, refined if ran else None),
        solver=_solver(two, refined if ran else None),
        kind=setup.kind,
        timings=timings,
        validation=None if validation is None else validation.report,
        warnings=warnings,
        ee_errors=None if validation is None else validation.ee_errors,
        refinement=refined.summary if ran else None,
        refine_fit=res,
        other_cameras=refined.other_cameras if ran else (),
        board=None if setup.board is None else setup.board.name,
        verdict=verdict,
        estimate=refined.estimate if ran else two.estimate,
        point_fit=two.points,
        **dict(zip(("terms", "term_fit"), _terms(setup, two, refined))),
    )


def _terms(setup: Setup, two: TwoStage, refined: Refined | None) -> tuple:
    """`(TermsSummary, TermFit)` of the terms the refinement or the point fit tried (Nones)."""
    if refined is not None and refined.terms is not None:
        return refined.terms.summary, refined.terms
    pf = two.points
    if pf is None or len(pf.models) < 2:
        return None, None
    k = pf.layout.base.axis_size
    kept = tuple(pf.layout.terms)
    d = pf.problem.data
    summary = TermsSummary(
        tried=tuple(dict.fromkeys(t for m in pf.models for t in m.terms)),
        kept=kept,
        models=pf.models,
        coefficients=pf.term_rows,
        folds=pf.folds,
    )
    fit = TermFit(kept, np.asarray(pf.fit.x)[k:], np.asarray(d.masses), np.asarray(d.coms), summary)
    return summary, fit
