"""The numeric core: transfer matrices M(z) of any method on the linear test models, the
regions of z = beta*h where an equilibrium keeps its structure, the step advice built on them,
and accuracy. Knows nothing of files or the terminal."""
