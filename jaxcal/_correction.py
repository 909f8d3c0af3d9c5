"""The correction vector: one owner for the unknowns of every calibration solver.

The axis fit and the refinement solve for corrections to a nominal robot, a
camera pose and marker mounts. Their flattened parameter vector is laid out
here, once, in `ravel_pytree` order of `AxisFitParams` / `RefineParams`:

| group    | size        | what                                                              |
| -------- | ----------- | ----------------------------------------------------------------- |
| `cam`    | 6           | twist on the fixed frame, $T_{cam,base} = T_0 \\exp(\\xi)$        |
| `origin` | 6 per joint | twist right-multiplying each joint origin (joint frame)           |
| `zero`   | 1 per joint | zero-offset increment (rad, or m for a prismatic joint)           |
| `tool`   | 6 per mount | twist right-multiplying each marker mount                         |
| `rate`   | 1 per joint | refinement: joint turn per commanded turn (nominal / true ratio)  |
| `clock`  | 1           | refinement: clock-offset increment (ms)                           |
| `intr`   | 9           | refinement: increments of $(f_x, f_y, c_x, c_y, k_1, k_2, p_1, p_2, k_3)$ |
| `others` | 6 per camera| refinement: twist on each further fixed camera's pose             |
| `angles` | 1 per view  | refinement without encoders: the sweeping joint's angle per view  |
| `line_delay` | 1 per camera | refinement, rolling shutters: line-delay increment (us per row) |
| `terms`  | per joint, per family | refinement: non-geometric coefficients (`jaxcal._terms`: compliance, backlash, harmonics) |

The axis fit's vector is the first four groups; the refinement's extends it,
so an axis-fit vector is a prefix of a refinement vector. `ParameterLayout`
gives the names (in an eye-in-hand capture the fixed frame is the board's,
`T_board_base`, and the mount the camera's), the index of every group, the
priority order of the identifiability search and the candidate masks;
`apply_correction` maps a correction onto a model; `physical_parameters`
maps the vector to the quantities a user reads (joint origins as xyz/rpy,
zero offsets, the camera pose, mounts) with their covariance. An `Estimate`
holds one solver's vector with its covariance, free mask and references, and
`parameters_to_model` maps any vector of that layout back to the calibrated
model, camera pose and mounts (`jaxcal._tables` builds the tables a user
reads on it). No other module does index arithmetic on the vector.
"""

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float

from ._exported import stored_jit
from ._geometry import matmul, matrix_to_rpy, se3_exp, so3_log
from ._kinematics import REVOLUTE, KinematicModel
from ._terms import check_terms
from ._terms import names as term_names
from ._terms import per_joint as terms_per_joint

#: Names of a pose twist's components, `(v, w)`.
POSE_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")
#: Names of the intrinsic increments, in `RefineParams.intrinsics` order.
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
#: Parameter groups in flattened order.
GROUPS = ("cam", "origin", "zero", "tool", "rate", "clock", "intr", "others", "angles", "line_delay", "terms")
#: The axis fit's groups (a prefix of `GROUPS`).
AXIS_GROUPS = GROUPS[:4]
#: Column order of the identifiability search: a column dependent on earlier
#: ones is frozen, so earlier groups are preferred (the cameras, the mounts,
#: the zero offsets, then the joint origins from base to tip, then the rest; the non-geometric
#: terms last, so a term is freed only where the geometry cannot already explain it).
PRIORITY = (
    "cam",
    "others",
    "tool",
    "zero",
    "origin",
    "rate",
    "clock",
    "line_delay",
    "intr",
    "angles",
    "terms",
)


class KinematicCorrection(eqx.Module):
    """Corrections to a nominal model, the unknowns of a kinematic calibration.

    - `origin`: per joint, a twist $(v, \\omega)$ (m, rad) right-multiplying the
      origin, `T_parent_joint @ se3_exp(origin[j])` (i.e. in the joint frame).
    - `zero_offset`: added to the zero offsets (rad).
    - `tool`: per marker, a twist right-multiplying the marker mount
      `T_flange_marker`.
    """

    origin: Float[Array, "joints 6"]
    zero_offset: Float[Array, " joints"]
    tool: Float[Array, "markers 6"]


