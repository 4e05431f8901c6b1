"""Agreement of our GTSAM WNOA smoother with asrl-pysteam, an independent implementation of the same prior.

Mapping between the parameterizations (verified by the error-vector test below):

* pose: our ``X = T_world_sensor`` (gtsam ``Pose3``, right perturbation ``X Exp(delta)``) is the inverse
  of pysteam's ``T_k0`` (``T_sensor_world``, left perturbation ``exp(eps) T``);
* twist: gtsam orders tangents ``[omega, v]``, pysteam ``[rho, phi]`` (translation first); pysteam's
  ``w_0k_ink`` is minus ours: ``X2 = X1 Exp(dt varpi)`` is ``T2 = exp(-dt varpi) T1``. So
  ``w = -P varpi`` with ``P`` swapping the two 3-blocks;
* every error vector of the WNOA prior is ``e_pysteam = -blkdiag(P, P) e_gtsam``; pose-measurement
  errors ``Log(M^-1 X)`` agree up to ``P``; covariances map by ``P Sigma P^T`` and
  ``Qc = diag(qc_rot, qc_trans)`` becomes pysteam's ``qcd = [qc_trans x3, qc_rot x3]``;
* both costs are ``0.5 sum e^T Sigma^-1 e``.

pysteam's Gauss-Newton uses first-order Jacobians of ``Jr^-1(xi) varpi`` and stops on relative cost
change, where the true gradient is still ~1e-2; so its optimum is compared by cost and gradient, and
states only to 1e-3.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pysteam")

import gtsam  # noqa: E402
from gtsam.symbol_shorthand import V, X  # noqa: E402
from pylgmath import Transformation  # noqa: E402
from pysteam.evaluable.se3 import SE3StateVar, se3_error  # noqa: E402
from pysteam.evaluable.vspace import VSpaceStateVar, vspace_error  # noqa: E402
from pysteam.problem import (  # noqa: E402
    L2LossFunc,
    OptimizationProblem,
    StaticNoiseModel,
    WeightedLeastSquareCostTerm,
)
from pysteam.solver import GaussNewtonSolver  # noqa: E402
from pysteam.trajectory import Time  # noqa: E402
from pysteam.trajectory.const_vel import Interface  # noqa: E402

from vtr.config import SmoothingConfig  # noqa: E402
from vtr.geometry import exp_se3, log_se3  # noqa: E402
from vtr.state.smoothing import TrajectorySmoother  # noqa: E402

N_KNOTS = 20
PERIOD_NS = 100_000_000  # 10 Hz keyframes
QC_ROT, QC_TRANS = 0.2, 2.0  # rad²/s³, m²/s³
SIGMA_ROT, SIGMA_TRANS = 0.01, 0.05
VEL_SIGMA_ROT, VEL_SIGMA_TRANS = 10.0, 100.0  # the smoother's weak prior on the first twist
REFINE_ITERATIONS = 10
FD_STEP = 1e-6
COST_RTOL = 1e-9
ERROR_RTOL = 1e-9
GRADIENT_RATIO = 100.0
STATE_ATOL = 1e-3

# [omega, v] <-> [rho, phi]
P6 = np.zeros((6, 6))
P6[:3, 3:] = np.eye(3)
P6[3:, :3] = np.eye(3)
P12 = np.kron(np.eye(2), P6)


def _truth(t: float) -> np.ndarray:
    """A curving, climbing, wobbling trajectory T_world_sensor(t)."""
    xi = np.array([0.1 * np.sin(2 * t), 0.05, 0.5 * t, 2.0 * np.sin(0.5 * t), 2.0 * (1 - np.cos(0.5 * t)), 0.3 * t])
    return exp_se3(xi)


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(42)
    A = rng.normal(size=(6, 6)) * 0.3
    cov = np.diag([SIGMA_ROT**2] * 3 + [SIGMA_TRANS**2] * 3)
    cov = cov + 0.2 * np.diag(np.sqrt(np.diag(cov))) @ (A @ A.T / 6) @ np.diag(np.sqrt(np.diag(cov)))
    times = [k * PERIOD_NS for k in range(N_KNOTS)]
    meas = []
    L = np.linalg.cholesky(cov)
    for t in times:
        meas.append(_truth(t * 1e-9) @ exp_se3(L @ rng.normal(size=6)))
    cfg = SmoothingConfig(qc_translation=QC_TRANS, qc_rotation=QC_ROT, lag_s=100.0)
    sm = TrajectorySmoother(cfg, initial_velocity_sigma=(VEL_SIGMA_ROT, VEL_SIGMA_TRANS))
    for t, M in zip(times, meas, strict=True):
        sm.add_pose(t, M, cov)
    sm.refine(REFINE_ITERATIONS)
    knots = sm.knots()
    return dict(times=times, meas=meas, cov=cov, sm=sm, poses=knots.poses, vels=knots.velocities)


# ---- gtsam batch graph of the same problem ----------------------------------------------------


def _gtsam_graph(s) -> gtsam.NonlinearFactorGraph:
    g = gtsam.NonlinearFactorGraph()
    q = np.array([QC_ROT] * 3 + [QC_TRANS] * 3)
    for k, (t, M) in enumerate(zip(s["times"], s["meas"], strict=True)):
        g.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(M), gtsam.noiseModel.Gaussian.Covariance(s["cov"])))
        if k == 0:
            sig = np.array([VEL_SIGMA_ROT] * 3 + [VEL_SIGMA_TRANS] * 3)
            g.add(gtsam.PriorFactorVector6(V(0), np.zeros(6), gtsam.noiseModel.Diagonal.Sigmas(sig)))
        else:
            g.add(
                gtsam.WnoaMotionFactorPose3(
                    gtsam.StateData(X(k - 1), V(k - 1), s["times"][k - 1] * 1e-9),
                    gtsam.StateData(X(k), V(k), t * 1e-9),
                    q,
                )
            )
    return g


def _gtsam_values(poses, vels) -> gtsam.Values:
    v = gtsam.Values()
    for k, (T, w) in enumerate(zip(poses, vels, strict=True)):
        v.insert(X(k), gtsam.Pose3(T))
        v.insert(V(k), np.asarray(w, float))
    return v


def _gtsam_gradient(graph, poses, vels) -> np.ndarray:
    """Central-difference gradient of the graph cost in gtsam coordinates (right pose perturbations)."""
    n = len(poses)
    grad = np.zeros(12 * n)
    for k in range(n):
        for j in range(12):
            cost = []
            for sgn in (1.0, -1.0):
                P = [np.array(T) for T in poses]
                W = [np.array(w) for w in vels]
                d = np.zeros(6)
                d[j % 6] = sgn * FD_STEP
                if j < 6:
                    P[k] = P[k] @ exp_se3(d)
                else:
                    W[k] = W[k] + d
                cost.append(graph.error(_gtsam_values(P, W)))
            grad[12 * k + j] = (cost[0] - cost[1]) / (2 * FD_STEP)
    return grad


# ---- pysteam problem ----------------------------------------------------------------------------


def _to_pysteam_pose(T_world_sensor: np.ndarray) -> Transformation:
    return Transformation(T_ba=np.linalg.inv(T_world_sensor))


def _to_pysteam_twist(varpi: np.ndarray) -> np.ndarray:
    return (-P6 @ np.asarray(varpi, float)).reshape(6, 1)


def _from_pysteam(T_var: SE3StateVar, w_var: VSpaceStateVar) -> tuple[np.ndarray, np.ndarray]:
    return np.linalg.inv(T_var.value.matrix()), -P6 @ w_var.value.reshape(6)


def _pysteam_problem(s, poses, vels):
    """Same measurements, velocity prior and WNOA prior in pysteam, states set to (poses, vels)."""
    qcd = np.array([QC_TRANS] * 3 + [QC_ROT] * 3)
    traj = Interface(qcd=qcd)
    T_vars, w_vars = [], []
    for t, T, w in zip(s["times"], poses, vels, strict=True):
        T_var = SE3StateVar(_to_pysteam_pose(T))
        w_var = VSpaceStateVar(_to_pysteam_twist(w))
        traj.add_knot(time=Time(nsecs=t), T_k0=T_var, w_0k_ink=w_var)
        T_vars.append(T_var)
        w_vars.append(w_var)
    loss = L2LossFunc()
    meas_terms = []
    cov_p = P6 @ s["cov"] @ P6.T
    for T_var, M in zip(T_vars, s["meas"], strict=True):
        err = se3_error(T_var, _to_pysteam_pose(M))
        meas_terms.append(WeightedLeastSquareCostTerm(err, StaticNoiseModel(cov_p, "covariance"), loss))
    vel_cov = P6 @ np.diag([VEL_SIGMA_ROT**2] * 3 + [VEL_SIGMA_TRANS**2] * 3) @ P6.T
    vel_term = WeightedLeastSquareCostTerm(
        vspace_error(w_vars[0], np.zeros((6, 1))), StaticNoiseModel(vel_cov, "covariance"), loss
    )
    prior_terms = traj.get_prior_cost_terms()
    problem = OptimizationProblem()
    problem.add_state_var(*T_vars, *w_vars)
    problem.add_cost_term(*meas_terms, vel_term, *prior_terms)
    return problem, T_vars, w_vars, prior_terms


# ---- tests --------------------------------------------------------------------------------------


def _perturbed_states(s, seed=7):
    rng = np.random.default_rng(seed)
    poses = [T @ exp_se3(rng.normal(scale=0.05, size=6)) for T in s["meas"]]
    vels = [rng.normal(scale=1.0, size=6) for _ in s["meas"]]
    return poses, vels


@pytest.mark.parametrize("which", ["perturbed", "optimum"])
def test_cost_and_prior_errors_agree(setup, which):
    s = setup
    poses, vels = _perturbed_states(s) if which == "perturbed" else (s["poses"], s["vels"])
    graph = _gtsam_graph(s)
    values = _gtsam_values(poses, vels)
    problem, _, _, prior_terms = _pysteam_problem(s, poses, vels)
    ours, theirs = graph.error(values), problem.cost()
    assert abs(ours - theirs) <= COST_RTOL * abs(theirs), (ours, theirs)
    # WNOA error vectors, one per segment: e_pysteam = -blkdiag(P, P) e_gtsam
    wnoa = [graph.at(i) for i in range(graph.size()) if isinstance(graph.at(i), gtsam.WnoaMotionFactorPose3)]
    assert len(wnoa) == len(prior_terms) == N_KNOTS - 1
    worst = 0.0
    for f, term in zip(wnoa, prior_terms, strict=True):
        e_g = f.unwhitenedError(values)
        e_p = term._error_func.evaluate().reshape(12)
        worst = max(worst, np.linalg.norm(e_p + P12 @ e_g) / np.linalg.norm(e_g))
    print(
        f"\n[{which}] cost gtsam {ours:.12g} pysteam {theirs:.12g} "
        f"rel diff {abs(ours - theirs) / theirs:.2e}; worst prior error rel diff {worst:.2e}"
    )
    assert worst <= ERROR_RTOL


def test_optimum_against_pysteam(setup):
    s = setup
    # pysteam's own optimum from the measurements (zero twists), default Gauss-Newton settings.
    problem, T_vars, w_vars, _ = _pysteam_problem(s, s["meas"], [np.zeros(6)] * N_KNOTS)
    GaussNewtonSolver(problem, verbose=False).optimize()
    pysteam_cost = problem.cost()
    theirs = [_from_pysteam(T, w) for T, w in zip(T_vars, w_vars, strict=True)]
    their_poses = [p for p, _ in theirs]
    their_vels = [w for _, w in theirs]
    # Our solution evaluated by pysteam.
    problem_ours, _, _, _ = _pysteam_problem(s, s["poses"], s["vels"])
    our_cost = problem_ours.cost()
    graph = _gtsam_graph(s)
    g_ours = np.linalg.norm(_gtsam_gradient(graph, s["poses"], s["vels"]))
    g_theirs = np.linalg.norm(_gtsam_gradient(graph, their_poses, their_vels))
    pose_diff = max(np.abs(log_se3(np.linalg.inv(a) @ b)).max() for a, b in zip(s["poses"], their_poses, strict=True))
    vel_diff = max(np.abs(a - b).max() for a, b in zip(s["vels"], their_vels, strict=True))
    print(
        f"\ncost ours {our_cost:.12g} pysteam optimum {pysteam_cost:.12g}; "
        f"|grad| ours {g_ours:.2e} pysteam {g_theirs:.2e}; "
        f"max state diff pose {pose_diff:.2e} twist {vel_diff:.2e}"
    )
    assert our_cost <= pysteam_cost
    assert g_ours * GRADIENT_RATIO <= g_theirs
    assert pose_diff <= STATE_ATOL and vel_diff <= STATE_ATOL
