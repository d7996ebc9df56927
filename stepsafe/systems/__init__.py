"""Whole systems: linear systems (stiffness, mass, Hessian) split into modes or analysed
coupled, nonlinear Hamiltonians and their equilibria, matrix files, and scene files."""
