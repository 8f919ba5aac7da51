"""Small-matrix kernels written for batched use under jit: Jacobi eigh / SVD, Cholesky, 2x2 eigh,
reductions, and the matmul precision every entry point traces with (`precision`).
"""
