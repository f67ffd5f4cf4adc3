"""The offline problem's hand-made derivatives (retarget.offline, chain rule over the per-frame
Jacobians) equal CasADi's own automatic differentiation of the same problem: the constraint
Jacobian (every block: velocity, sole height, slide, balance, collision) and the Gauss-Newton
Hessian 2·J_Rᵀ·J_R, at random points and parameters."""

import casadi as ca
import numpy as np
import pytest
from retarget_toy import toy_robot
from test_retarget_streaming import op3_for_round_trip

from retarget.offline import OfflineConfig, OfflineRetargeter


@pytest.mark.parametrize("robot, zmp", [(toy_robot, False), (toy_robot, True), (op3_for_round_trip, False)])
def test_chain_rule_derivatives_equal_casadis_ad(robot, zmp):
    rb = robot()
    W = 9
    off = OfflineRetargeter(rb, OfflineConfig(window=W, balance=True, zmp=zmp, compile=False, engine="ipopt"))
    off._solver(W, 30.0)
    prob = off._problems[(W, 30.0)]
    nlp = prob["nlp"]
    w, p = nlp["x"], nlp["p"]
    assert nlp["g"].shape[0] > (rb.nx * (W - 1))  # contact, balance (and collision) rows are there too
    ad_jac = ca.Function("ad_jac", [w, p], [ca.jacobian(nlp["g"], w)])
    JR = ca.jacobian(prob["R"], w)
    ad_hess = ca.Function("ad_hess", [w, p], [ca.triu(2 * ca.mtimes(JR.T, JR))])
    rng = np.random.default_rng(0)
    lo, hi = np.tile(rb.x_lower, W), np.tile(rb.x_upper, W)
    n_l = w.shape[0] - rb.nx * W
    for _ in range(3):
        x = np.concatenate([rng.uniform(np.maximum(lo, -1.0), np.minimum(hi, 1.0)), rng.uniform(0, 1, n_l)])
        par = rng.normal(size=p.shape[0])
        g_ours, jac_ours = prob["jac_g"](x, par)
        np.testing.assert_allclose(
            np.array(g_ours).ravel(), np.array(ca.Function("g", [w, p], [nlp["g"]])(x, par)).ravel(), atol=1e-12
        )
        np.testing.assert_allclose(jac_ours.full(), ad_jac(x, par).full(), atol=1e-10, rtol=1e-10)
        h_ours = prob["hess"](x, par, 1.0, np.zeros(nlp["g"].shape[0]))
        h_ad = ad_hess(x, par)
        np.testing.assert_allclose(h_ours.full(), h_ad.full(), atol=1e-8 * max(1.0, np.abs(h_ad.full()).max()))
