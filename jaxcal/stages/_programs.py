"""The compiled programs the stages run, built once per process.

Each is a `jax.jit` of a pure solver; what changes between datasets (the
numbers) are arguments, what decides shapes and control flow is static. Each
runs a few times per calibration, so each compiles without XLA's optimisation
passes (`jaxcal._cache.QUICK_COMPILE`). Each is a `jaxcal._exported.stored_jit`:
its traced program is stored beside JAX's persistent cache (`jaxcal._cache`),
which keeps its executable, so a second process neither traces nor compiles it.
"""

import atexit
import functools
import itertools
import threading
from concurrent.futures import Future
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np

from .. import _lsq
from .._arcdata import make_arc_data
from .._arcfit import ARC_OPTIONS, fit_arc, fit_joint_sweeps
from .._axisfit import axis_jacobian, axis_problem, fit_axes, home_jacobian, register_lines
from .._buckets import bucket
from .._clocksync import fit_clock_offset
from .._correction import ParameterLayout
from .._device import to_device
from .._diagnostics import score_tests as score_tests_of
from .._diagnostics import view_information as view_information_of
from .._exported import stored_jit
from .._kinematics import forward_kinematics
from .._options import RobustOptions
from .._refine import identifiable_mask, refine
from .._terms import column_map, gravity_torques, transmission_torques
from .._terms import term_basis as _term_basis_of
from .._uncertainty import ee_sigma, joint_travel, on_travel, random_configurations

#: The arc and clock fits' inlier threshold (robust sigmas of the deletion
#: residual, as a 2-D radius; see `jaxcal._robust`). PnP's covariance is
#: optimistic in its tails, so the refinement's 3.7 rejects ~5 % of clean frames,
#: which cost the two-stage fit 40 % of its accuracy on `data/ur5e_sweeps`
#: (0.56 -> 0.77 mm, measured with the plain residual); at 6 about one clean frame
#: in 144 goes and 13 of 14 sheared images (10 %) do. With the deletion residual:
#: 0.538 mm clean; `benchmarks/corrupted.py` ratios at most 1.39.
ARC_REJECT = 6.0
#: The arc fits' solver settings (`fit_arc`'s with twice its steps).
ARC_LM = replace(ARC_OPTIONS, max_steps=100)


def _arc_robust(loss: str | None) -> RobustOptions | None:
    return None if loss is None else RobustOptions(loss, reject=ARC_REJECT)


@functools.cache
def arc_fits(loss: str | None, joint_types: tuple[str, ...]):
    """Every joint's fit at once over stacked `ArcData`: `jax.vmap(fit_arc)`, a
    prismatic joint's by `fit_line` (`jaxcal._arcfit.fit_joint_sweeps`)."""

    def arc_fits(data):
        return fit_joint_sweeps(data, joint_types, robust=_arc_robust(loss), options=ARC_LM)

    return stored_jit(arc_fits, "arc_fits", (loss, joint_types, ARC_REJECT))


@functools.cache
def arc_fit(loss: str | None):
    """One joint's arc fit (the sequential procedure fits joint after joint)."""

    def arc_fit(data):
        return fit_arc(data, robust=_arc_robust(loss), options=ARC_LM)

    return stored_jit(arc_fit, "arc_fit", (loss, ARC_REJECT))


@functools.cache
def axis_fit(use_poses: bool):
    """`fit_axes(nominal, arcs, T_flange_marker=mount, free=free, home=home)`;
    `free=None` searches the identifiable parameters. The search and a given
    mask (the validation's gauge reuses the fit's) share one program: `free`
    enters as an array with a traced switch. Without `fixed_frame_free` (an
    argument too) the fixed frame is the base frame: `T_cam_base` is the
    identity and its block is no candidate of the identifiability search."""

    def program(nominal, arcs, mount, free, search, home, fixed_frame_free):
        T0 = jnp.where(fixed_frame_free, register_lines(nominal, arcs, home), jnp.eye(4))
        layout = ParameterLayout.sized(nominal.num_joints, mount.shape[0])
        cand = jnp.asarray(fixed_frame_free) | ~jnp.asarray(
            np.isin(np.arange(layout.axis_size), layout.index("cam"))
        )
        return fit_axes(
            nominal,
            arcs,
            T_flange_marker=mount,
            T_cam_base0=T0,
            use_poses=use_poses,
            free=free,
            home=home,
            candidates=cand,
            search=search,
        )

    program = stored_jit(program, "axis_fit", (use_poses,))

    def axis_fit(nominal, arcs, mount, free=None, home=None, fixed_frame_free=True):
        layout = ParameterLayout.sized(nominal.num_joints, mount.shape[0])
        search = free is None
        free = to_device(np.ones(layout.axis_size, bool) if search else free, bool)
        return program(nominal, arcs, mount, free, search, home, fixed_frame_free)

    axis_fit.program = program  # the compiled program both cases share
    return axis_fit


