"""Compiled CasADi code: built once, cached on disk by graph hash, and a clear fallback without a compiler."""

import casadi as ca
import numpy as np
import pytest

import retarget.codegen as codegen


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("DUALFLOW_CACHE", str(tmp_path))
    monkeypatch.setattr(codegen, "_warned", set())
    return tmp_path / "retarget"


def _fn(scale=2.0):
    x = ca.SX.sym("x", 3)
    return ca.Function("toyfk", [x], [ca.vertcat(ca.sin(x) * scale, ca.dot(x, x))])


def test_compiled_function_is_cached_and_matches(cache):
    if codegen.find_compiler() is None:  # the uncompiled fallback is what such a machine runs; tested below
        pytest.skip("no C compiler on this machine")
    f = _fn()
    g, info = codegen.compiled_function(f, "k1")
    assert info.startswith("compiled")
    files = sorted(cache.glob("toyfk_k1_*.so"))
    assert len(files) == 1
    stamp = files[0].stat().st_mtime_ns
    x = np.array([0.3, -1.2, 2.0])
    assert np.allclose(np.array(g(x)), np.array(f(x)), atol=1e-15)
    g2, info2 = codegen.compiled_function(_fn(), "k1")  # same graph: reuses the binary
    assert files[0].stat().st_mtime_ns == stamp and info2 == info
    codegen.compiled_function(_fn(scale=3.0), "k1")  # changed graph: a new binary, never the stale one
    assert len(list(cache.glob("toyfk_k1_*.so"))) == 2


def test_no_compiler_falls_back_with_a_warning(cache, monkeypatch):
    monkeypatch.setattr(codegen, "find_compiler", lambda: None)
    f = _fn(scale=5.0)
    with pytest.warns(RuntimeWarning, match="no C compiler found"):
        g, info = codegen.compiled_function(f, "k2")
    assert g is f and "virtual machine" in info
    assert not list(cache.glob("toyfk_k2_*"))


def test_nlpsol_fallback_still_solves(cache, monkeypatch):
    monkeypatch.setattr(codegen, "find_compiler", lambda: None)
    x = ca.MX.sym("x", 2)
    nlp = {"x": x, "f": ca.sumsqr(x - ca.DM([1.0, 2.0])), "g": x[0] + x[1]}
    with pytest.warns(RuntimeWarning):
        solver, info = codegen.compiled_nlpsol(
            "tiny", nlp, {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes"}, "k3"
        )
    sol = solver(x0=[0, 0], lbg=-np.inf, ubg=2.0)
    assert np.allclose(np.array(sol["x"]).ravel(), [0.5, 1.5], atol=1e-6)


def test_ipopt_linear_algebra_runs_on_one_thread():
    """After an IPOPT solve has loaded MUMPS and the wheel's OpenBLAS, the helper sets that
    OpenBLAS (the copy this process actually loaded) to one thread; calling it again is harmless."""
    import ctypes
    import os

    x = ca.MX.sym("x", 2)
    solver = ca.nlpsol(
        "one_thread",
        "ipopt",
        {"x": x, "f": ca.sumsqr(x - 1), "g": x[0] - x[1]},
        {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes"},
    )
    solver(x0=[0, 0], lbg=0, ubg=0)
    folder = os.path.realpath(os.path.dirname(ca.__file__))
    with open("/proc/self/maps") as fh:
        loaded = {line.split()[-1] for line in fh if "openblas" in line and line.split()[-1].startswith(folder)}
    if not loaded:
        # casadi builds linked against the system's BLAS have nothing for the helper to set;
        # the PyPI wheels bundle OpenBLAS, so a pip install (and CI) runs the assertions below
        pytest.skip("this casadi build's IPOPT does not load a bundled OpenBLAS")
    done = codegen.single_threaded_linear_algebra()
    assert {os.path.basename(p) for p in loaded} <= set(done)
    for path in loaded:
        assert ctypes.CDLL(path).openblas_get_num_threads() == 1
    assert codegen.single_threaded_linear_algebra() == done


def test_bad_solver_options_raise_and_keep_the_cached_binary(cache):
    """An option IPOPT refuses fails uncompiled too: the error is the caller's, and the valid
    cached binary stays (it used to be deleted, costing a recompile on the next run)."""
    if codegen.find_compiler() is None:  # nothing is cached without a compiler; the fallback is tested above
        pytest.skip("no C compiler on this machine")
    x = ca.MX.sym("x", 2)
    nlp = {"x": x, "f": ca.sumsqr(x - ca.DM([1.0, 2.0])), "g": x[0] + x[1]}
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes"}
    _, info = codegen.compiled_nlpsol("tiny2", nlp, opts, "k4")
    assert info.startswith("compiled")
    (so_file,) = cache.glob("tiny2_k4_*.so")
    with pytest.raises(RuntimeError):
        codegen.compiled_nlpsol("tiny2", nlp, {**opts, "ipopt.linear_solver": "pardisomkl"}, "k4")
    assert so_file.exists()
    solver, info = codegen.compiled_nlpsol("tiny2", nlp, opts, "k4")
    assert info == f"compiled ({so_file})"
    sol = solver(x0=[0, 0], lbg=-np.inf, ubg=2.0)
    assert np.allclose(np.array(sol["x"]).ravel(), [0.5, 1.5], atol=1e-6)
