"""benchmarks/make_report.py: BENCHMARKS.md is the current result files rendered, nothing else."""

import json
import sys
from pathlib import Path

import pytest

# benchmarks/ is not a package of the project; make_report renders BENCHMARKS.md.
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import make_report

DATE = "2000-01-02T03:04:05+00:00"  # any ISO time: the report shows its day


def _trace_run(by_source):
    return {
        "machine": {"platform": "gpu", "device_kind": "NVIDIA H100 80GB HBM3", "jax": "0.11",
                    "date": DATE, "command": "python3 benchmarks/trace_generation.py"},
        "conditions": 300,
        "us_per_condition": 2.0,
        "seconds_per_generation": 6e-4,
        "trace": {
            "kernels_per_generation": 61.0,
            "busy_us_per_generation": 400.0,
            "span_us_per_generation": 500.0,
            "by_source": by_source,
        },
    }  # fmt: skip


def test_trace_section_lists_kernels_by_source_with_their_share(tmp_path):
    by_source = [
        {"source": "compile_optim:_cholesky_solve", "kernels_per_generation": 51.0,
         "us_per_generation": 300.0},
        {"source": "dynamics_rnea:_s_mul", "kernels_per_generation": 10.0,
         "us_per_generation": 100.0},
    ]  # fmt: skip
    (tmp_path / "trace_generation_gpu_x.json").write_text(json.dumps(_trace_run(by_source)))
    cpu = {**_trace_run([]), "trace": None}  # a CPU run has no device stream to trace
    cpu["machine"] = {**cpu["machine"], "device_kind": "cpu", "cpu_count": 2}
    (tmp_path / "trace_generation_cpu.json").write_text(json.dumps(cpu))
    src = make_report.Sources(tmp_path)
    lines = make_report.trace_generation(src)
    assert (
        "| `trace_generation_gpu_x.json` | `compile_optim:_cholesky_solve` | 51 | 300.0 | 75% |"
        in lines
    )
    assert "| `trace_generation_gpu_x.json` | `dynamics_rnea:_s_mul` | 10 | 100.0 | 25% |" in lines
    assert "| `trace_generation_cpu.json` | 2 CPUs | 300 | 2.00 | - | - | - |" in lines
    assert "| `trace_generation_gpu_x.json` | H100 | 300 | 2.00 | 61 | 0.40 | 0.50 |" in lines
    assert any(x.startswith("- `trace_generation_gpu_x.json`: H100, jax 0.11, 2000-01-02; `python3")
               for x in lines)  # fmt: skip
    assert src.used == {"trace_generation_gpu_x.json", "trace_generation_cpu.json"}


def test_machine_label_names_the_device_or_the_cpu_model_where_recorded():
    """Benchmark JSONs record the CPU's model (`dynamics_throughput.cpu_model`, read from
    ``/proc/cpuinfo`` on Linux), and the report's machine label shows it; older records without
    it, or without a machine record at all, still render."""
    from benchmarks.dynamics_throughput import cpu_model

    model = cpu_model()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        names = [x.split(":", 1)[1].strip() for x in cpuinfo.read_text().splitlines()
                 if x.startswith("model name")]  # fmt: skip
        assert not names or model == names[0]
    assert model
    m = {"device_kind": "cpu", "cpu_count": 2, "jax": "0.10.2", "date": DATE}
    assert make_report.machine_label(m) == "2 CPUs"
    assert make_report.machine_label({**m, "cpu_model": "AMD EPYC"}) == "2 CPUs, AMD EPYC"
    gpu = {"device_kind": "NVIDIA H200", "device_count": 2, "date": DATE}
    assert make_report.machine_label(gpu) == "2 x H200"
    assert make_report.machine_label({"devices": ["cpu:0"]}) == "CPU"
    assert make_report.machine_label("x86_64") == "CPU (x86_64)"
    assert make_report.date_of(gpu) == "2000-01-02"
    assert make_report.date_of("x86_64") == make_report.NOT_RECORDED


def test_a_result_file_no_section_renders_is_refused(tmp_path):
    """Every file in results/ is current and shown: a stray one (an A/B leftover, a typo in a
    tag) makes the report fail, naming it."""
    (tmp_path / "generations_per_sec_ab.txt").write_text("x")
    with pytest.raises(ValueError, match=r"no section renders generations_per_sec_ab\.txt"):
        make_report.render(tmp_path)


def test_benchmarks_page_is_the_current_result_files_rendered():
    """BENCHMARKS.md is exactly what make_report renders from benchmarks/results/ (no figure
    typed by hand; rerun ``python benchmarks/make_report.py`` after changing a result), every
    file there is rendered, and the page stays within its length."""
    page = make_report.render()
    assert make_report.PAGE.read_text() == page
    assert page.count("\n") <= make_report.MAX_LINES
    names = {p.name for p in make_report.RESULTS.iterdir()}
    assert set(make_report.NOTES) <= names  # every note is about a file that is there
    for name in names - {p for p in names if p.endswith((".md", ".png"))}:
        assert f"`{name}`" in page