def zero_correction(num_joints: int, num_markers: int) -> KinematicCorrection:
    """The correction that leaves the nominal model and mounts as they are."""
    return KinematicCorrection(
        origin=jnp.zeros((num_joints, 6)), zero_offset=jnp.zeros(num_joints), tool=jnp.zeros((num_markers, 6))
    )


def apply_correction(
    model: KinematicModel, T_flange_marker: Float[Array, "markers 4 4"], corr: KinematicCorrection
) -> tuple[KinematicModel, Float[Array, "markers 4 4"]]:
    """The corrected model and marker mounts."""
    dT = jax.vmap(se3_exp)(corr.origin)
    new = eqx.tree_at(
        lambda m: (m.T_parent_joint, m.zero_offset),
        model,
        (matmul(model.T_parent_joint, dT), model.zero_offset + corr.zero_offset),
    )
    mounts = matmul(T_flange_marker, jax.vmap(se3_exp)(corr.tool))
    return new, mounts


@dataclass(frozen=True)
class ParameterLayout:
    """The flattened correction vector of one calibration problem.

    **Fields:**
    - `joints`: the joint names, base to tip.
    - `num_markers`: marker mounts solved for (on the flange, or on links).
    - `other_cameras`: names of further fixed cameras (refinement only).
    - `angles`: names of the per-view joint angles (refinement without encoders).
    - `line_delays`: with rolling-shutter cameras, every camera's name (the
      first, then `other_cameras`), one line delay each (refinement only).
    - `eye_in_hand`: the camera rides on the flange: the fixed frame is the
      board's (`T_board_base`) and the one mount is the camera's.
    - `fixed_name`: the fixed frame's name where it is neither (an external
      measuring device's `T_device_base`).
    - `terms`: the non-geometric term families of the refinement (`jaxcal._terms`),
      their coefficients last, family-major and joint-major within a family.
    """

    joints: tuple[str, ...]
    num_markers: int = 1
    other_cameras: tuple[str, ...] = ()
    angles: tuple[str, ...] = ()
    eye_in_hand: bool = False
    line_delays: tuple[str, ...] = ()
    fixed_name: str | None = None
    terms: tuple[str, ...] = ()

    def __post_init__(self):
        check_terms(self.terms)

    @classmethod
    def of(cls, model: KinematicModel, num_markers: int = 1, **kwargs) -> "ParameterLayout":
        return cls(tuple(model.joint_names), num_markers, **kwargs)

    # ------------------------------------------------------------------ sizes and indices

    def sizes(self) -> dict[str, int]:
        n, M = len(self.joints), self.num_markers
        return {
            "cam": 6,
            "origin": 6 * n,
            "zero": n,
            "tool": 6 * M,
            "rate": n,
            "clock": 1,
            "intr": len(INTRINSIC_NAMES),
            "others": 6 * len(self.other_cameras),
            "angles": len(self.angles),
            "line_delay": len(self.line_delays),
            "terms": n * terms_per_joint(self.terms),
        }

    def index(self, group: str) -> np.ndarray:
        """Indices of `group` in the flattened vector."""
        if group not in GROUPS:
            raise ValueError(f"unknown parameter group {group!r}; groups are {GROUPS}")
        start = 0
        for g, size in self.sizes().items():
            if g == group:
                return np.arange(start, start + size)
            start += size
        raise AssertionError  # unreachable

    def indices(self) -> dict[str, np.ndarray]:
        """Every group's indices (`GROUPS` order)."""
        return {g: self.index(g) for g in GROUPS}

    @classmethod
    def sized(
        cls, num_joints: int, num_markers: int = 1, others: int = 0, angles: int = 0
    ) -> "ParameterLayout":
        """A layout of the given sizes with placeholder names (for index arithmetic-free tests and studies)."""
        return cls(
            tuple(f"joint{j}" for j in range(num_joints)),
            num_markers,
            other_cameras=tuple(f"camera{c + 1}" for c in range(others)),
            angles=tuple(f"view{v}" for v in range(angles)),
        )

    @property
    def axis_size(self) -> int:
        """Length of the axis fit's vector (the prefix of the refinement's)."""
        s = self.sizes()
        return sum(s[g] for g in AXIS_GROUPS)

    @property
    def size(self) -> int:
        """Length of the refinement's vector."""
        return sum(self.sizes().values())

    # ------------------------------------------------------------------ names

    @property
    def fixed_frame(self) -> str:
        """The frame the robot is located in: the camera's or, eye-in-hand, the board's (or `fixed_name`)."""
        if self.fixed_name is not None:
            return self.fixed_name
        return "T_board_base" if self.eye_in_hand else "T_cam_base"

    def mount_labels(self) -> list[str]:
        """Labels of the mounts (`marker`, or `marker0..`; `camera` eye-in-hand)."""
        if self.eye_in_hand:
            return ["camera"]
        return ["marker"] if self.num_markers == 1 else [f"marker{m}" for m in range(self.num_markers)]

    def names(self, *, refine: bool = True) -> list[str]:
        """Names of the flattened vector (the axis fit's prefix when not `refine`)."""
        names = [f"{self.fixed_frame}.{p}" for p in POSE_NAMES]
        for j in self.joints:
            names += [f"{j}.origin.{p}" for p in POSE_NAMES]
        names += [f"{j}.zero_offset" for j in self.joints]
        for mk in self.mount_labels():
            names += [f"{mk}.mount.{p}" for p in POSE_NAMES]
        if not refine:
            return names
        names += [f"{j}.rate" for j in self.joints]
        names += ["clock_offset_ms"]
        names += [f"intrinsics.{k}" for k in INTRINSIC_NAMES]
        for c in self.other_cameras:
            names += [f"{c}.T_cam_base.{p}" for p in POSE_NAMES]
        names += list(self.angles) + [f"{c}.line_delay_us" for c in self.line_delays]
        return names + term_names(self.terms, self.joints)

    def split(self, x: Float[Array, " n"]) -> tuple[Float[Array, "6"], KinematicCorrection, Array | None]:
        """`(cam, correction, rate)` of a flattened vector: an axis fit's
        (`axis_size` long; `rate` is then None) or a refinement's (`size`)."""
        n, M = len(self.joints), self.num_markers
        if x.shape not in ((self.axis_size,), (self.size,)):
            raise ValueError(
                f"parameter vector has shape {x.shape}; this layout's is ({self.axis_size},) "
                f"(axis fit) or ({self.size},) (refinement)"
            )
        corr = KinematicCorrection(
            origin=x[self.index("origin")].reshape(n, 6),
            zero_offset=x[self.index("zero")],
            tool=x[self.index("tool")].reshape(M, 6),
        )
        rate = x[self.index("rate")] if x.shape[0] == self.size else None
        return x[self.index("cam")], corr, rate

    # ------------------------------------------------------------------ masks

    def priority(self, *, refine: bool = True) -> np.ndarray:
        """Column order of the identifiability search (see `PRIORITY`)."""
        groups = PRIORITY if refine else [g for g in PRIORITY if g in AXIS_GROUPS]
        return np.concatenate([self.index(g) for g in groups])

    def candidates(
        self,
        *,
        rates: bool = True,
        clock: bool = False,
        intrinsics: bool = False,
        line_delay=False,
        terms=False,
    ) -> np.ndarray:
        """Candidate mask of the refinement: pose and kinematic corrections
        (every camera's pose and every per-view angle included), and the
        optional groups (`line_delay`: one bool, or one per camera of `line_delays`;
        `terms`: one bool, or one per coefficient)."""
        free = np.ones(self.size, bool)
        free[self.index("rate")] = rates
        free[self.index("clock")] = clock
        free[self.index("intr")] = intrinsics
        free[self.index("line_delay")] = line_delay
        free[self.index("terms")] = terms
        return free

    def axis_columns(self, group: str) -> np.ndarray:
        """Per joint (rows), which axis-fit parameters move joint $j$'s axis
        (`group="line"`) or, per marker, the marker (`group="marker"`).

        Joint $j$'s axis moves with the camera pose, the origins of joints
        $i \\le j$ and the zero offsets of joints $i < j$; a marker with
        everything but the other markers' mounts.
        """
        n, M = len(self.joints), self.num_markers
        if group == "line":
            j = np.arange(n)[:, None]
            i = np.arange(n)[None, :]
            return np.concatenate(
                [np.ones((n, 6)), np.repeat(i <= j, 6, axis=1), i < j, np.zeros((n, 6 * M))], axis=1
            )
        if group == "marker":
            return np.concatenate([np.ones((M, 6 + 7 * n)), np.repeat(np.eye(M), 6, axis=1)], axis=1)
        raise ValueError(f"group must be 'line' or 'marker', got {group!r}")


