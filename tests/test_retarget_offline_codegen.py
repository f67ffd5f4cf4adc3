"""compiled_nlpsol with a hand-made constraint Jacobian (``jac_g``, as the offline retargeter
passes it): compiled and cached next to the problem, and the function IPOPT actually uses."""

import casadi as ca
import numpy as np
import pytest

import retarget.codegen as codegen


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("DUALFLOW_CACHE", str(tmp_path))
    monkeypatch.setattr(codegen, "_warned", set())
    return tmp_path / "retarget"


def _problem(jac_scale):
    """min ‖x − (1, 2)‖² s.t. x0·x1 = 1, with jac_g scaled by ``jac_scale`` in its first column."""
    x = ca.MX.sym("x", 2)
    p = ca.MX.sym("p", 0, 1)
    g = x[0] * x[1]
    jac = ca.horzcat(jac_scale * x[1], x[0])
    jac_g = ca.Function("tiny_jac_g", [x, p], [g, jac], ["x", "p"], ["g", "jac_g_x"])
    return {"x": x, "p": p, "f": ca.sumsqr(x - ca.DM([1.0, 2.0])), "g": g}, jac_g


@pytest.mark.parametrize("compile_", [True, False])
def test_given_jacobian_is_used_compiled_or_not(cache, compile_):
    if compile_ and codegen.find_compiler() is None:
        pytest.skip("no C compiler on this machine (the uncompiled case below still runs)")
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.max_iter": 50}
    nlp, jac_g = _problem(1.0)
    solver, info = codegen.compiled_nlpsol("tinyj", nlp, opts, "k5", enable=compile_, jac_g=jac_g)
    assert info.startswith("compiled") == compile_
    if compile_:
        assert list(cache.glob("tiny_jac_g_tinyj_k5_*.so")) and list(cache.glob("tinyj_k5_*.so"))
    sol = solver(x0=[1.0, 1.0], lbg=1.0, ubg=1.0, lbx=0.1, ubx=10)
    x = np.array(sol["x"]).ravel()
    assert abs(x[0] * x[1] - 1.0) < 1e-8 and solver.stats()["success"]
    # a wrong Jacobian (first column halved) changes what IPOPT does: it is the function in use
    nlp_bad, jac_bad = _problem(0.5)
    bad, _ = codegen.compiled_nlpsol("tinyj", nlp_bad, opts, "k5", enable=compile_, jac_g=jac_bad)
    xb = np.array(bad(x0=[1.0, 1.0], lbg=1.0, ubg=1.0, lbx=0.1, ubx=10)["x"]).ravel()
    assert np.abs(xb - x).max() > 1e-4
