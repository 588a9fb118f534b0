"""The total-least-squares problem as a GTSAM factor graph (the peer a user would otherwise
pick), solved one trial at a time.  Needs ``gtsam`` (the ``peers`` extra); imported lazily.

The full errors-in-variables MAP: the true frames F_ga_n as Gal3 variables with
``PriorFactorGal3`` on the observations F~_ga_n (GTSAM's prior error Logmap(F~^-1 X) is our
eps_a), and a ``CustomFactor`` on (X_n, F, dtau) for the observation of b through the motion
model, error Logmap(F~_gb_n^-1 X_n A_n), A_n = T^n F T^-n.  This minimises the same function
as ``tls.eiv_cost`` and the iterated Gauss-Helmert solver.

GTSAM orders the Gal3 tangent [phi, nu, rho, iota]; ours is [rho, nu, phi, iota].
"""
from __future__ import annotations

import numpy as np

# xi_gtsam = xi_ours[PERM]
PERM = np.array([6, 7, 8, 3, 4, 5, 0, 1, 2, 9])
INV_PERM = np.argsort(PERM)


def _time_translation(gtsam, s: float):
    xi = np.zeros(10)
    xi[9] = s
    return gtsam.Gal3.Expmap(xi)


def solve_trial(F_ga: np.ndarray, F_gb: np.ndarray, cov_a: np.ndarray, cov_b: np.ndarray,
                F0: np.ndarray, dtau0: float, indices: np.ndarray | None = None,
                max_iterations: int = 100, relative_tol: float = 1e-12):
    """One trial: F_ga, F_gb (N+1, 5, 5) matrices, cov_a, cov_b (10, 10) in OUR tangent
    order, initial F0 (5, 5) and dtau0.  Returns (F (5, 5), dtau, marginal covariance of
    (F, dtau) (11, 11) in our order, iterations)."""
    import gtsam

    N1 = F_ga.shape[0]
    n_idx = np.arange(N1, dtype=float) if indices is None else np.asarray(indices, float)
    Sa = cov_a[np.ix_(PERM, PERM)]
    Sb = cov_b[np.ix_(PERM, PERM)]
    noise_a = gtsam.noiseModel.Gaussian.Covariance(Sa)
    noise_b = gtsam.noiseModel.Gaussian.Covariance(Sb)
    KF, KT = 0, 1

    def KX(n):
        return 2 + n

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(KF, gtsam.Gal3(F0))
    values.insert(KT, np.array([dtau0]))
    e10 = np.zeros(10)
    e10[9] = 1.0
    for n in range(N1):
        meas_a = gtsam.Gal3(F_ga[n])
        graph.add(gtsam.PriorFactorGal3(KX(n), meas_a, noise_a))
        values.insert(KX(n), meas_a)
        meas_b_inv = gtsam.Gal3(F_gb[n]).inverse()
        nn = float(n_idx[n])

        def error(this, v, jacobians, meas_b_inv=meas_b_inv, nn=nn, n=n):
            X = v.atGal3(KX(n))
            F = v.atGal3(KF)
            dtau = float(v.atVector(KT)[0])
            T = _time_translation(gtsam, nn * dtau)
            A = T.compose(F).compose(T.inverse())
            E = meas_b_inv.compose(X).compose(A)
            H = np.zeros((10, 10), order="F")
            err = gtsam.Gal3.Logmap(E, H)  # H = J_r(err)^-1
            if jacobians is not None:
                jacobians[0] = H @ A.inverse().AdjointMap()
                jacobians[1] = H @ T.AdjointMap()
                col = T.compose(F.inverse()).AdjointMap() @ e10 - e10
                jacobians[2] = (H @ (nn * col)).reshape(10, 1)
            return err

        graph.add(gtsam.CustomFactor(noise_b, [KX(n), KF, KT], error))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_tol)
    params.setAbsoluteErrorTol(0.0)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    F = result.atGal3(KF).matrix()
    dtau = float(result.atVector(KT)[0])
    marg = gtsam.Marginals(graph, result)
    keys = gtsam.KeyVector([KF, KT])
    P = marg.jointMarginalCovariance(keys).fullMatrix()
    order = np.concatenate([PERM, [10]])  # gtsam blocks: F (gtsam order), then dtau
    P_ours = np.empty_like(P)
    P_ours[np.ix_(order, order)] = P  # P_gtsam[i, j] = P_ours[order[i], order[j]]
    return F, dtau, P_ours, opt.iterations()
