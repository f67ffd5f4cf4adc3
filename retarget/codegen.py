"""Compile CasADi functions and IPOPT problems to C once, and cache the shared objects on disk.

Cache: ``$DUALFLOW_CACHE/retarget`` (default ``~/.cache/dualflow/retarget``); a file is
named by the function's name, a key the caller derives from the robot model, its profile
and the problem layout, and a hash of the expression graph itself, so a changed MJCF,
profile or solver code never reuses a stale binary. Files are written under a temporary name and renamed into place.

Compiler: ``$CC`` or ``cc``/``gcc``/``clang`` on PATH, ``-O1 -shared -fPIC``. Without one
(or when compilation fails) the caller gets the uncompiled CasADi object back, which
evaluates in CasADi's virtual machine: same results, several times slower. The reason is
returned so it can be shown to the user (``info``) and logged once as a warning.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import casadi as ca

_warned: set[str] = set()


def cache_dir() -> Path:
    base = os.environ.get("DUALFLOW_CACHE")
    root = Path(base) if base else Path.home() / ".cache" / "dualflow"
    d = root / "retarget"
    d.mkdir(parents=True, exist_ok=True)
    return d


def graph_hash(*functions: ca.Function) -> str:
    """Hash of the expression graphs (CasADi's serialisation) of ``functions``: part of every
    cache key, so a change in the model, the profile or our code never reuses a stale binary."""
    import hashlib

    h = hashlib.sha256(ca.__version__.encode())
    for f in functions:
        h.update(f.serialize().encode())
    return h.hexdigest()[:12]


def find_compiler() -> str | None:
    cc = os.environ.get("CC")
    if cc and shutil.which(cc):
        return shutil.which(cc)
    for name in ("cc", "gcc", "clang"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _fallback(reason: str) -> str:
    msg = f"retarget: {reason}; using CasADi's virtual machine instead of compiled code (same results, slower)"
    if msg not in _warned:
        _warned.add(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)
    return msg


def _compile(c_file: Path, so_file: Path) -> str | None:
    """Compile ``c_file`` to ``so_file`` atomically; returns an error text or None."""
    cc = find_compiler()
    if cc is None:
        return "no C compiler found (set CC or install gcc)"
    tmp = so_file.with_name(so_file.name + f".{os.getpid()}.partial")
    cmd = [cc, "-O1", "-shared", "-fPIC", "-o", str(tmp), str(c_file), "-lm"]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"compiling {c_file.name} failed ({exc})"
    if res.returncode != 0:
        tmp.unlink(missing_ok=True)
        return (
            f"compiling {c_file.name} failed: "
            f"{res.stderr.strip().splitlines()[-1] if res.stderr.strip() else res.returncode}"
        )
    tmp.replace(so_file)
    return None


def compiled_function(fn: ca.Function, key: str, enable: bool = True) -> tuple[ca.Function, str]:
    """``fn`` compiled to C and loaded back (cached by ``key``), or ``fn`` itself as fallback.

    Returns (function, info) where info says which it is and why."""
    if not enable:
        return fn, "not compiled (disabled)"
    name = fn.name()
    so_file = cache_dir() / f"{name}_{key}_{graph_hash(fn)}.so"
    if not so_file.exists():
        with tempfile.TemporaryDirectory() as tmp:
            c_name = f"{name}_{key}.c"
            gen = ca.CodeGenerator(c_name)
            gen.add(fn)
            gen.generate(tmp + os.sep)
            err = _compile(Path(tmp) / c_name, so_file)
        if err:
            return fn, _fallback(err)
    try:
        return ca.external(name, str(so_file)), f"compiled ({so_file})"
    except RuntimeError as exc:
        so_file.unlink(missing_ok=True)
        return fn, _fallback(f"loading {so_file} failed ({str(exc).splitlines()[0]})")


_single_threaded: list[str] = []
_looked = [False]  # the loaded libraries were searched once (after a solve): never again per window


def single_threaded_linear_algebra() -> list[str]:
    """Limit the OpenBLAS and OpenMP thread pools of the libraries bundled in the casadi wheel
    (``libcasadi-tp-openblas``, ``libgomp``, used by IPOPT's MUMPS) to one thread.

    On small KKT systems their worker threads mostly spin: profiling an 80-frame window, IPOPT
    spent much of its time in system CPU and one thread was about 20 % faster (40 → 48
    frames/s in that run), and it leaves the other cores alone. Setting OMP_NUM_THREADS /
    OPENBLAS_NUM_THREADS before the libraries load does the same (bench/retarget_speed.py
    does; there this call changes nothing measurable); this works afterwards too, so a
    program that set neither gets it. The libraries are found among those this
    process has loaded (/proc/self/maps; IPOPT loads MUMPS and its BLAS at its first solve, so
    call this after one). Cheap to call repeatedly: the libraries are searched on the first
    call only (a casadi whose BLAS lives outside its folder is not re-searched per window), and
    it is a no-op where a library or /proc is absent. Returns the libraries it set."""
    import ctypes

    if _looked[0]:
        return list(_single_threaded)
    _looked[0] = True

    folder = os.path.realpath(os.path.dirname(ca.__file__))
    try:
        with open("/proc/self/maps") as fh:  # the copies actually loaded (the wheel holds several)
            loaded = sorted({line.split()[-1] for line in fh if ".so" in line})
    except OSError:
        return []
    for path in loaded:
        if not path.startswith(folder + os.sep):
            continue
        base = os.path.basename(path)
        fn = "openblas_set_num_threads" if "openblas" in base else "omp_set_num_threads" if "gomp" in base else None
        if fn is None:
            continue
        try:
            getattr(ctypes.CDLL(path), fn)(1)
        except (OSError, AttributeError):
            continue
        if base not in _single_threaded:
            _single_threaded.append(base)
    return list(_single_threaded)


def compiled_nlpsol(
    name: str,
    nlp: dict,
    opts: dict,
    key: str,
    enable: bool = True,
    hess_lag: ca.Function | None = None,
    jac_g: ca.Function | None = None,
) -> tuple[ca.Function, str]:
    """An IPOPT solver whose problem functions (objective, constraints, their gradient and
    Jacobian, and the Lagrangian Hessian, or ``hess_lag`` / ``jac_g`` when given: (x, p) →
    (g, jac_g_x)) are compiled C loaded from the cache, or the plain CasADi solver as
    fallback. Returns (solver, info)."""
    opts = dict(opts)
    given = {k: fn for k, fn in (("hess_lag", hess_lag), ("jac_g", jac_g)) if fn is not None}
    if not enable:
        return ca.nlpsol(name, "ipopt", nlp, opts | given), "not compiled (disabled)"
    for k, fn in given.items():  # each compiled on its own and handed to the solver loaded below
        opts[k], fn_info = compiled_function(fn, f"{name}_{key}", enable=True)
        if not fn_info.startswith("compiled"):
            return ca.nlpsol(name, "ipopt", nlp, opts | given), fn_info
    sym = type(nlp["x"])
    graph = ca.Function("nlp_graph", [nlp["x"], nlp.get("p", sym(0, 1))], [nlp["f"], nlp.get("g", sym(0, 1))])
    so_file = cache_dir() / f"{name}_{key}_{graph_hash(graph, *given.values())}.so"
    if not so_file.exists():
        solver = ca.nlpsol(name, "ipopt", nlp, opts | given)
        with tempfile.TemporaryDirectory() as tmp:
            c_file = Path(tmp) / f"{name}_{key}.c"
            cwd = os.getcwd()
            try:
                os.chdir(tmp)
                solver.generate_dependencies(c_file.name)
            finally:
                os.chdir(cwd)
            err = _compile(c_file, so_file)
        if err:
            return ca.nlpsol(name, "ipopt", nlp, opts | given), _fallback(err)
    try:
        return ca.nlpsol(name, "ipopt", str(so_file), opts), f"compiled ({so_file})"
    except RuntimeError as exc:
        # the solver's options (an unknown or unavailable one) fail the same way uncompiled:
        # then the cached binary is fine and the error is the caller's; only a binary that
        # fails where the uncompiled problem loads is dropped from the cache
        plain = ca.nlpsol(name, "ipopt", nlp, opts | given)
        so_file.unlink(missing_ok=True)
        return plain, _fallback(f"loading {so_file} failed ({str(exc).splitlines()[0]})")
