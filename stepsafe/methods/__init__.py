"""Method data: the frozen tableaux (RK, PRK, splitting, composition), the Gauss and
Lobatto families, the method-file format and the built-in library (YAML files installed as
``stepsafe.methods.builtin``)."""
