"""The ``system:`` key of scene files: read matrices or a Hamiltonian, and turn the system
into what advise/check analyse (the modes, or the coupled analysis).

::

    system: {stiffness: K.npz, mass: M.npy}        # or inline lists of lists; K indefinite ok
    system: {hessian: [[2, 0.3], [0.3, 1]]}         # H = x^T S x / 2, x = (q, p)
    system: {hamiltonian: "alpha*q*p*(p-1)", parameters: {alpha: 2},
             box: {q: [-2, 2], p: [-2, 2]}}

Matrix files (paths relative to the scene file): ``.npy`` (dense), ``.npz`` (a dense array
saved by numpy, or a sparse matrix saved by ``scipy.sparse.save_npz``) and ``.mtx`` (Matrix
Market), read within the budgets of :mod:`stepsafe.systems.matrixfile`. Sparse stiffness matrices
with more than :data:`DENSE_LIMIT` rows are analysed through their extreme eigenvalues only
(enough for ``h_max``; islands are then not analysed, and the output says so).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from stepsafe.core.advice import Modes
from stepsafe.exceptions import StepsafeError, unknown_key
from stepsafe.exceptions import StepsafeError as _E
from stepsafe.files.expressions import ExpressionError
from stepsafe.methods.tableaux import Method
from stepsafe.systems.coupled import coupled_safe_steps
from stepsafe.systems.coupled_exact import EXACT_SIZE
from stepsafe.systems.dynamics import separable_terms
from stepsafe.systems.indexed import read_indexed
from stepsafe.systems.linear import (
    EPS,
    LinearMode,
    check_square,
    gaussian_modes,
    hessian_modes,
    is_diagonal,
    separable_modes,
    sparse_extreme_modes,
)
from stepsafe.systems.manydof import MAX_DOF, MAX_STARTS, ManyDofHamiltonian, find_many, parse_many
from stepsafe.systems.matrixfile import read_matrix
from stepsafe.systems.md import system as md
from stepsafe.systems.nonlinear import GRID, find_equilibria, parse_hamiltonian
from stepsafe.systems.scene import number, parse_real
from stepsafe.systems.walks import RESOLUTION, Walks
from stepsafe.units import ENERGY_UNITS, LENGTH_UNITS, MASS_UNITS, TIME_UNITS, stiffness_scale

DENSE_LIMIT = 2000
#: Relative uncertainty of an equilibrium's beta: its Hessian is exact to ~30 digits (see
#: stepsafe.systems.nonlinear), the float64 square roots and products add a few ulps.
EQUILIBRIUM_ERROR = 8 * float(np.finfo(float).eps)
SYSTEM_KEYS = {"stiffness", "precision", "covariance", "mass", "hessian", "hamiltonian",
               "parameters", "box", "q", "p", "energy_below", "starts", "sizes", "fixed",
               "all_modes", "units", "invariants"}


class SystemReport(NamedTuple):
    """What was found in the system, ready for JSON, and how to advise on it."""

    analysis: str
    items: list[dict[str, Any]]  # each mode or equilibrium: type, beta, model, ...
    modes: Modes | None  # decoupled test-model frequencies (None if all coupled)
    coupled: list[Any]  # CoupledResult per coupled piece (with its Hessian)
    notes: list[str]
    primary_only: bool = False  # only the safe interval from 0 was analysed (no islands)
    source: str = ""  # the file and key the modes came from (``file::$.system.precision``)
    #: a Hamiltonian's equilibrium search: what it searched and whether it can vouch that
    #: it found every equilibrium (:func:`search_record`); None for other systems
    search: dict[str, Any] | None = None
    #: an MD engine's system with ``runs:``: ``engine_check(method name, h)`` runs the method
    #: in the engine at step h (the scene's time unit) and returns the JSON-ready record
    #: (:func:`stepsafe.systems.md.system.engine_check`); None for other systems
    engine_check: Callable[[str, float], dict[str, Any]] | None = None
    #: the ``system:`` mapping as given (what the analysis at temperature integrates)
    tree: Any = None
    #: an MD engine's system: its analysis (:class:`stepsafe.systems.md.system.MDAnalysis`,
    #: with the engine the analysis at temperature samples and runs); None for other systems
    md: Any = None


def _fail(where: str, path: str, message: str) -> StepsafeError:
    return StepsafeError(message, f"{where}::$.system.{path}")


def _matrix(value: Any, where: str, key: str, folder: Path, sparse_ok: bool = False):
    if isinstance(value, str):
        try:
            return read_matrix(folder / value, value, sparse_ok)
        except StepsafeError as exc:
            raise _fail(where, key, str(exc)) from None
    if isinstance(value, np.ndarray) or hasattr(value, "tocsr"):  # from the Python API
        return _array(value, where, key, sparse_ok)
    if not isinstance(value, list) or not value or not all(isinstance(r, list) for r in value):
        raise _fail(where, key, "must be a list of rows or a .npy/.npz/.mtx file name")
    n = len(value)
    out = np.empty((n, len(value[0])))
    for i, row in enumerate(value):
        if len(row) != out.shape[1]:
            raise _fail(where, f"{key}[{i}]", f"has {len(row)} entries, row 0 has "
                                               f"{out.shape[1]}")
        for j, x in enumerate(row):
            try:
                number = (parse_real(x) if isinstance(x, str) else  # YAML text, or the API's
                          float(x) if isinstance(x, (int, float)) and not isinstance(x, bool)
                          else None)
            except OverflowError:
                number = np.inf  # an int beyond float64: refused below as non-finite
            if number is None:
                raise _fail(where, f"{key}[{i}][{j}]", f"is not a number: {str(x)[:40]!r}")
            out[i, j] = number
    if not np.all(np.isfinite(out)):
        raise _fail(where, key, "has a non-finite entry")
    return out


def _array(value: Any, where: str, key: str, sparse_ok: bool):
    """A numpy array or scipy sparse matrix given through the API: real, square, finite."""
    sparse = hasattr(value, "tocsr")
    if sparse and not sparse_ok:
        value = value.toarray()
        sparse = False
    data = value.data if sparse else value
    if np.asarray(data).dtype.kind not in "iuf":
        raise _fail(where, key, f"must hold real numbers, got dtype {np.asarray(data).dtype}")
    if value.ndim != 2 or value.shape[0] != value.shape[1] or value.shape[0] == 0:
        raise _fail(where, key, f"must be a non-empty square matrix, got shape {value.shape}")
    out = value.tocsr().astype(float) if sparse else np.array(value, dtype=float)
    if not np.all(np.isfinite(out.data if sparse else out)):
        raise _fail(where, key, "has a non-finite entry")
    return out


def _float(value: Any, where: str, key: str) -> float:
    return number(value, where, f"system.{key}")


def analyse_system(tree: Any, where: str, folder: Path, method: Method,
                   zmax: float = 10.0, progress: Callable[[float], None] | None = None,
                   deadline: float | None = None, time_unit: str | None = None
                   ) -> SystemReport:
    """Read a ``system:`` mapping and decide the analysis for ``method`` (``progress`` and
    ``deadline``: see :func:`stepsafe.systems.coupled.coupled_safe_steps`; ``time_unit``:
    the scene's, which a stiffness given with ``units:`` is converted to)."""
    if not isinstance(tree, dict):
        raise _fail(where, "", "must be a mapping (stiffness/mass, hessian or hamiltonian)")
    if "openmm" in tree:
        return _md_system(tree, where, folder, time_unit, progress, method)
    if "potential" in tree:
        raise _fail(where, "potential", "a potential (U = -log pi) is a target for HMC: "
                                        "stepsafe hmc SCENE --steps L; advise and check "
                                        "analyse a hamiltonian:")
    unknown = set(tree) - SYSTEM_KEYS
    if unknown:
        key = sorted(unknown)[0]
        raise _fail(where, key, unknown_key(key, sorted(SYSTEM_KEYS)))
    kinds = [k for k in ("stiffness", "precision", "covariance", "hessian", "hamiltonian")
             if k in tree]
    if len(kinds) != 1:
        raise _fail(where, "", "give exactly one of stiffness, precision or covariance (each "
                               "with an optional mass), hessian or hamiltonian")
    all_modes = False
    if "all_modes" in tree:
        flag = str(tree["all_modes"]).lower()
        if kinds[0] not in ("stiffness", "precision") or flag not in ("true", "false"):
            raise _fail(where, "all_modes", "must be true or false, beside a stiffness or "
                                            f"precision, got {tree['all_modes']!r}")
        all_modes = flag == "true"
    if "units" in tree and kinds[0] != "stiffness":
        raise _fail(where, "units", f"units: go with a stiffness (and mass), not with "
                                    f"{kinds[0]}")
    if "mass" in tree and kinds[0] not in ("stiffness", "precision", "covariance"):
        raise _fail(where, "mass", f"a mass goes with a stiffness, precision or covariance, "
                                   f"not with {kinds[0]} (it would be ignored)")
    try:
        if kinds[0] in ("stiffness", "precision"):
            report = _stiffness(tree, where, folder, kinds[0], all_modes, time_unit)
        elif kinds[0] == "covariance":
            report = _covariance(tree, where, folder)
        elif kinds[0] == "hessian":
            report = _hessian(tree, where, folder, method, zmax, progress, deadline)
        else:
            report = _hamiltonian(tree, where, method, zmax, deadline)
        return report._replace(source=f"{where}::$.system.{kinds[0]}", tree=tree)
    except _E as exc:
        if exc.where:
            raise
        # a MatrixError names the matrix at fault (mass errors under $.system.mass)
        key = getattr(exc, "key", None)
        raise _fail(where, key if isinstance(key, str) and key in tree else kinds[0],
                    exc.message) from None


#: What each stage of an MD system's analysis counts, as a progress bar labels it.
MD_STAGES = {"minimize": "minimising (OpenMM's L-BFGS iterations)",
             "step control": "difference step control (trial steps)",
             "hessian": "dense Hessian (force-difference columns)",
             "products": "Lanczos iterations (Hessian-vector products)"}


def _md_system(tree: dict, where: str, folder: Path, time_unit: str | None,
               progress: Callable[[float], None] | None = None,
               method: Method | None = None) -> SystemReport:
    """An MD engine's system (``system: {openmm:, positions:, ...}``,
    :mod:`stepsafe.systems.md.system`): its instantaneous normal modes as vibrations
    (omega^2 > its error), barriers (omega^2 < -its error) or undecided (both, at the rate
    the error allows), in rad per ``time_unit`` (ps, OpenMM's, when the scene names none);
    the fastest modes carry the atoms that move in them. A ``method`` analysed on
    vibrations only (a Langevin splitting) takes the undecided modes as vibrations (their
    barrier half is the rigid-body motion rounding leaves near 0) and refuses a
    configuration with a barrier beyond rounding (not a minimum)."""
    def fail(key: str, message: str) -> StepsafeError:
        return _fail(where, key, message)

    def tick(stage: str, done: int, total: int | None) -> None:
        # a callback with a stage(label, done, total) attribute (the command line's bar)
        # is told what is counted, also without a total (Lanczos); others get fractions
        named = getattr(progress, "stage", None)
        if named is not None:
            named(MD_STAGES.get(stage, stage), done, total)
        elif progress is not None and total:
            progress(done / total)

    chosen = md.settings(tree, fail)
    engine = md.load_engine(tree["openmm"], tree.get("positions"), folder, fail)
    engine, repartitioned, minimization = md.prepare(engine, chosen, fail, progress=tick)
    result = md.analyse(engine, chosen, repartitioned, minimization, progress=tick)
    unit = time_unit or "ps"
    scale = float(TIME_UNITS[unit] / TIME_UNITS["ps"])  # rad/ps -> rad per unit
    lam = result.spectrum.eigenvalues * scale ** 2
    err = md.eigenvalue_errors(result) * scale ** 2
    modes: list[LinearMode] = []
    sources: list[int] = []
    for i, (value, e) in enumerate(zip(lam.tolist(), err.tolist())):
        if abs(value) <= e:
            top = float(np.sqrt(e))
            modes += [LinearMode(top, "oscillator", complex(value), False, 1.0),
                      LinearMode(top, "inverted", complex(value), False, 1.0)]
            sources += [i, i]
            continue
        rel = 0.5 * e / abs(value) + 2 * EPS
        modes.append(LinearMode(float(np.sqrt(abs(value))),
                                "oscillator" if value > 0 else "inverted", complex(value),
                                True, rel))
        sources.append(i)
    models = getattr(method, "models", ("oscillator", "inverted"))
    if "inverted" not in models:
        barriers = sum(1 for m in modes if m.decided and m.model == "inverted")
        if barriers:
            raise _fail(where, "openmm", f"the configuration has {barriers} barrier mode(s) "
                                         "(omega^2 < 0 beyond its error) and "
                                         f"{getattr(method, 'name', 'the method')} is "
                                         "analysed on vibrations only: minimise it first "
                                         "(minimize: true)")
        kept = [(m, i) for m, i in zip(modes, sources) if m.model != "inverted"]
        modes, sources = [m for m, _ in kept], [i for _, i in kept]
    notes = _md_notes(result, unit, time_unit is None)
    if "inverted" not in models:
        notes.append(f"{getattr(method, 'name', 'the method')} is analysed on vibrations "
                     "only: the modes within rounding of omega^2 = 0 are taken as "
                     "vibrations")
    if not result.complete:  # every other eigenvalue lies within +- the last modulus found
        # (an upper bound already: the rates lie anywhere in [0, top], nothing above)
        bound = float(np.min(np.abs(lam) + err))
        top = float(np.sqrt(bound))
        modes.append(LinearMode(top, "oscillator", complex(bound), False, 2 * EPS))
        sources.append(-1)
        if "inverted" in models:
            modes.append(LinearMode(top, "inverted", complex(-bound), False, 2 * EPS))
            sources.append(-1)
    report = _report_modes(tuple(modes), _md_analysis(result), notes,
                           primary_only=not result.complete)._replace(tree=tree, md=result)
    if chosen.runs is not None:
        report = report._replace(engine_check=lambda name, h: md.engine_check(
            result, name, h * scale))
    raw = result.spectrum.eigenvalues
    raw_err = md.eigenvalue_errors(result)
    for item, i in zip(report.items, sources):
        if i < 0:
            item["type"] = "bound"
            item["note"] = "every mode not computed has |omega^2| below this"
            continue
        # the eigenvalue in the engine's units and the error allowed it (rad^2/ps^2)
        item["omega_squared"], item["omega_squared_error"] = float(raw[i]), float(raw_err[i])
        if i < len(result.fastest):
            mode = result.fastest[i]
            item["wavenumber"] = mode.wavenumber
            item["atoms"] = [[label or str(index), share] for index, label, share in mode.atoms]
    return report


def _md_analysis(result: Any) -> str:
    sp = result.spectrum
    free = 3 * result.n_moving - sp.removed - result.rigid
    if result.complete:
        rigid = (f", less its {result.rigid} rigid-body motions" if result.rigid else "")
        return (f"instantaneous normal modes of an OpenMM system: all {free} modes of a "
                f"dense Hessian ({result.n_moving} moving atoms{rigid})")
    found = "the one" if len(sp.eigenvalues) == 1 else f"the {len(sp.eigenvalues)}"
    return (f"instantaneous normal modes of an OpenMM system: {found} of "
            f"largest |omega^2| of {free} by Lanczos on Hessian-vector products "
            f"({result.n_moving} moving atoms, {sp.products} products); islands not analysed")


def _md_notes(result: Any, unit: str, implied: bool) -> list[str]:
    """What was done to the system, in the words a user checks."""
    chosen = result.settings
    notes = []
    rule = "" if chosen.constraints in (None, "none") else \
        f" (the System's own and the rule {chosen.constraints})"
    notes.append(f"{result.n_particles} particles, {result.n_moving} moving, "
                 f"{result.n_constraints} distance constraints{rule}: the modes are those on "
                 "the constraints' tangent space (mass metric)" if result.n_constraints else
                 f"{result.n_particles} particles, {result.n_moving} moving, no constraints")
    if result.repartition is not None:
        r = result.repartition
        notes.append(f"hydrogen mass {r.hydrogen_mass:g} amu on {len(r.hydrogens)} hydrogens, "
                     "taken from their bonded heavy atoms (OpenMM's hydrogenMass rule)")
    m = result.minimization
    if m is not None:
        notes.append(f"minimised (OpenMM LocalEnergyMinimizer on its CPU platform, RMS force "
                     f"tolerance "
                     f"{m.tolerance:g} kJ/mol/nm): energy {m.energy_before:.6g} -> "
                     f"{m.energy_after:.6g} kJ/mol, RMS force {result.rms_force:.3g} kJ/mol/nm")
    else:
        notes.append(f"not minimised: the modes of the configuration given (RMS force "
                     f"{result.rms_force:.3g} kJ/mol/nm); minimize: true minimises first")
    sp = result.spectrum
    bound = f", eigenvalue error bound {sp.bound:.2g} rad^2/ps^2" if result.complete else ""
    notes.append(f"Hessian by central differences of OpenMM's Reference-platform forces: step "
                 f"{result.step:.2g} nm, relative error estimate {result.relative_error:.1g}, "
                 f"{result.force_calls} force evaluations{bound}")
    notes.append("a verdict is the linear stability at this configuration (0 K at a "
                 "minimum); at 300 K OpenMM's own runs blew up or drifted from about 0.8 to "
                 "0.95 of this limit (README: engine validation): a temperature (with the "
                 "run's length) measures the limit there in OpenMM")
    if implied:
        notes.append("frequencies in rad/ps (OpenMM's time unit): time_unit: fs gives steps "
                     "in fs")
    if chosen.runs is not None:
        runs = chosen.runs
        notes.append(f"runs: check also runs the method in OpenMM at the step, "
                     f"{len(runs.seeds)} seeds ({', '.join(map(str, runs.seeds))}) of "
                     f"{runs.duration:g} ps from states thermalised at {runs.temperature:g} K")
    return notes


def _report_modes(modes, analysis: str, notes: list[str],
                  primary_only: bool = False) -> SystemReport:
    items = [{"type": {"oscillator": "elliptic", "inverted": "hyperbolic",
                       "saddle": "hyperbolic", "saddle-p": "hyperbolic",
                       "free": "free"}[m.model] if m.decided else "undecided",
              "model": m.model, "beta": m.beta} for m in modes]
    if not all(m.decided for m in modes):
        notes.append("eigenvalues within rounding of 0 have no decided type: each is "
                     "analysed both as a vibration and as a barrier at the largest rate "
                     "rounding allows")
    grouped: dict[str, list[float]] = {}
    errors: dict[str, list[float]] = {}
    for m in modes:
        if m.model != "free":
            grouped.setdefault(m.model, []).append(m.beta)
            errors.setdefault(m.model, []).append(m.rel_error)
    if not grouped:
        notes.append("every mode is free (beta = 0): no limit on h")
        grouped, errors = {"oscillator": [0.0]}, {"oscillator": [0.0]}
    return SystemReport(analysis, items, Modes.from_arrays(
        {k: np.array(v) for k, v in grouped.items()},
        {k: np.array(v) for k, v in errors.items()}), [], notes, primary_only)


def _covariance(tree, where, folder) -> SystemReport:
    """A Gaussian target for HMC given by its covariance (and a mass matrix, the
    preconditioner): the frequencies are ``1/sqrt(mu)`` for the eigenvalues ``mu`` of
    ``L^T Sigma L`` (``M = L L^T``), i.e. those of the precision ``Sigma^-1`` against M."""
    C = _matrix(tree["covariance"], where, "covariance", folder, sparse_ok=True)
    if hasattr(C, "toarray"):
        if C.shape[0] > DENSE_LIMIT:
            raise _fail(where, "covariance", f"a {C.shape[0]}-dimensional covariance is "
                                             "analysed densely: give its (sparse) precision "
                                             "instead")
        C = C.toarray()
    M = _matrix(tree["mass"], where, "mass", folder) if "mass" in tree else None
    if C.shape[0] > DENSE_LIMIT:
        raise _fail(where, "covariance", f"a {C.shape[0]}-dimensional dense covariance is "
                                         f"larger than {DENSE_LIMIT}: give its precision")
    d = gaussian_modes(C, M)
    return _report_modes(d.modes, d.analysis, [])


def units_scale(tree: dict, where: str, time_unit: str | None) -> float | None:
    """The factor a stiffness given with ``units: {energy:, length:, mass:}`` is multiplied
    by so that its frequencies (against the mass) are in rad per ``time_unit``
    (:func:`stepsafe.units.stiffness_scale`); None without ``units:``."""
    if "units" not in tree:
        return None
    units = tree["units"]
    table = {"energy": ENERGY_UNITS, "length": LENGTH_UNITS, "mass": MASS_UNITS}
    if not isinstance(units, dict) or set(units) != set(table):
        raise _fail(where, "units", "must be a mapping {energy:, length:, mass:}, e.g. "
                                    "{energy: kcal/mol, length: angstrom, mass: amu}")
    for part, known in table.items():
        if units[part] not in known:
            raise _fail(where, f"units.{part}", f"must be one of {', '.join(known)}, got "
                                                f"{units[part]!r}")
    if time_unit is None:
        raise _fail(where, "units", "give the scene's time_unit: (or --time-unit): the "
                                    "frequencies of K and M in these units are per it")
    return float(stiffness_scale(units["energy"], units["length"], units["mass"], time_unit))


def _stiffness(tree, where, folder, key: str = "stiffness", all_modes: bool = False,
               time_unit: str | None = None) -> SystemReport:
    K = _matrix(tree[key], where, key, folder, sparse_ok=True)
    scale = units_scale(tree, where, time_unit)
    if scale is not None:
        with np.errstate(over="ignore"):
            K = K * scale
        if not np.all(np.isfinite(K.data if hasattr(K, "tocsr") else K)):
            raise _fail(where, key, "overflows in rad per time unit (units:)")
        units = tree["units"]
        notes = [f"K in {units['energy']}/{units['length']}^2 against M in {units['mass']}: "
                 f"frequencies in rad/{time_unit}"]
    else:
        notes = []
    M = _matrix(tree["mass"], where, "mass", folder, sparse_ok=True) if "mass" in tree else None
    if M is not None and K.shape[0] == K.shape[1] and M.shape != K.shape:
        # before any dense copy of a sparse mass
        raise _fail(where, "mass", f"mass is {'x'.join(map(str, M.shape))} but stiffness is "
                                   f"{'x'.join(map(str, K.shape))}")
    sparse = hasattr(K, "tocsr")
    if K.shape[0] > DENSE_LIMIT and not all_modes and \
            (sparse or M is None or is_diagonal(M)):
        d = sparse_extreme_modes(K, M)
        notes.append(f"{K.shape[0]} dof{' sparse' if sparse else ''}: only the extreme modes "
                     "were computed; islands beyond h_max are not analysed (all_modes: true "
                     "analyses them)")
    else:
        if K.shape[0] > 4 * DENSE_LIMIT:
            raise StepsafeError(f"a dense {K.shape[0]} x {K.shape[0]} stiffness is too large"
                                + ("" if sparse else "; save it as a sparse .npz or .mtx")
                                + (f" (all_modes: up to {4 * DENSE_LIMIT} rows)"
                                   if all_modes else ""))
        K = K.toarray() if hasattr(K, "toarray") else K
        M = M.toarray() if M is not None and hasattr(M, "toarray") else M
        d = separable_modes(K, M)
    return _report_modes(d.modes, d.analysis, notes, d.extremes_only)


def _hessian(tree, where, folder, method, zmax, progress=None, deadline=None
             ) -> SystemReport:
    S = check_square(_matrix(tree["hessian"], where, "hessian", folder), "hessian")
    if S.shape[0] > 2 * DENSE_LIMIT:
        raise StepsafeError(f"a {S.shape[0]} x {S.shape[0]} Hessian is too large")
    if not np.any(S):
        raise StepsafeError("the Hessian is zero: H has no linear model, nothing to analyse "
                            "(a step cannot be certified for it)")
    d = hessian_modes(S, method)
    if d is not None:
        return _report_modes(d.modes, d.analysis, [])
    result = coupled_safe_steps(method, S, zmax, progress, deadline)
    items = [_with_undecided({"type": "coupled", "dof": S.shape[0] // 2,
                              "h_limit": result.h_max}, result)]
    return SystemReport(result.analysis, items, None, [(result, S)], [
        "the modes do not decouple for this method (partitioned method, non-separable H, "
        "or loxodromic modes): h_max comes from the full one-step matrix; islands beyond it "
        "are not analysed", *_undecided_notes([(result, S)])])


def _hamiltonian(tree, where, method, zmax, deadline=None) -> SystemReport:
    if "q" in tree or "p" in tree:
        return _hamiltonian_many(tree, where, method, zmax, deadline)
    for key in ("energy_below", "sizes", "fixed"):
        if key in tree:
            raise _fail(where, key, "applies to Hamiltonians with named variables (q: and "
                                    "p: lists)")
    grid = GRID
    if "starts" in tree:  # a square grid of at least that many
        grid = math.isqrt(_starts(tree, where) - 1) + 1
    text = tree["hamiltonian"]
    if not isinstance(text, str):
        raise _fail(where, "hamiltonian", "must be an expression in q and p")
    params_tree = tree.get("parameters", {})
    if not isinstance(params_tree, dict):
        raise _fail(where, "parameters", "must be a mapping of names to numbers")
    params = {k: _float(v, where, f"parameters.{k}") for k, v in params_tree.items()}
    box = tree.get("box")
    if not isinstance(box, dict) or set(box) != {"q", "p"}:
        raise _fail(where, "box", "must be {q: [lo, hi], p: [lo, hi]}")
    bounds = []
    for axis in ("q", "p"):
        pair = box[axis]
        if not isinstance(pair, list) or len(pair) != 2:
            raise _fail(where, f"box.{axis}", "must be [lo, hi]")
        bounds.append((_float(pair[0], where, f"box.{axis}[0]"),
                       _float(pair[1], where, f"box.{axis}[1]")))
    try:
        H = parse_hamiltonian(text, params)
        _force_gradient_needs_separable(method, separable_terms(H.expression.tree), where)
        search = find_equilibria(H, bounds[0], bounds[1], grid)
    except ExpressionError as exc:
        raise _fail(where, "hamiltonian", f"{exc} in {text[:60]!r}") from None
    equilibria = search.equilibria
    if not equilibria:
        raise _fail(where, "box", f"no equilibrium of H found in the box ({search.explain()})")
    if all(e.model is None for e in equilibria):
        where_ = ", ".join(f"({e.q:.6g}, {e.p:.6g})" for e in equilibria[:3])
        raise _fail(where, "hamiltonian", "nothing to analyse: every equilibrium found is "
                    f"degenerate (no linear model): {where_}"
                    + (" ..." if len(equilibria) > 3 else ""))
    items, notes = [], []
    grouped: dict[str, list[float]] = {}  # per model: the frequencies and their errors
    errors: dict[str, list[float]] = {}
    coupled: list[Any] = []
    for e in equilibria:
        item = {"q": e.q, "p": e.p, "type": e.kind, "D": e.D, "beta": e.beta,
                "model": e.model}
        if e.model is None:
            notes.append(f"degenerate equilibrium at (q, p) = ({e.q:.6g}, {e.p:.6g}): no linear "
                         "model, not analysed")
        elif e.model == "coupled":
            if _analyse_hessian(e.hessian, method, zmax, item, grouped, errors, coupled):
                item["analysis"] = "coupled 2x2 (mixed q-p terms with a partitioned method)"
            else:
                item.pop("analysis")
        else:
            assert e.beta is not None  # (an equilibrium with a test model has its beta)
            grouped.setdefault(e.model, []).append(e.beta)
            errors.setdefault(e.model, []).append(EQUILIBRIUM_ERROR)
        items.append(item)
    modes = Modes.from_arrays({k: np.array(v) for k, v in grouped.items()},
                              {k: np.array(v) for k, v in errors.items()}) if grouped else None
    return SystemReport("equilibria of H found in the box and linearised exactly "
                        "(automatic differentiation)", items, modes, coupled,
                        notes + _undecided_notes(coupled),
                        search=search_record(search))


def search_record(search: Any) -> dict[str, Any]:
    """What the equilibrium search did, JSON-ready: its Newton starts, the walks from the
    equilibria found (:mod:`stepsafe.systems.walks`) and how they ended, the interval
    branch and bound (:mod:`stepsafe.systems.intervals`: ``boxes`` evaluated,
    ``found_by_bound`` equilibria the starts and walks missed), and ``complete``: whether
    the bound proved that every equilibrium in the box was found (``gaps`` says why not;
    ``walk_gaps`` what the starts and walks alone left out)."""
    walks: Walks = search.walks
    certified = search.certified
    return {"starts": search.starts, "walks": walks.followed,
            "walks_to_equilibrium": walks.to_equilibrium,
            "walks_to_boundary": walks.to_boundary,
            "walks_to_singularity": walks.to_singularity,
            "walks_stopped": walks.stopped, "found_by_walks": walks.new,
            "resolution": RESOLUTION,
            "boxes": certified.boxes if certified is not None else 0,
            "found_by_bound": search.found_by_bound,
            "complete": not search.gaps(), "gaps": list(search.gaps()),
            "walk_gaps": list(search.walk_gaps()),
            "caveat": "complete means an interval branch and bound on grad H over the box "
                      "(outward-rounded interval arithmetic, a Krawczyk test proving each "
                      "equilibrium unique in its box) excluded every other part of the box: "
                      "every equilibrium in it was found"}


def read_many(tree, where):
    """The n-dof Hamiltonian of a ``system:`` with ``q:`` and ``p:`` lists and its box."""
    params_tree = tree.get("parameters", {})
    if not isinstance(params_tree, dict):
        raise _fail(where, "parameters", "must be a mapping of names to numbers")
    params = {k: _float(v, where, f"parameters.{k}") for k, v in params_tree.items()}
    if isinstance(tree.get("q"), str) or isinstance(tree.get("p"), str):
        expanded, qs, ps, box = read_indexed(tree, where,
                                             lambda v, key: _float(v, where, key))
        if len(qs) != len(ps):
            raise _fail(where, "p", f"{len(ps)} momenta for {len(qs)} coordinates")
        if len(qs) > MAX_DOF:
            raise _fail(where, "q", f"{len(qs)} degrees of freedom; at most {MAX_DOF}")
        clash = (set(qs) | set(ps)) & set(params)
        if clash:
            raise _fail(where, "parameters", f"{sorted(clash)[0]!r} is also a variable")
        H = ManyDofHamiltonian(str(tree["hamiltonian"]), tuple(qs), tuple(ps), params,
                               expanded)
    else:
        for key in ("sizes", "fixed"):
            if key in tree:
                raise _fail(where, key, "applies to indexed variables (q: \"q[1..N]\")")
        H = parse_many(tree["hamiltonian"], tree.get("q"), tree.get("p"), params, where)
        box = tree.get("box")
    if not isinstance(box, dict):
        raise _fail(where, "box", "must map every variable to [lo, hi]")
    missing = [name for name in H.names if name not in box]
    extra = sorted(set(box) - set(H.names))
    if missing or extra:
        raise _fail(where, "box", f"must give [lo, hi] for exactly the variables "
                                  f"{', '.join(H.names)}"
                    + (f" (missing {missing[0]})" if missing else f" (unknown {extra[0]})"))
    lo, hi = [], []
    for name in H.names:
        pair = box[name]
        if not isinstance(pair, list) or len(pair) != 2:
            raise _fail(where, f"box.{name}", "must be [lo, hi]")
        a, b = (_float(pair[0], where, f"box.{name}[0]"), _float(pair[1], where,
                                                                 f"box.{name}[1]"))
        if not a < b:
            raise _fail(where, f"box.{name}", f"needs lo < hi, got [{a:g}, {b:g}]")
        if not math.isfinite(b - a):
            raise _fail(where, f"box.{name}", "is wider than float64 can hold")
        lo.append(a)
        hi.append(b)
    return H, np.array(lo), np.array(hi)


def _hamiltonian_many(tree, where, method, zmax, deadline=None) -> SystemReport:
    """Equilibria of an n-dof Hamiltonian, each linearised exactly and analysed: decoupled
    where its Hessian separates for this method, the coupled analysis otherwise."""
    H, lo, hi = read_many(tree, where)
    _force_gradient_needs_separable(method, H.separable, where)
    starts = _starts(tree, where) if "starts" in tree else None
    below = _float(tree["energy_below"], where, "energy_below") if "energy_below" in tree \
        else None
    search = find_many(H, lo, hi, starts, deadline)
    if search.stopped is not None:
        raise _fail(where, "starts", f"the equilibrium search stopped at the time budget after "
                                     f"{search.stopped} of {search.starts} starts: an "
                                     "equilibrium may be missing (a larger --budget, or fewer "
                                     "starts:)")
    if not search.equilibria:
        raise _fail(where, "box", f"no equilibrium of H found in the box ({search.explain()})")
    items, notes = [], []
    grouped: dict[str, list[float]] = {}  # per model: the frequencies and their errors
    errors: dict[str, list[float]] = {}
    coupled: list[Any] = []
    reached = [e for e in search.equilibria if below is None or e.energy < below]
    for e in search.equilibria:
        if below is not None and not e.energy < below:
            notes.append(f"equilibrium at {_point(H, e.x)} has energy {e.energy:.6g}, not "
                         f"below {below:g}: not reached, not analysed")
    if not reached:
        raise _fail(where, "energy_below", f"no equilibrium has energy below {below:g} (the "
                                           f"lowest: {search.equilibria[0].energy:.6g})")
    family = next((e for e in reached if e.family), None)
    if family is not None:
        raise _fail(where, "hamiltonian", f"the equilibria form a family (a line or ring "
                                          f"through {_point(H, family.x)} along a zero mode): "
                                          "only isolated equilibria are analysed, and the "
                                          "family's members across the box may set other "
                                          "limits; remove the symmetry (fix a coordinate, "
                                          "or use relative coordinates)")
    for e in reached:
        item = {"x": [float(v) for v in e.x], "names": list(H.names), "type": e.kind,
                "index": e.index, "energy": e.energy, "frequencies": list(e.frequencies),
                "rates": list(e.rates), "model": None}
        if e.kind == "degenerate":
            notes.append(f"equilibrium at {_point(H, e.x)} is degenerate (a zero mode, "
                         "isolated: no family continues along it), which sets no step limit; "
                         "its other modes are analysed")
        if _analyse_hessian(e.hessian, method, zmax, item, grouped, errors, coupled):
            item["model"] = "coupled"
            item["analysis"] = f"coupled {2 * len(H.q)}x{2 * len(H.q)}"
        items.append(item)
    modes = Modes.from_arrays({k: np.array(v) for k, v in grouped.items()},
                              {k: np.array(v) for k, v in errors.items()}) if grouped else None
    return SystemReport(f"{len(search.equilibria)} equilibria of H found in the box "
                        f"({search.explain()}), linearised exactly (automatic "
                        "differentiation)", items, modes, coupled,
                        notes + _undecided_notes(coupled),
                        search=search_record(search))


def _starts(tree: dict, where: str) -> int:
    """``starts:``, the number of Newton starts: a whole number up to
    :data:`stepsafe.systems.manydof.MAX_STARTS`."""
    starts = _float(tree["starts"], where, "starts")
    if starts != int(starts) or not 1 <= starts <= MAX_STARTS:
        raise _fail(where, "starts", f"must be a whole number from 1 to {MAX_STARTS}")
    return int(starts)


def _force_gradient_needs_separable(method, separable: bool, where: str) -> None:
    """A force-gradient method is defined only for ``H = p^T M^-1 p / 2 + V(q)``: refuse a
    Hamiltonian with a term in both coordinates and momenta (its linearisation at an
    equilibrium may separate, but the method cannot be run on H)."""
    if method is not None and method.force_gradient and not separable:
        raise _fail(where, "hamiltonian", f"{method.name} is a force-gradient method: it needs "
                                          "a separable H = T(p) + V(q), and this H has a term "
                                          "in both coordinates and momenta")


def _analyse_hessian(S, method, zmax, item, grouped, errors, coupled) -> bool:
    """An equilibrium's exact linearisation ``S``: its decoupled modes added to
    ``grouped``/``errors`` (the item's ``model`` lists their models, ``analysis`` how), or
    the coupled analysis appended to ``coupled`` (the item's ``h_limit``); True if coupled."""
    d = hessian_modes(S, method)
    if d is None:
        result = coupled_safe_steps(method, S, zmax)
        coupled.append((result, S))
        item["h_limit"] = result.h_max
        _with_undecided(item, result)
        return True
    for m in d.modes:
        if m.model != "free":
            grouped.setdefault(m.model, []).append(m.beta)
            errors.setdefault(m.model, []).append(m.rel_error + EQUILIBRIUM_ERROR)
    item["model"] = ",".join(sorted({m.model for m in d.modes}))
    item["analysis"] = d.analysis
    return False


def _with_undecided(item: dict[str, Any], result) -> dict[str, Any]:
    """The item with ``h_undecided_to`` when float64 left the coupled boundary open."""
    if result.undecided_to is not None:
        item["h_undecided_to"] = result.undecided_to
    return item


def _undecided_notes(coupled: list[Any]) -> list[str]:
    """One note per coupled analysis whose boundary float64 could not place."""
    notes = []
    for result, S in coupled:
        if result.undecided_to is None:
            continue
        low, high = result.h_max, result.undecided_to
        certified = f"steps below {low:.6g} are certified" if low > 0 else "no step is certified"
        lost = (f"the structure is lost at {high:.6g}" if high < result.horizon else
                f"no loss is certain up to the horizon {high:.6g}")
        notes.append(f"float64 cannot decide the coupled {S.shape[0]}x{S.shape[0]} analysis for "
                     f"h in ({low:.6g}, {high:.6g}): S is too ill-conditioned for float64 "
                     "there (the rounding bound of the criterion reaches its margin), and "
                     "the high-precision "
                     f"criterion applies only to a splitting method on at most {EXACT_SIZE} "
                     f"rows whose S is definite at 40 digits; {certified}, {lost}")
    return notes


def _point(H, x) -> str:
    return "(" + ", ".join(f"{n} = {v:.6g}" for n, v in zip(H.names, x)) + ")"
