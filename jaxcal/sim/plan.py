"""A capture plan in MuJoCo: its frames checked for contacts and lines of sight, and rendered.

- `MujocoChecker`: the scene `jaxcal.sim.scene.build_scene` renders, built from
  the nominal robot with the plan's camera and target and collisions switched
  on (every arm geom, the plate's backing board, the floor). A configuration
  fails `self_collision` (or `scene_collision`, against the floor) when MuJoCo
  finds a contact with penetration, and `occlusion` when a ray from the camera
  to a target corner (`mujoco.mj_ray`) hits another geom first. Passed as the
  `checker` of `jaxcal.plan`, it is the last word on what the pure-JAX capsules
  of `jaxcal.planning` approximate.
- `render_plan`: `jaxcal simulate-plan`: the plan's exact motion and frames,
  filmed by its camera; `metadata.json` records the plan (`plan.json` in the
  dataset, `x_plan` at the top, `x_plan_segment` / `x_plan_kind` per motion
  segment), so a calibration knows what was planned.
"""

import json
from pathlib import Path

import numpy as np

from ..errors import PlanError
from ..planning import ALWAYS, CapturePlan, PoseSet, Robot, plan_robot, plan_to_dict
from ..planning._scene import floor_fixed_links
from .motion import Segment, Trajectory
from .scene import CameraSpec, PlateSpec, build_scene, mujoco
from .simulate import SimConfig, nominal_robot, simulate


def fovy_of(camera, exact: bool = True) -> float:
    """MuJoCo's vertical field of view (deg) for a plan camera. MuJoCo renders square
    pixels about the image centre: with `exact` (rendering) other intrinsics are refused;
    without (the contact and line-of-sight checks, which need only the camera's place),
    the field of view of `fy` is used."""
    K = np.asarray(camera.K)
    w, h = camera.width, camera.height
    hint = (
        "; planning and --evaluate work with any camera, only `jaxcal simulate-plan` renders through "
        "MuJoCo's pinhole"
    )
    if exact and (abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or abs(K[0, 1]) > 1e-12):
        raise PlanError(
            f"camera {camera.name!r}: MuJoCo renders square pixels only (fx = fy, no skew), the plan has fx "
            f"{K[0, 0]}, fy {K[1, 1]}{hint}"
        )
    if exact and (abs(K[0, 2] - 0.5 * (w - 1)) > 1e-6 or abs(K[1, 2] - 0.5 * (h - 1)) > 1e-6):
        raise PlanError(
            f"camera {camera.name!r}: MuJoCo renders the principal point at the image centre "
            f"({0.5 * (w - 1)}, {0.5 * (h - 1)}), the plan has ({K[0, 2]}, {K[1, 2]}){hint}"
        )
    return float(np.degrees(2.0 * np.arctan(0.5 * h / K[1, 1])))


def plan_layout(plan: CapturePlan, exact: bool = True) -> tuple[list, list]:
    """The plan's target and camera as the renderer's `PlateSpec` / `CameraSpec`
    (`exact`: see `fovy_of`)."""
    cam, tgt = plan.camera, plan.target
    camera = CameraSpec(
        cam.name,
        cam.width,
        cam.height,
        fovy_of(cam, exact),
        np.asarray(cam.T_mount_cam),
        cam.mount,
        tuple(np.asarray(cam.distortion, float)),
    )
    return [PlateSpec(tgt.spec, tgt.link, np.asarray(tgt.T_link_target))], [camera]


