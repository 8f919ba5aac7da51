"""benchmarks/trace_summary.py: a profiler trace's device and host time, on a trace made by hand."""

import gzip
import json
import sys
from pathlib import Path

import pytest

# benchmarks/ is not a package of the project; the summary is what trace_generation.py reports.
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.trace_summary import (
    NO_SOURCE,
    NOT_IN_HLO,
    kernel_sources,
    read_trace,
    summarise_trace,
)

GPU, HOST = 1, 2
COMPUTE, COPY, MAIN = 10, 11, 20


def _meta():
    return [
        {"ph": "M", "name": "process_name", "pid": GPU, "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "name": "process_name", "pid": HOST, "args": {"name": "/host:CPU"}},
        {"ph": "M", "name": "thread_name", "pid": GPU, "tid": COMPUTE,
         "args": {"name": "Stream #14(Compute)"}},
        {"ph": "M", "name": "thread_name", "pid": GPU, "tid": COPY,
         "args": {"name": "Stream #15(MemcpyH2D)"}},
    ]  # fmt: skip


def _x(pid, tid, name, ts, dur):
    return {"ph": "X", "pid": pid, "tid": tid, "name": name, "ts": ts, "dur": dur}


def _trace():
    """Two generations on the compute stream, listed out of order: kernels a (3 x 10 us), b
    (2 x 4 us) and c (1 x 32 us); gaps 2, 50, 1, 5 and 0 us. A copy on another stream (fewer
    events: not the one summarised) and host events."""
    kernels = [
        _x(GPU, COMPUTE, "b", 12, 4),  # gap 2 after a@0
        _x(GPU, COMPUTE, "a", 0, 10),
        _x(GPU, COMPUTE, "c", 66, 32),  # gap 50 after b@12
        _x(GPU, COMPUTE, "a", 99, 10),  # gap 1
        _x(GPU, COMPUTE, "b", 114, 4),  # gap 5
        _x(GPU, COMPUTE, "a", 118, 10),  # gap 0
    ]
    other = [_x(GPU, COPY, "memcpy", 0, 500)]
    host = [
        _x(HOST, MAIN, "cuGraphLaunch", 0, 6),
        _x(HOST, MAIN, "cuGraphLaunch", 50, 6),
        _x(HOST, MAIN, "command_buffer::update", 20, 40),
    ]
    return _meta() + kernels + other + host


def test_device_time_and_gaps_of_the_busiest_stream():
    s = summarise_trace(_trace(), generations=2)
    assert s["stream"] == "Stream #14(Compute)"
    assert s["kernels_per_generation"] == 3.0
    busy, span, idle = 3 * 10 + 2 * 4 + 32, 128, 2 + 50 + 1 + 5 + 0
    assert s["busy_us_per_generation"] == busy / 2
    assert s["span_us_per_generation"] == span / 2
    assert s["idle_us_per_generation"] == idle / 2
    assert busy + idle == span  # the stream's time is kernels or gaps
    assert s["busy_fraction"] == pytest.approx(busy / span, rel=1e-12)
    assert s["largest_gaps"][0] == {"us": 50, "after": "b", "before": "c"}
    assert [g["us"] for g in s["largest_gaps"]] == [50, 5, 2, 1, 0]


def test_kernels_and_host_events_ranked_by_time():
    s = summarise_trace(_trace(), generations=2)
    assert s["top_kernels"] == [
        {"name": "c", "per_generation": 0.5, "mean_us": 32.0},
        {"name": "a", "per_generation": 1.5, "mean_us": 10.0},
        {"name": "b", "per_generation": 1.0, "mean_us": 4.0},
    ]
    assert s["top_host_events"] == [
        {"name": "command_buffer::update", "per_generation": 0.5, "us_per_generation": 20.0},
        {"name": "cuGraphLaunch", "per_generation": 1.0, "us_per_generation": 6.0},
    ]


def test_a_trace_without_device_events_is_refused():
    host_only = [e for e in _trace() if e.get("pid") != GPU]
    with pytest.raises(ValueError, match="no device events"):
        summarise_trace(host_only, generations=1)


def test_read_trace_reads_the_one_gzipped_trace(tmp_path):
    with pytest.raises(FileNotFoundError, match="found 0"):
        read_trace(tmp_path)
    folder = tmp_path / "plugins" / "profile" / "run"
    folder.mkdir(parents=True)
    with gzip.open(folder / "host.trace.json.gz", "wt") as f:
        json.dump({"traceEvents": _trace()}, f)
    assert read_trace(tmp_path) == _trace()


# A compiled program's HLO as `as_text()` prints it, cut down: kernel "a" fuses two instructions
# of `objective` and one of `step`; "b" (deduplicated name of fusion.2) one of a library file
# called from `solve`; "c" has no frame in the package. Frame 3 (objective) has parent 2
# (solve), whose parent 1 is outside the package.
_HLO = """HloModule jit_step

FileNames
1 "/x/site-packages/jax/_src/lax.py"
2 "/repo/evojax_motion/compiler/optimisation.py"
3 "/repo/evojax_motion/evolution/step.py"

FunctionNames
1 "add"
2 "solve"
3 "objective"
4 "step"

FileLocations
1 {file_name_id=1 function_name_id=1 line=5 end_line=5 column=1 end_column=2}
2 {file_name_id=2 function_name_id=2 line=10 end_line=10 column=1 end_column=2}
3 {file_name_id=2 function_name_id=3 line=20 end_line=20 column=1 end_column=2}
4 {file_name_id=3 function_name_id=4 line=30 end_line=30 column=1 end_column=2}

StackFrames
1 {file_location_id=4 parent_frame_id=1}
2 {file_location_id=2 parent_frame_id=1}
3 {file_location_id=3 parent_frame_id=2}
4 {file_location_id=1 parent_frame_id=2}
5 {file_location_id=1 parent_frame_id=5}

%fused_a (p: f32[4]) -> f32[4] {
  %p = f32[4]{0} parameter(0)
  %m = f32[4]{0} multiply(%p, %p), metadata={op_name="mul" stack_frame_id=3}
  %s = f32[4]{0} sine(%m), metadata={op_name="sin" stack_frame_id=3}
  ROOT %n = f32[4]{0} negate(%s), metadata={op_name="neg" stack_frame_id=1}
}

%fused_b (p: f32[4]) -> f32[4] {
  %p = f32[4]{0} parameter(0)
  ROOT %e = f32[4]{0} exponential(%p), metadata={op_name="exp" stack_frame_id=4}
}

%fused_c (p: f32[4]) -> f32[4] {
  %p = f32[4]{0} parameter(0)
  ROOT %e = f32[4]{0} exponential(%p), metadata={op_name="exp" stack_frame_id=5}
}

ENTRY %main (x: f32[4]) -> f32[4] {
  %x = f32[4]{0} parameter(0)
  %loop_a.1 = f32[4]{0} fusion(%x), kind=kLoop, calls=%fused_a, metadata={op_name="a"}
  %fusion.2 = f32[4]{0} fusion(%loop_a.1), kind=kLoop, calls=%fused_b, metadata={deduplicated_name="b"}
  ROOT %c = f32[4]{0} fusion(%fusion.2), kind=kLoop, calls=%fused_c
}
"""  # noqa: E501


def test_kernels_are_traced_to_the_project_function_most_of_their_code_comes_from():
    assert kernel_sources(_HLO) == {
        "loop_a_1": "optimisation:objective",
        "fusion_2": "optimisation:solve",
        "b": "optimisation:solve",
        "c": NO_SOURCE,
    }


def test_kernel_time_by_source():
    kernels = [("loop_a_1", 0, 10), ("b", 10, 4), ("c", 14, 2), ("memcpy", 16, 1)]
    kernels.append(("loop_a_1", 17, 10))
    events = [*_meta(), *(_x(GPU, COMPUTE, *k) for k in kernels)]
    s = summarise_trace(events, generations=2, hlo_text=_HLO)
    keys = ("source", "kernels_per_generation", "us_per_generation")
    rows = [tuple(r[k] for k in keys) for r in s["by_source"]]
    assert rows == [
        ("optimisation:objective", 1.0, 10.0),
        ("optimisation:solve", 0.5, 2.0),
        (NO_SOURCE, 0.5, 1.0),
        (NOT_IN_HLO, 0.5, 0.5),
    ]
    assert "by_source" not in summarise_trace(events, generations=2)


def test_programs_traced_apart_are_summed_and_their_sources_merged():
    """`merge_stages`: kernels and times per generation add up, sources merge across programs
    (each traced to its own HLO, even where both name a kernel alike), each program's summary
    is kept."""
    from benchmarks.trace_summary import merge_stages

    a = [*_meta(), *(_x(GPU, COMPUTE, *k) for k in [("loop_a_1", 0, 10), ("b", 12, 4)])]
    b = [*_meta(), *(_x(GPU, COMPUTE, *k) for k in [("loop_a_1", 0, 6), ("memcpy", 8, 2)])]
    other_hlo = _HLO.replace('3 "objective"', '3 "other"')  # its "loop_a_1" is another kernel
    stages = {
        "prepare": summarise_trace(a, generations=1, hlo_text=_HLO),
        "finish": summarise_trace(b, generations=1, hlo_text=other_hlo),
    }
    m = merge_stages(stages)
    assert m["kernels_per_generation"] == 4
    assert m["busy_us_per_generation"] == 22
    assert m["span_us_per_generation"] == 16 + 10
    assert m["idle_us_per_generation"] == 2 + 2
    rows = {
        r["source"]: (r["kernels_per_generation"], r["us_per_generation"]) for r in m["by_source"]
    }
    assert rows == {"optimisation:objective": (1, 10.0), "optimisation:other": (1, 6.0),
                    "optimisation:solve": (1, 4.0), NOT_IN_HLO: (1, 2.0)}  # fmt: skip
    assert m["stages"] == stages
    assert [(k["name"], k["mean_us"]) for k in m["top_kernels"]] == [
        ("prepare:loop_a_1", 10.0), ("finish:loop_a_1", 6.0), ("prepare:b", 4.0),
        ("finish:memcpy", 2.0),
    ]  # fmt: skip
    assert "by_source" not in merge_stages({"a": summarise_trace(a, generations=1)})
