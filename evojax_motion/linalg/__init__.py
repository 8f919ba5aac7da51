"""Small-matrix kernels written for batches under ``vmap`` on accelerators: Jacobi eigen- and
singular value decompositions, an unrolled Cholesky solve, a closed-form 2 x 2 eigensolver and
fusable row reductions. One copy of each, shared by the basis, the compilers and the online query.
"""
