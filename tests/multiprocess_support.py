"""Forced CPU devices and multi-process JAX runs on one machine, for the tests that start them
(tests/evolution/test_parallel.py, tests/run/test_distributed.py).

XLA fixes the CPU device count when JAX starts, so such runs are subprocesses with
``--xla_force_host_platform_device_count``; several processes join through
``jax.distributed`` (`evolution.sharding.initialize_distributed`) on a free localhost port and
run their collectives over gloo.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CPU_POOL_THREADS = 32  # PJRT_NPROC of the subprocesses (see `cpu_devices_env`)


def cpu_devices_env(devices_per_process: int, x64: bool = False) -> dict:
    """This process's environment for a subprocess that sees ``devices_per_process`` CPU devices
    (float64 with ``x64``), gloo collectives, and this checkout on its path."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices_per_process}"
    ).strip()
    env.update(JAX_PLATFORMS="cpu", JAX_CPU_COLLECTIVES_IMPLEMENTATION="gloo")
    if x64:
        env["JAX_ENABLE_X64"] = "1"
    # XLA:CPU runs a device's ready collectives on its shared thread pool (one thread per core),
    # where they block until every device arrives; with more devices than cores the other
    # devices' work can starve and the step deadlocks now and then. More pool threads avoid it.
    env.setdefault("PJRT_NPROC", str(CPU_POOL_THREADS))
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def process_envs(n_processes: int, devices_per_process: int, x64: bool = False) -> list[dict]:
    """The environments of ``n_processes`` processes of one ``jax.distributed`` run on this
    machine (a plain launch: coordinator on a free localhost port, process count and ids)."""
    with socket.socket() as sock:  # a free port for the coordinator
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    env = cpu_devices_env(devices_per_process, x64)
    env.update(JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}", EVOJAX_NUM_PROCESSES=str(n_processes))
    return [{**env, "EVOJAX_PROCESS_ID": str(i)} for i in range(n_processes)]