class MujocoChecker:
    """MuJoCo's verdict on configurations of a plan's robot, camera and target (see the module docstring).

    `checker(q (V, joints), path=False) -> [None or reason]`: `"self_collision"`,
    `"scene_collision"` (the floor), or, unless `path` (a configuration on the way
    between frames, not filmed), `"occlusion"`.
    """

    def __init__(self, plan: CapturePlan, *, margin: float = 0.005):
        model, _ = nominal_robot(plan.robot)
        self.nominal, self.robot = model, plan.robot
        plates, cameras = plan_layout(plan, exact=False)  # contacts and rays: the camera's place only
        floor = plan.floor_z
        self.scene = build_scene(model, plates=plates, cameras=cameras, floor_z=floor)
        spec = self.scene.spec
        for g in spec.geoms:
            if g.type != mujoco.mjtGeom.mjGEOM_MESH:  # the printed face: its backing board collides
                g.contype, g.conaffinity = 1, 1
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.qpos = np.array([self.model.joint(n).qposadr[0] for n in model.joint_names], dtype=int)
        # The floor against links no joint can lower (the base, a shoulder turning about the vertical)
        # is the robot's mounting, as in jaxcal.planning's floor check.
        self.excluded = self._structural(model) + [("world", n) for n in floor_fixed_links(model)[1:]]
        for a, b in self.excluded:
            spec.add_exclude(bodyname1=a, bodyname2=b)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.floor = {
            i for i in range(self.model.ngeom) if self.model.geom_type[i] == mujoco.mjtGeom.mjGEOM_PLANE
        }
        self.plate_body = self.model.body(f"plate:{plan.target.spec.name}").id
        self.camera = plan.camera.name
        self.points = plan.target.spec.points()
        self.eye_in_hand = plan.eye_in_hand
        self.margin = margin

    def _structural(self, model, samples: int = 500) -> list[tuple[str, str]]:
        """Body pairs in contact in more than `ALWAYS` of random configurations within
        the joint limits (seeded): structural, left out (`jaxcal.planning`'s rule)."""
        limits = Robot.load(self.robot).lower, Robot.load(self.robot).upper
        lo, hi = (np.clip(v, -np.pi, np.pi) for v in limits)
        counts: dict = {}
        for q in np.random.default_rng(0).uniform(lo, hi, (samples, len(lo))):
            self._pose(q)
            pairs = set()
            for c in self.data.contact[: self.data.ncon]:
                if c.dist < -1e-4:
                    b = sorted((int(self.model.geom_bodyid[c.geom1]), int(self.model.geom_bodyid[c.geom2])))
                    pairs.add(tuple(b))
            for p in pairs:
                counts[p] = counts.get(p, 0) + 1
        return [
            (self.model.body(a).name, self.model.body(b).name)
            for (a, b), k in counts.items()
            if k > ALWAYS * samples and 0 not in (a, b)
        ]

    def _pose(self, q) -> None:
        self.data.qpos[self.qpos] = np.asarray(q, np.float64) + np.asarray(self.nominal.zero_offset)
        mujoco.mj_forward(self.model, self.data)

    def _contact(self) -> str | None:
        for c in self.data.contact[: self.data.ncon]:
            if c.dist < -1e-4:
                return "scene_collision" if {c.geom1, c.geom2} & self.floor else "self_collision"
        return None

    def _occluded(self) -> bool:
        cam = self.data.camera(self.camera)
        eye = np.asarray(cam.xpos, np.float64)
        body = self.data.body(self.plate_body)
        R, p = np.asarray(body.xmat).reshape(3, 3), np.asarray(body.xpos)
        geomid = np.zeros(1, np.int32)
        for X in self.points @ R.T + p:
            ray = X - eye
            dist = np.linalg.norm(ray)
            hit = mujoco.mj_ray(self.model, self.data, eye, ray / dist, None, 1, self.plate_body, geomid)
            if 0 <= hit < dist - self.margin and self.model.geom_bodyid[geomid[0]] != self.plate_body:
                return True
        return False

    def __call__(self, q, path: bool = False) -> list:
        out = []
        for qq in np.asarray(q, np.float64).reshape(-1, len(self.qpos)):
            self._pose(qq)
            why = self._contact()
            if why is None and not path and self._occluded():
                why = "occlusion"
            out.append(why)
        return out


def plan_trajectory(plan: CapturePlan) -> tuple[Trajectory, np.ndarray, list]:
    """The renderer's `Trajectory`, the frames' controller times and, per recorded
    segment, what `metadata.json` says of it (`x_plan_segment`, `x_plan_kind`)."""
    m = plan.motion()
    segments = [Segment(j, float(a), float(b)) for j, a, b in m.segments]
    kinds, k = [], 0
    for i, seg in enumerate(plan.segments):
        count = len(seg.poses) if isinstance(seg, PoseSet) else 1
        kinds += [{"x_plan_segment": i, "x_plan_kind": seg.kind}] * count
        k += count
    return Trajectory(m.times, m.q, segments), m.frame_times, kinds


def render_plan(
    plan: CapturePlan, out, *, seed: int = 0, overwrite: bool = False, progress: bool = True, **config
) -> Path:
    """Render exactly `plan` (`jaxcal simulate-plan`): the perturbed arm (seeded as
    `jaxcal simulate`'s) moves along the plan and the plan's camera takes its frames.

    **Arguments:** the plan; the dataset directory `out`; `seed` of the true
    arm, mounts and noise; further `SimConfig` fields in `config` (e.g.
    `grayscale=True`, `encoder_rate_hz`).

    **Returns:** the dataset path. Raises `PlanFileError` for a plan its robot
    cannot carry out (other joints, a configuration outside the joint limits).
    """
    plan_robot(plan)
    cfg = SimConfig(
        robot=plan.robot,
        seed=seed,
        resolution=(plan.camera.width, plan.camera.height),
        fovy_deg=fovy_of(plan.camera),
        eye_in_hand=plan.eye_in_hand,
        distortion=tuple(np.asarray(plan.camera.distortion, float)),
        **config,
    )
    trajectory, t_frames, seg_notes = plan_trajectory(plan)
    text = json.dumps(plan_to_dict(plan), indent=1) + "\n"
    notes = {"metadata": {"x_plan": "plan.json"}, "segments": seg_notes, "files": {"plan.json": text}}
    return simulate(
        cfg,
        Path(out),
        trajectory=trajectory,
        overwrite=overwrite,
        progress=progress,
        frame_times=t_frames,
        layout=plan_layout(plan),
        notes=notes,
    )