#: Programs compiling on background threads (`compile_two_stage_ahead`), by key.
_AHEAD: dict[tuple, threading.Thread] = {}


def compile_two_stage_ahead(
    loss, nominal, data, n_mounts: int, use_poses: bool, fixed_frame_free: bool, home: bool = False
):
    """Trace, lower and compile the arc fits' and the axis fit's programs for sweeps
    shaped as `data` on background threads (one each), while the clock fit runs: XLA compiles
    without Python's lock, so on two cores the two stages' compiles overlap the clock
    fit's (a cold `jaxcal calibrate data/ur5e_sweeps`: see the README). The stages
    then find them compiled (`wait_ahead` first: never two compiles of one program).
    `home`: the sweeps start from a home (`Sync.homes` is not None). Shapes the
    stages end up calling with differently (frames moving between size buckets at
    the fitted offset) only cost the wasted compile."""
    key = ("two_stage", loss, nominal.joint_types, use_poses)
    if key + (0,) in _AHEAD:
        return
    arcs_program = arc_fits(loss, nominal.joint_types)
    axis_program = axis_fit(use_poses).program
    layout = ParameterLayout.sized(nominal.num_joints, n_mounts)

    def compile_axes(arcs):
        mounts = jax.ShapeDtypeStruct((n_mounts, 4, 4), jnp.float64)
        free = jax.ShapeDtypeStruct((layout.axis_size,), jnp.bool_)
        homes = jax.ShapeDtypeStruct((nominal.num_joints,) * 2, jnp.float64) if home else None
        axis_program.compile(nominal, arcs, mounts, free, True, homes, fixed_frame_free)

    def compile_both():
        arcs = arcs_program.out_info(data)
        # The axis fit's program on a thread of its own once the arcs' shapes are known:
        # with the clock fit's, three compiles share the two cores.
        _start(key + (1,), compile_axes, arcs)
        arcs_program.compile(data)

    _start(key + (0,), compile_both)


def _start(key, job, *args) -> None:
    thread = threading.Thread(target=_quietly, args=(job, *args), name="jaxcal compile ahead", daemon=True)
    _AHEAD[key] = thread
    thread.start()


def _quietly(job, *args) -> None:
    try:
        job(*args)
    except Exception:  # noqa: BLE001 - the stage's own call reports it, with its context
        pass


def compile_ahead(program, *args) -> None:
    """Compile (load or export, lower and compile; never run) `program` for `args` on a
    background thread, so that the call that follows later finds it compiled (a call while it
    compiles waits for it: `StoredProgram`'s entries compile once). Compiling beside a running
    program is safe; running two at once is not (`run_ahead`)."""
    _start(("compile", program.name, next(_COMPILES)), program.compile, *args)


#: Numbers `compile_ahead`'s keys apart (`_AHEAD`'s size repeats once `wait_ahead` pops from it).
_COMPILES = itertools.count()


class Deferred(Future):
    """A `Future` whose `job(*args)` runs, here, when its result is first asked for."""

    def __init__(self, job, *args):
        super().__init__()
        self._job = (job, args)

    def result(self, timeout=None):
        if self._job is not None:
            job, args = self._job
            self._job = None
            try:
                self.set_result(job(*args))
            except Exception as e:  # noqa: BLE001 - raised below, as a Future does
                self.set_exception(e)
        return super().result(timeout)


def run_ahead(name: str, job, *args) -> Future:
    """`job(*args)`, its result (or exception) in the returned `Future`, for a check the
    pipeline could run beside the next stage. It runs here, inline: two jaxcal programs
    running at once on XLA:CPU's two-thread pool were seen to deadlock (both pool threads
    waiting in a batched QR's task split, each on work only the other could run), and
    the overlap measured no wall-time gain (docs/performance.md, start-up). `name` labels
    the job for a later, safe overlap."""
    del name
    future: Future = Future()
    try:
        future.set_result(job(*args))
    except Exception as e:  # noqa: BLE001 - handed to whoever asks for the result, as a thread would
        future.set_exception(e)
    return future


def wait_ahead() -> None:
    """Wait for the programs `compile_two_stage_ahead` is compiling."""
    while _AHEAD:  # a thread may start another before it ends: join in start order
        _AHEAD.pop(next(iter(_AHEAD))).join()


# A calibration that fails before its arc fits leaves its compile running: the process
# waits for it at exit rather than tearing XLA down under it.
atexit.register(wait_ahead)