# --------------------------------------------------------------------------- physical parameters


def physical_names(
    layout: ParameterLayout, mount_names: list[str], joint_types: tuple[str, ...] | None = None
) -> list[tuple[str, str, str]]:
    """`(name, unit, group)` of every row of `physical_parameters` (a zero
    offset in m for a prismatic joint of `joint_types`, else rad)."""
    pose = [("x", "m"), ("y", "m"), ("z", "m"), ("roll", "rad"), ("pitch", "rad"), ("yaw", "rad")]
    types = (REVOLUTE,) * len(layout.joints) if joint_types is None else joint_types
    rows = []
    for j in layout.joints:
        rows += [(f"{j}.origin.{a}", u, "correction") for a, u in pose]
    rows += [
        (f"{j}.zero_offset", "rad" if t == REVOLUTE else "m", "correction")
        for j, t in zip(layout.joints, types)
    ]
    rows += [(f"{layout.fixed_frame}.{a}", "m", "camera") for a in "xyz"]
    rows += [(f"{layout.fixed_frame}.rot_{a}", "rad", "camera") for a in "xyz"]
    for t in mount_names:
        rows += [(f"{t}.mount.{a}", u, "mount") for a, u in pose]
    return rows


def physical_values(
    nominal: KinematicModel,
    T_flange_marker0: Float[Array, "markers 4 4"],
    T_cam_base0: Float[Array, "4 4"],
    cam: Float[Array, "6"],
    correction: KinematicCorrection,
) -> Float[Array, " rows"]:
    """The physical parameters at a correction: every joint origin as
    (x, y, z, roll, pitch, yaw) (m, rad, URDF convention), the zero offsets,
    the fixed frame's translation and its rotation relative to `T_cam_base0`
    (a rotation vector, rad), and every mount as (x, y, z, roll, pitch, yaw)."""
    model, mounts = apply_correction(nominal, T_flange_marker0, correction)
    T_cb = T_cam_base0 @ se3_exp(cam)
    xyz_rpy = jax.vmap(lambda T: jnp.concatenate([T[:3, 3], matrix_to_rpy(T[:3, :3])]))
    dR = so3_log(T_cam_base0[:3, :3].T @ T_cb[:3, :3])
    return jnp.concatenate(
        [
            xyz_rpy(model.T_parent_joint).reshape(-1),
            model.zero_offset,
            T_cb[:3, 3],
            dR,
            xyz_rpy(mounts).reshape(-1),
        ]
    )


