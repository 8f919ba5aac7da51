"""benchmarks/make_report.py: the trace section of BENCHMARKS.md, from a trace JSON made by hand."""

import json
import sys
from pathlib import Path

# benchmarks/ is not a package of the project; make_report renders BENCHMARKS.md.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks import make_report


def test_trace_section_lists_kernels_by_source_with_their_share(tmp_path, monkeypatch):
    by_source = [
        {"source": "compile_optim:_cholesky_solve", "kernels_per_generation": 51.0,
         "us_per_generation": 300.0},
        {"source": "dynamics_rnea:_s_mul", "kernels_per_generation": 10.0,
         "us_per_generation": 100.0},
    ]  # fmt: skip
    trace = {
        "kernels_per_generation": 61.0,
        "busy_us_per_generation": 400.0,
        "span_us_per_generation": 500.0,
        "busy_fraction": 0.8,
        "top_kernels": [{"name": "k", "mean_us": 5.0, "per_generation": 61.0}],
        "by_source": by_source,
    }
    run = {
        "machine": {"platform": "gpu", "device_kind": "H100", "jax": "0.11", "date": "2026-11-25"},
        "conditions": 300,
        "us_per_condition": 2.0,
        "seconds_per_generation": 6e-4,
        "trace": trace,
    }
    (tmp_path / "trace_generation_x.json").write_text(json.dumps(run))
    (tmp_path / "trace_generation_cpu.json").write_text(json.dumps({**run, "trace": None}))
    monkeypatch.setattr(make_report, "RESULTS", tmp_path)
    lines = make_report.trace_section()
    assert "| `compile_optim:_cholesky_solve` | 51 | 300.0 | 75% |" in lines
    assert "| `dynamics_rnea:_s_mul` | 10 | 100.0 | 25% |" in lines
    assert sum("by the project function" in line for line in lines) == 1  # not for the CPU run


def test_machine_line_names_the_cpu_model_where_recorded():
    """Benchmark JSONs record the CPU's model (`dynamics_throughput.cpu_model`, read from
    ``/proc/cpuinfo`` on Linux), and the report's machine line shows it; older records without it
    still render."""
    from benchmarks.dynamics_throughput import cpu_model

    model = cpu_model()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        names = [x.split(":", 1)[1].strip() for x in cpuinfo.read_text().splitlines()
                 if x.startswith("model name")]  # fmt: skip
        assert not names or model == names[0]
    assert model
    m = {"device_kind": "cpu", "cpu_count": 2, "jax": "0.10.2", "date": "2026-11-25T23:48:46"}
    assert make_report._machine(m) == "cpu, 2 CPUs, jax 0.10.2, 2026-11-25"
    m["cpu_model"] = "AMD EPYC"
    assert make_report._machine(m) == "cpu, 2 CPUs, AMD EPYC, jax 0.10.2, 2026-11-25"