@functools.cache
def clock_fit(loss: str | None):
    """`fit_clock_offset(data, t_cam, enc_t, enc_q, offset0_s, drift_ppm)` with `loss`."""
    robust = None if loss is None else RobustOptions(loss)

    def clock_fit(data, t_cam, enc_t, enc_q, offset0_s, drift_ppm):
        return fit_clock_offset(
            data, t_cam, enc_t, enc_q, offset0_s=offset0_s, drift_ppm=drift_ppm, robust=robust
        )

    return stored_jit(clock_fit, "clock_fit", (loss,))


@functools.cache
def _refinement(free: tuple, jacobian: bool):
    def refinement(problem, params0):
        return refine(problem, params0, np.asarray(free), jacobian=jacobian)

    return stored_jit(refinement, "refinement", (free, jacobian) if jacobian else (free,))


def refinement(free: np.ndarray, jacobian: bool = False):
    """`refine(problem, params0, free, jacobian=jacobian)` for a concrete `free` mask (static)."""
    return _refinement(tuple(bool(f) for f in np.asarray(free)), bool(jacobian))


@functools.cache
def score_tests():
    """`jaxcal._diagnostics.score_tests(problem, res)`: the rolling-shutter, lens and intrinsics score tests of
    a global-shutter refinement."""
    return stored_jit(score_tests_of, "score_tests")


@functools.cache
def _view_information(free: tuple[bool, ...]):
    def view_information_program(problem, res):
        return view_information_of(problem, res, np.asarray(free))

    return stored_jit(view_information_program, "view_information", (free,))


def view_information(free: np.ndarray):
    """`jaxcal._diagnostics.view_information(problem, res, free)` for a concrete `free` mask (static):
    compiled only for a capture whose residuals' errors repeat."""
    return _view_information(tuple(bool(f) for f in np.asarray(free)))


@functools.cache
def hac_covariance():
    """`jaxcal._lsq.hac_covariance(bread, scores, information, lags)`, the lags traced."""
    return jax.jit(_lsq.hac_covariance)


@functools.cache
def identifiable():
    """The refinement's `identifiable_mask(problem, params, candidates, tol=...)`."""
    return stored_jit(identifiable_mask, "identifiable")


def _stacked_arc_data(positions, orientations, covariances, mask, encoder):
    if encoder is None:
        return jax.vmap(lambda P, O, C, m: make_arc_data(P, O, None, m, covariances=C))(
            positions, orientations, covariances, mask
        )
    return jax.vmap(lambda P, O, C, m, e: make_arc_data(P, O, e, m, covariances=C))(
        positions, orientations, covariances, mask, encoder
    )


@functools.cache
def _arc_data():
    return stored_jit(_stacked_arc_data, "arc_data")


def arc_data(positions, orientations, covariances, mask, encoder):
    """Stacked `ArcData` of sweeps (joints leading; `jaxcal._arcdata.make_arc_data` of
    each): one program rather than an eager operation per step of the whitening."""
    return _arc_data()(positions, orientations, covariances, mask, encoder)


@functools.cache
def arm_score(use_poses: bool):
    """The arm-rigidity score test's terms (`jaxcal.stages._armcheck`) in one program:
    `(r, J, Jc, tau)`, the axis fit's whitened residuals at `params`, their Jacobian in the
    parameters and in the compliances, and each sweep's mean gravity torques `tau (joints,
    joints)`, the mean over the frames `q (frames, joints)` with `weights (frames, joints)`
    (column `j`: `1/count` on sweep `j`'s frames, 0 elsewhere and on padding)."""

    def arm_score(nominal, arcs, mount, T_cam_base0, home, params, q, weights, masses, coms):
        problem = axis_problem(nominal, arcs, mount, T_cam_base0, home, use_poses=use_poses)
        tau = weights.T @ jax.vmap(gravity_torques, in_axes=(None, 0, None, None))(nominal, q, masses, coms)
        r, J = axis_jacobian(params, problem)
        Jc = jnp.einsum("rjk,jk->rk", home_jacobian(params, problem), 1e-3 * tau)
        return r.ravel(), J, Jc, tau

    return stored_jit(arm_score, "arm_score", (use_poses,))


@functools.cache
def _term_basis(terms: tuple[str, ...], moving: bool):
    if moving:

        def term_basis(nominal, q, approach, masses, coms, torque, load):
            return _term_basis_of(terms, nominal, q, masses, coms, approach, torque, load)

    else:

        def term_basis(nominal, q, approach, masses, coms):
            return _term_basis_of(terms, nominal, q, masses, coms, approach)

    return stored_jit(term_basis, "term_basis", (terms, moving))


def _padded(n: int, *arrays) -> list:
    """Each `(n, joints)` array on the device, zero-padded to `n`'s size bucket."""
    out = []
    for a in arrays:
        a = np.asarray(a, np.float64)
        p = np.zeros((bucket(n), a.shape[1]))
        p[:n] = a
        out.append(to_device(p))
    return out


