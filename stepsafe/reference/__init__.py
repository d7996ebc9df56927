"""The independent high-precision path: transfer matrices from the stage equations at
mpmath precision (:mod:`.highprec`) and ``--verify`` (:mod:`.verify`), which recomputes every
reported point. Shares no numerics with :mod:`stepsafe.core`."""