def physical_jacobian(nominal, mounts0, T_cam_base0, cam, correction):
    """`physical_values` at the estimate and at zero, and its Jacobian wrt the
    flattened `(cam, correction)` (the axis-fit vector), as one compiled call."""
    flat, unravel = ravel_pytree((cam, correction))

    def f(x):
        c, corr = unravel(x)
        return physical_values(nominal, mounts0, T_cam_base0, c, corr)

    return f(flat), f(jnp.zeros_like(flat)), jax.jacfwd(f)(flat)


physical_jacobian = stored_jit(physical_jacobian, "physical_jacobian")


def physical_parameters(
    layout: ParameterLayout,
    nominal: KinematicModel,
    T_flange_marker0,
    T_cam_base0,
    cam,
    correction: KinematicCorrection,
    cov,
    free,
    mount_names: list[str],
) -> list[dict]:
    """The parameter table a user reads: one row per physical parameter.

    **Arguments:** the layout; the nominal model, mounts and camera pose the
    correction is relative to; the estimate (`cam`, `correction`); the
    covariance `cov` and `free` mask of the axis-fit part of the vector
    (`layout.axis_size` square / long); the mounts' names.

    **Returns:** per row `name`, `unit`, `group` (`correction`, `camera`,
    `mount`), `nominal`, `estimate`, `std` (the covariance propagated through
    the Jacobian of `physical_values`) and `free` (whether an estimated
    parameter moves it).
    """
    est, nom, G = (
        np.asarray(a)
        for a in physical_jacobian(
            nominal, jnp.asarray(T_flange_marker0), jnp.asarray(T_cam_base0), cam, correction
        )
    )
    std = np.sqrt(np.maximum(np.einsum("ia,ab,ib->i", G, np.asarray(cov), G), 0.0))
    moves = np.abs(G[:, np.asarray(free)]).sum(axis=1) > 1e-12
    return [
        {
            "name": n,
            "unit": u,
            "group": g,
            "nominal": float(nom[i]),
            "estimate": float(est[i]),
            "std": float(std[i]),
            "free": bool(moves[i]),
        }
        for i, (n, u, g) in enumerate(physical_names(layout, mount_names, nominal.joint_types))
    ]


