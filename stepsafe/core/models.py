"""The linear test models, scaled so that only ``z = beta*h`` matters
(docs/theory.md#the-test-models).

Each model is ``x' = beta L x`` with ``x = (q, p~)`` (``p~ = p/beta`` for the two
kinetic + potential models). ``L`` is the matrix below:

=============  ==================  ==========================  =========================
model          equations           L                           continuous eigenvalues
=============  ==================  ==========================  =========================
``oscillator`` q' = p, p' = -b^2 q  [[0, 1], [-1, 0]]           +-i beta (elliptic centre)
``saddle``     q' = b q, p' = -b p  [[1, 0], [0, -1]]           +-beta (H = beta p q)
``inverted``   q' = p, p' = +b^2 q  [[0, 1], [1, 0]]            +-beta (barrier top)
``saddle-p``   q' = -b q, p' = b p  [[-1, 0], [0, 1]]           +-beta (H = -beta p q)
=============  ==================  ==========================  =========================

``saddle`` and ``saddle-p`` are not of the form T(p) + V(q); splitting methods reach them
through their PRK form. A partitioned method treats q and p differently, so the saddle that
expands along q and the one that expands along p (``saddle-p``, e.g. the equilibrium (0, 0)
of the paper's Sec. 3 example) have different regions; ``saddle-p`` at z is ``saddle`` at -z.
"""

from __future__ import annotations

import numpy as np

MODELS = ("oscillator", "saddle", "inverted", "saddle-p")
#: The models ``region --model all`` shows (the paper's two and the barrier top).
MAIN_MODELS = ("oscillator", "saddle", "inverted")

#: The scaled generator L of each model, rows (q', p') and columns (q, p).
GENERATORS = {
    "oscillator": np.array([[0.0, 1.0], [-1.0, 0.0]]),
    "saddle": np.array([[1.0, 0.0], [0.0, -1.0]]),
    "inverted": np.array([[0.0, 1.0], [1.0, 0.0]]),
    "saddle-p": np.array([[-1.0, 0.0], [0.0, 1.0]]),
}

#: Type of the continuous equilibrium.
ELLIPTIC = {"oscillator": True, "saddle": False, "inverted": False, "saddle-p": False}

#: Sign of the potential force coefficient seen by a kick: p' = kick_sign * q.
KICK_SIGN = {"oscillator": -1.0, "inverted": 1.0}


def check_model(model: str) -> str:
    """Return ``model`` if it is a known model name, else raise ``ValueError``."""
    if model not in GENERATORS:
        raise ValueError(f"unknown model {model!r}; choose one of {', '.join(MODELS)}")
    return model
