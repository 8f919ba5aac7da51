"""The movement compilers of sec. 2: neighbours (eq. 6) and the PCA basis (`basis`), interpolation
under the boundary conditions (eq. 1-2, `interpolation`) and torque-optimal weights (eq. 3-5,
`optimisation`, on the reduced problems of `problems` and the objective of `search_objective`).
Their settings are in `settings.compiler`.
"""
