"""Batched solvers of the optimisation compiler (`compile_optim`): a trust-region solver assembled
from a Hessian model and a descent (`base`, `trust_region`, `quasi_newton`, `steps`), optax
wrappers (`first_order`) and chunked batches (`chunking`).
"""