def term_basis(terms, nominal, q, approach, masses, coms, torque=None, load=None) -> np.ndarray:
    """`jaxcal._terms.term_basis` of the families `terms` at commanded positions `q (n, joints)`
    with approach flanks `approach (n, joints)` and, along a logged motion, the transmissions'
    torques `torque` and load flanks `load` (`(n, joints)` each; None: the arm still), computed
    on all padded to a bucket: `(n, joints, k)`."""
    q = np.asarray(q, np.float64)
    moving = torque is not None
    rows = (q, approach, torque, load) if moving else (q, approach)
    padded = _padded(len(q), *rows)
    inert = [to_device(np.asarray(masses, np.float64)), to_device(np.asarray(coms, np.float64))]
    out = _term_basis(tuple(terms), moving)(nominal, *padded[:2], *inert, *padded[2:])
    return np.array(out)[: len(q)]


@functools.cache
def _transmission_torques():
    def torques(nominal, q, qd, qdd, masses, coms, tensors):
        return jax.vmap(transmission_torques, in_axes=(None, 0, 0, 0, None, None, None))(
            nominal, q, qd, qdd, masses, coms, tensors
        )

    return stored_jit(torques, "transmission_torques")


def motion_torques(nominal, q, qd, qdd, masses, coms, tensors) -> np.ndarray:
    """`jaxcal._terms.transmission_torques` at every row of `q`, `qd`, `qdd` `(n, joints)`
    (padded to a bucket), `(n, joints)`."""
    n = len(q)
    out = _transmission_torques()(
        nominal,
        *_padded(n, q, qd, qdd),
        *(to_device(np.asarray(a, np.float64)) for a in (masses, coms, tensors)),
    )
    return np.array(out)[:n]


@functools.cache
def _chains():
    def chains(T_cam_base, model, q):
        return T_cam_base @ jax.vmap(lambda qq: forward_kinematics(model, qq))(q)

    return stored_jit(chains, "chains")


def chains(T_cam_base, model, q) -> np.ndarray:
    """$T_{cam,base}\\,T_{base,link}(q)$ for every link and configuration `q (n, joints)`:
    `(n, links, 4, 4)` (computed on `q` padded to a bucket)."""
    q = np.asarray(q, np.float64)
    padded = np.zeros((bucket(len(q)), q.shape[1]))
    padded[: len(q)] = q
    return np.asarray(_chains()(jnp.asarray(T_cam_base), model, jnp.asarray(padded)))[: len(q)]


@functools.cache
def _ee_sigma(terms: tuple[str, ...] = ()):
    def ee_sigma_program(nominal, T_cam_base0, mounts0, cam, correction, cov, travel, masses, coms):
        key = jax.random.key(0)
        q = on_travel(nominal, random_configurations(key, EE_CONFIGURATIONS, nominal.num_joints), travel)
        if not terms:
            return ee_sigma(nominal, T_cam_base0, mounts0, cam, correction, cov, q)
        # A configuration's approach flank is unknown: either, so the lost motion's whole half-width.
        basis = _term_basis_of(terms, nominal, q, masses, coms, jnp.ones_like(q))
        joint, col = column_map(terms, nominal.num_joints)
        return ee_sigma(nominal, T_cam_base0, mounts0, cam, correction, cov, q, joint, basis[:, joint, col])

    return stored_jit(
        ee_sigma_program, "ee_sigma", (EE_CONFIGURATIONS, terms) if terms else (EE_CONFIGURATIONS,)
    )


#: Configurations (seed 0) of the end-effector uncertainty.
EE_CONFIGURATIONS = 1000


def end_effector_sigma(
    nominal, T_cam_base0, mounts0, cam, correction, cov, limits=None, terms=None
) -> np.ndarray:
    """Per configuration (1000, seed 0: the validation's sample) the 1-sigma tool-point
    uncertainty (m); a prismatic joint within its URDF `limits` (`joint_travel`). `terms`:
    `(families, masses, coms)` of non-geometric terms whose coefficients follow the axis-fit
    prefix in `cov` (`jaxcal._uncertainty.ee_sigma`)."""
    families, masses, coms = terms if terms is not None else ((), np.zeros(0), np.zeros(0))
    return np.asarray(
        _ee_sigma(tuple(families))(
            nominal,
            to_device(T_cam_base0),
            to_device(mounts0),
            cam,
            correction,
            to_device(cov),
            to_device(joint_travel(nominal, limits)),
            to_device(np.asarray(masses, np.float64)),
            to_device(np.asarray(coms, np.float64)),
        )
    )
