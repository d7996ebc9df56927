"""The numpydoc entries of keywords that several public functions take, written once.

A docstring's Parameters section names a block by a line holding only
``<keywords: NAME>`` (indented as the entries around it). :func:`shared_keywords` puts the
block in its place when the function is defined, so ``help()`` shows every parameter;
the documentation site reads docstrings from the source instead of importing them, and
its griffe extension (``docs/hooks/shared_keywords.py``) calls :func:`expand` there, so
the API reference shows them too.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import TypeVar

#: The problem's frequencies, in every form, and the unit of steps (``problem``,
#: ``advise``, ``check``, ``check_scenes``, ``compare``).
FREQUENCIES = """\
beta : array_like, optional
    Angular frequencies of vibrations, rad per time unit.
saddle_beta, inverted_beta : array_like, optional
    Rates of saddles (H = beta p q) and of barrier tops (p' = +beta^2 q), rad per time
    unit.
modes : mapping, optional
    ``{model: betas}``, rad per time unit (models as in :func:`region`).
ordinary_frequency : number, text or list, optional
    f = beta / (2 pi) of vibrations: cycles per time unit, or texts with a frequency
    unit (``"100 THz"``, ``"3 ps-1"``).
wavenumber : number, text or list, optional
    Vibrations in cm^-1 (``3700`` or ``"3700 cm-1"``); needs a time unit.
period : number, text or list, optional
    T = 2 pi / beta of vibrations: in the time unit, or texts with a time unit
    (``"9 fs"``).
sigma : array_like, optional
    Standard deviations of a Gaussian target (HMC, unit mass), in the units of q:
    beta = 1 / sigma.
time_unit : str, optional
    The unit of every step in and out (``"fs"``, ``"ps"``, ...; see
    :data:`stepsafe.units.TIME_UNITS`). Default: the scene's, else the unit that the
    texts of steps and periods name, else the time unit of 1/beta."""

#: The modes' names, a system instead of frequencies, the method's family, and how far
#: and how long the analysis looks (``problem``, ``advise``, ``check``, ``check_scenes``).
ANALYSIS = """\
labels : mapping, optional
    Names of the modes given by keyword, per model.
system : mapping, optional
    A system instead of frequencies: ``{"stiffness": K, "mass": M}``,
    ``{"precision": P}`` or ``{"covariance": C}`` with an optional mass,
    ``{"hessian": H}``, or a scene's ``system:`` (a Hamiltonian).
stages, base : int, str, optional
    A family's stage count; a composition's base.
margin : float, optional
    F in (0, 1]: every frequency may be up to 1/F times larger (default: the scene's,
    else 1).
zmax : float, optional
    How far in z = beta*h (dimensionless) to analyse (default: the scene's, else 10).
budget : float, optional
    Seconds after which a coupled analysis stops (steps above the h reached are then
    not analysed)."""

#: An OpenMM system and how it is prepared (``problem``, ``advise``, ``check``).
OPENMM = """\
openmm_system : openmm.System or str, optional
    An OpenMM System (or its ``XmlSerializer`` file) whose instantaneous normal modes
    are analysed, with ``positions`` (``pip install 'stepsafe[openmm]'``;
    :mod:`stepsafe.systems.md.system`); as a scene's ``system: {openmm:, positions:}``.
positions : array_like or str, optional
    With ``openmm_system``: (N, 3) positions in nm (or an OpenMM Quantity), or a
    ``.pdb``/``.cif``/State ``.xml`` file.
constraints : {"none", "h-bonds", "all-bonds", "h-angles"}, optional
    Distance constraints added to an OpenMM system's own by OpenMM's ``createSystem``
    rule (needs a PDB or PDBx structure).
hydrogen_mass : float or str, optional
    Hydrogen mass repartitioning of an OpenMM system, amu (``3`` or ``"3 amu"``).
minimize : bool, optional
    Minimise an OpenMM system's energy before the analysis (default: the scene's, else
    no)."""

#: A scene file, or a problem built beforehand (``advise``, ``check``).
SCENE = """\
scene : str, Path or Scene, optional
    A scene file (``stepsafe schema scene``) or a :func:`load_scene` result.
progress : callable, optional
    Called with the fraction done.
problem : Problem, optional
    A :func:`problem` built beforehand, given instead of the method, the frequencies
    and the keywords above."""

#: The system a measurement runs and how (``measure``, ``refine``).
RUN = """\
scene : str or Path, optional
    A scene file whose ``system:`` is run.
system : mapping, optional
    Or the mapping a scene's ``system:`` holds.
time : float or str, optional
    How long each run lasts, in the time unit or as a text with a time unit.
initial : list of float, optional
    The start, q then p.
energy : float, optional
    The start's energy (a 1-dof Hamiltonian's), or an ensemble's energy shell.