# --------------------------------------------------------------------------- estimates


class Estimate(eqx.Module):
    """One calibration solve's estimate, with everything needed to read it.

    - `x`, `cov`, `free`: the flattened vector (`layout.names()` order: the
      axis fit's `axis_size`, or the refinement's `size`), its covariance
      (zero rows and columns where frozen) and which entries were estimated.
    - `nominal`, `T_flange_marker0`, `T_cam_base0`: what the corrections are
      relative to (`apply_correction`; $T_{cam,base} = T_0 \\exp(\\xi_{cam})$).
    - `reduction_ratio`: the ratios of a vector without rates (the arc fits');
      a refinement's vector carries them as rates, $\\rho = \\rho_{nom} / r$.
    - `layout`, `mount_names`: the vector's layout and the mounts' names.
    """

    x: Float[Array, " n"]
    cov: Float[Array, "n n"]
    free: Bool[Array, " n"]
    nominal: KinematicModel
    T_flange_marker0: Float[Array, "markers 4 4"]
    T_cam_base0: Float[Array, "4 4"]
    reduction_ratio: Float[Array, " joints"]
    layout: ParameterLayout = eqx.field(static=True)
    mount_names: tuple[str, ...] = eqx.field(static=True)

    def __check_init__(self):
        n = self.x.shape[0]
        if n not in (self.layout.axis_size, self.layout.size):
            raise ValueError(
                f"Estimate: a vector of {n} does not fit the layout ({self.layout.axis_size} or {self.layout.size})"
            )
        if self.cov.shape != (n, n) or self.free.shape != (n,):
            raise ValueError(f"Estimate: cov {self.cov.shape} and free {self.free.shape} must fit x ({n},)")
        if len(self.mount_names) != self.layout.num_markers:
            raise ValueError(
                f"Estimate: {len(self.mount_names)} mount names for {self.layout.num_markers} mounts"
            )


class CalibratedModel(eqx.Module):
    """The calibrated arm a parameter vector stands for.

    - `model`: the corrected `KinematicModel` (its reduction ratios the
      estimate's, `T_flange_tool` the first mount).
    - `T_cam_base`: the fixed frame's pose ($T_{board,base}$ eye-in-hand).
    - `T_flange_marker`: every mount (eye-in-hand, the one mount is $T_{flange,cam}$).
    """

    model: KinematicModel
    T_cam_base: Float[Array, "4 4"]
    T_flange_marker: Float[Array, "markers 4 4"]


def parameters_to_model(estimate: Estimate, x: Float[Array, " n"] | None = None) -> CalibratedModel:
    """The calibrated model, fixed-frame pose and mounts at parameter vector `x`.

    $T_{parent,joint} = T^{nom}_{parent,joint}\\exp(\\xi_j)$, $\\delta = \\delta_{nom} +
    \\Delta\\delta$, $T_{flange,marker} = T^0_{flange,marker}\\exp(\\xi_m)$,
    $T_{cam,base} = T_0\\exp(\\xi_{cam})$, and with a refinement's vector the
    ratios $\\rho_{nom} / r$. Pure: differentiate it, or vmap it over samples of `x`.

    **Arguments:** `estimate`; `x` a vector of its layout (default `estimate.x`).
    """
    x = estimate.x if x is None else jnp.asarray(x)
    cam, corr, rate = estimate.layout.split(x)
    model, mounts = apply_correction(estimate.nominal, estimate.T_flange_marker0, corr)
    ratio = estimate.reduction_ratio if rate is None else estimate.nominal.reduction_ratio / rate
    model = eqx.tree_at(lambda m: (m.reduction_ratio, m.T_flange_tool), model, (ratio, mounts[0]))
    return CalibratedModel(
        model=model, T_cam_base=estimate.T_cam_base0 @ se3_exp(cam), T_flange_marker=mounts
    )