time_unit : str, optional
    The unit of steps and times in and out (default: the scene's, else the unit their
    texts name).
solver : str
    How implicit methods solve their stages: ``fixed-point`` or ``newton``."""

#: A Gaussian target's modes (``hmc``, ``design``).
TARGET = """\
beta : array_like, optional
    Angular frequencies of the target's modes, rad per time unit (beta = 1/sigma for
    unit mass).
sigma : array_like, optional
    Standard deviations of the target's modes (unit mass), in the units of q.
saddle_beta, inverted_beta : array_like, optional
    Rates of saddles and barrier tops, rad per time unit (refused: a Gaussian target
    has only vibrations).
modes : mapping, optional
    ``{model: betas}``, rad per time unit.
ordinary_frequency : number, text or list, optional
    f = beta / (2 pi): cycles per time unit, or texts with a frequency unit.
wavenumber : number, text or list, optional
    In cm^-1 (``3700`` or ``"3700 cm-1"``); needs a time unit.
period : number, text or list, optional
    T = 2 pi / beta: in the time unit, or texts with a time unit (``"9 fs"``).
time_unit : str, optional
    The unit of every step and length in and out (``"fs"``, ...); default: the
    scene's, else the unit the texts name, else the time unit of 1/beta.
labels : mapping, optional
    Names of the modes given by keyword, per model.
system : mapping, optional
    ``{"covariance": C}`` or ``{"precision": P}``, with an optional ``"mass"``.
scene : str, Path or Scene, optional
    A scene file (``stepsafe schema scene``) or a :func:`~stepsafe.load_scene` result.
zmax : float, optional
    How far in z = beta*h (dimensionless) each method's region is analysed
    (default: the scene's, else 10).
budget : float, optional
    Seconds after which the analysis of a coupled system stops."""

#: Each block by the name its marker line gives.
BLOCKS = {"frequencies": FREQUENCIES, "analysis": ANALYSIS, "openmm": OPENMM,
          "scene": SCENE, "run": RUN, "target": TARGET}

_MARKER = re.compile(r"( *)<keywords: ([a-z]+)>")

F = TypeVar("F", bound=Callable[..., object])


def expand(doc: str) -> str:
    """``doc`` with each marker line ``<keywords: NAME>`` replaced by the block NAME of
    :data:`BLOCKS`, indented as the marker.

    Parameters
    ----------
    doc : str
        A docstring (as written, or as cleaned by :func:`inspect.cleandoc`).

    Returns
    -------
    str
        The docstring with every block in place (a name not in :data:`BLOCKS` is a
        KeyError: a docstring of the package names a block that does not exist).
    """
    out = []
    for line in doc.split("\n"):
        marker = _MARKER.fullmatch(line)
        if marker is None:
            out.append(line)
            continue
        indent, name = marker.groups()
        out.extend(indent + entry if entry else entry for entry in BLOCKS[name].split("\n"))
    return "\n".join(out)


def shared_keywords(func: F) -> F:
    """Decorate a function whose docstring names blocks of :data:`BLOCKS`: they are put
    in its ``__doc__`` (apply below :func:`stepsafe.arguments.public`, which copies it).

    Parameters
    ----------
    func : callable
        The function.

    Returns
    -------
    callable
        ``func``, its docstring expanded (unchanged where docstrings are stripped).
    """
    if func.__doc__:
        func.__doc__ = expand(func.__doc__)
    return func
